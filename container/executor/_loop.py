"""The executor's own event loop, which times what each node schedules on it.

A node's loop work outside its callbacks and tasks is handles: a callback
it asks for soon (``call_soon``, ``call_soon_threadsafe``, a future's
done-callback), later (``call_later``, ``call_at``: a ``sleep``'s wake-up,
a timeout), or whenever a file descriptor is ready (``add_reader``, a
socket or serial transport's reads). asyncio copies the current context
into every handle when it is scheduled and runs the handle in it, so the
node it was scheduled by is known then (``_owners.OWNER``); here the
callback is wrapped, at that moment, in a call of the node's meter for
that kind of work (``Meter.call``: two clock reads, as a callback's step,
and no Python frame of its own). A timer handle is late from its due
time; a soon one from when it was scheduled. Which node's handle holds
the loop, the watchdog learns from the meter in step (``Meter.running``,
see ``Accounting.running_on_loop``).

Public methods only, but for one: transports register their readers
through the loop's private ``_add_reader`` (``_compat.FdCallbackLoop``).

Not wrapped: the steps of asyncio tasks (a task's own handles, told by
their ``__self__``: the task factory meters each step of a node's task,
and a lane's runner task carries callbacks that are metered already), and
everything scheduled in the executor's own context
(:data:`~._owners.EXECUTOR`), which costs one ``ContextVar`` read a
handle. Handles of nobody's (scheduled from a thread no node started) are
metered as unattributed.
"""

from __future__ import annotations

import asyncio
import functools
import time
from collections.abc import Callable
from concurrent.futures import Executor
from contextvars import Context
from typing import Any, TypeVar, TypeVarTuple

from .._compat import FdCallbackLoop
from ._engine import HandleMeter
from ._owners import EXECUTOR, OWNER, Account, Owner, executor_work

__all__ = ["AccountedLoop"]

_T = TypeVar("_T")
_Ts = TypeVarTuple("_Ts")

_monotonic_ns = time.monotonic_ns
_Task = asyncio.Task

# asyncio's own methods, called with the meter's call in the callback's place (typed loosely for that).
_call_soon: Callable[..., asyncio.Handle] = asyncio.SelectorEventLoop.call_soon
_call_soon_threadsafe: Callable[..., asyncio.Handle] = asyncio.SelectorEventLoop.call_soon_threadsafe
_call_at: Callable[..., asyncio.TimerHandle] = asyncio.SelectorEventLoop.call_at
_run_in_executor: Callable[..., asyncio.Future[Any]] = asyncio.SelectorEventLoop.run_in_executor


class AccountedLoop(HandleMeter, FdCallbackLoop):
    """A selector event loop that credits each handle to the node that scheduled it.

    ``call_soon`` and ``call_at``, the hottest (every task's wake-up, every
    sleep), are the engine's (``HandleMeter``: in C on the compiled engine);
    the others are here.

    :param unattributed: the owner of work nobody's context names.
    """

    def __init__(self, selector: Any, *, unattributed: Owner) -> None:
        #: Set before the loop's own set-up registers its self-pipe's reader.
        self._unattributed = unattributed
        HandleMeter.__init__(self, OWNER, EXECUTOR, _Task, _call_soon, _call_at, unattributed)
        # The loop's self-pipe reader is the executor's own.
        with executor_work():
            FdCallbackLoop.__init__(self, selector)

    def _account(self, owner: Owner | None, kind: str) -> Account:
        return (owner if owner is not None else self._unattributed).account(kind)

    # The check is written out, not a helper's call: a Python call costs as much as the check.
    def call_soon_threadsafe(
        self, callback: Callable[[*_Ts], object], *args: *_Ts, context: Context | None = None
    ) -> asyncio.Handle:
        owner = OWNER.get() if context is None else context.get(OWNER)
        if owner is EXECUTOR or isinstance(getattr(callback, "__self__", None), _Task):
            return _call_soon_threadsafe(self, callback, *args, context=context)
        call = self._account(owner, "loop_callback").call  # type: ignore[arg-type]
        return _call_soon_threadsafe(self, call, _monotonic_ns(), callback, *args, context=context)

    def fd_callback(
        self, callback: Callable[..., Any], args: tuple[Any, ...]
    ) -> tuple[Callable[..., Any], tuple[Any, ...]]:
        owner = OWNER.get()
        if owner is EXECUTOR:
            return callback, args
        return self._account(owner, "fd").call, (0, callback, *args)  # type: ignore[arg-type]

    def run_in_executor(
        self, executor: Executor | None, func: Callable[[*_Ts], _T], *args: *_Ts
    ) -> asyncio.Future[_T]:
        """Jobs on the loop's default pool are metered as their caller's (its threads are the
        executor's); on a pool of one's own, its threads are whoever started them."""
        if executor is not None:
            started: asyncio.Future[_T] = _run_in_executor(self, executor, func, *args)
            return started
        owner = OWNER.get()
        job: Callable[..., _T] = func
        if owner is not EXECUTOR:
            job = functools.partial(self._account(owner, "thread_call").call, 0, func)  # type: ignore[arg-type]
        with executor_work():  # the pool's threads, if this starts one
            future: asyncio.Future[_T] = _run_in_executor(self, None, job, *args)
        return future
