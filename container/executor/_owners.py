"""Whose work runs: the node each piece of work is credited to, carried in a ``ContextVar``.

A node does more than its callbacks: it starts asyncio tasks, schedules
loop callbacks (``call_soon``, ``call_later``), registers file descriptors
(``add_reader``, a serial transport) and starts threads. Asyncio copies
the current context into everything that runs later (a task at its
creation, a handle when it is scheduled, a reader when it is registered),
so a node's mark in the context that its code runs in follows that work
wherever it goes, with nothing passed by hand: :data:`OWNER`.

The executor sets it once per callback group, in the context every
callback of the group runs in a copy of (its lane's, see ``_lanes``); the
loop (``_loop``) reads it when work is scheduled, the task factory when a
task is made, the thread ledger (``_threads``) when a thread starts. Work
the executor itself schedules runs under :data:`EXECUTOR` (the loop is run
in such a context, see :func:`executor_context`); work scheduled where
nobody set it (another thread's code) is nobody's, and counted as
unattributed, by kind, never as the executor's.

An :class:`Owner` keeps, for one node, an :class:`Account` per kind of
work beside its callbacks: a meter, timed where that work runs.
"""

from __future__ import annotations

import contextlib
import contextvars
import sys
import threading
import weakref
from collections.abc import Callable, Iterator
from typing import Any, Final, TypeAlias

__all__ = [
    "EXECUTOR",
    "KINDS",
    "OWNER",
    "Account",
    "Owner",
    "Whose",
    "executor_context",
    "executor_work",
]


class _Executor:
    """The executor's own work: neither a node's nor unattributed."""

    __slots__ = ()

    def __repr__(self) -> str:
        return "<the executor>"


#: What :data:`OWNER` holds while the executor's own code runs.
EXECUTOR: Final = _Executor()

#: What :data:`OWNER` holds: a node's owner, the executor, or nobody (``None``).
Whose: TypeAlias = "Owner | _Executor | None"

#: The node whose code runs in this context (``None``: unknown, nobody's).
OWNER: contextvars.ContextVar[Whose] = contextvars.ContextVar("container_owner", default=None)

#: Each kind of work beside callbacks: (the group it is shown in, how it is named).
KINDS: Final[dict[str, tuple[str, str]]] = {
    "task": ("asyncio", "asyncio tasks"),
    "loop_callback": ("asyncio", "loop callbacks (call_soon, futures)"),
    "loop_timer": ("asyncio", "loop timers (call_later, sleeps)"),
    "fd": ("asyncio", "file descriptors (readers, transports)"),
    "thread_call": ("threads", "calls on threads (to_thread, pools)"),
    "thread": ("threads", "threads it started"),
}


def executor_context() -> contextvars.Context:
    """A new context where :data:`OWNER` is :data:`EXECUTOR` (and nothing else is set).

    For work the executor schedules from inside a node's code (a poll of
    its own, a future it resolves): without it the node would be credited.
    """
    context = contextvars.Context()
    context.run(OWNER.set, EXECUTOR)
    return context


#: The threads the executor started (in :func:`executor_work`), noted by the thread ledger
#: (``_threads``) from the audit event of each thread's start, or on Python 3.11, which raises
#: none, by :func:`executor_work` itself.
EXECUTOR_THREADS: weakref.WeakSet[threading.Thread] = weakref.WeakSet()
#: Whether this Python tells audit hooks of a thread's start (3.12 and later).
SEES_THREAD_STARTS: Final = sys.version_info >= (3, 12)


@contextlib.contextmanager
def executor_work() -> Iterator[None]:
    """Count what this block starts (threads above all) as the executor's own.

    On Python 3.11 the threads are found by looking: those alive (or
    starting) after the block and not before it. A thread another thread
    started meanwhile would count as the executor's too; there, with no
    thread of a node's told apart, it would count as nobody's otherwise.
    """
    reset = OWNER.set(EXECUTOR)
    before = None if SEES_THREAD_STARTS else frozenset(threading.enumerate())
    try:
        yield
    finally:
        OWNER.reset(reset)
        if before is not None:
            EXECUTOR_THREADS.update(thread for thread in threading.enumerate() if thread not in before)


class Account:
    """One kind of work of one owner: its meter, and its totals across windows."""

    __slots__ = ("call", "cpu_ns_total", "idle", "kind", "meter", "owner", "runs_total")

    def __init__(self, owner: Owner, kind: str, meter: Any) -> None:
        self.owner = owner
        self.kind = kind
        #: The engine's ``Meter``: timed where the work runs.
        self.meter = meter
        #: ``call(arrived, callback, *args)``: ``callback(*args)`` as one run of it
        #: (``Meter.call``, bound once: handles call it).
        self.call: Callable[..., Any] = meter.call
        self.runs_total = 0
        self.cpu_ns_total = 0
        #: Its row of the last window, kept while nothing of it ran (the accounting's).
        self.idle: Any = None

    @property
    def name(self) -> str:
        """How the kind is shown (``asyncio tasks``)."""
        return KINDS[self.kind][1]

    def __repr__(self) -> str:
        return f"<{self.name} of {self.owner.name or 'nobody'}>"


class Owner:
    """One node's work beside its callbacks, by kind (``name`` empty: nobody's).

    :param name: the node's fully qualified name (a node's rows in the
        accounting are by name: an owner made for a node being constructed
        meets its callbacks' rows once it exists).
    :param plugin: whether it is a plugin's node (the watchdog reports
        stalls in plugins' work only).
    :param new_meter: makes a meter (the engine's).
    :param thread_ended: told ``(owner, native thread id, its CPU clock in ns)``
        by each of its threads as it ends (see ``_threads``).
    """

    __slots__ = ("_accounts", "_lock", "_new_meter", "name", "plugin", "thread_ended")

    def __init__(
        self,
        name: str,
        *,
        plugin: bool,
        new_meter: Callable[[], Any],
        thread_ended: Callable[[Owner, int, int], None],
    ) -> None:
        self.name = name
        self.plugin = plugin
        self._new_meter = new_meter
        self.thread_ended = thread_ended
        self._accounts: dict[str, Account] = {}
        self._lock = threading.Lock()

    def account(self, kind: str) -> Account:
        """The account of ``kind`` (one of :data:`KINDS`), made on first use."""
        found = self._accounts.get(kind)  # a dict read is atomic: no lock on the hot path
        if found is not None:
            return found
        with self._lock:
            return self._accounts.setdefault(kind, Account(self, kind, self._new_meter()))

    def accounts(self) -> list[Account]:
        """Every account used so far."""
        with self._lock:
            return list(self._accounts.values())

    def __repr__(self) -> str:
        return f"<Owner {self.name or 'nobody'}>"
