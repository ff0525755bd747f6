"""Which thread is whose, and what each one spent, window by window.

A thread a node's code starts (``threading.Thread``, a pool's workers, a
``threading.Timer``) is the node's. Python tells audit hooks of every
thread start, in the starting thread (``_thread.start_new_thread``; from
3.13 ``_thread.start_joinable_thread``), so one hook reads who starts it
there (:data:`~._owners.OWNER`, which the node's callbacks, tasks and
handles run with) and notes it. Its ``run`` is wrapped so that the thread
itself runs as the node (what it starts and hands to the loop is the
node's too) and tells its last stretch of CPU when it ends. Python 3.11
raises no such event: there a node's threads are unattributed Python
threads (said in ``docs/guide/load.md``), and the executor's are found by
``executor_work`` itself.

Each window :class:`ThreadLedger` reads every thread of the process
(``/proc/self/task``) through its own CPU clock and credits what it spent:

* a node's thread, to the node;
* the executor's threads (those started under ``executor_work``: lane
  workers, the watchdog, the waiters, the spare threads, the loop's
  default pool, the compiled fd watcher named ``fd-watcher``) and the
  thread that runs the loop, to the executor, which then gives the nodes
  back what their callbacks took on them;
* any other Python thread, to "python threads";
* a thread Python does not know (started by C or C++ code): the
  middleware's (Fast DDS names its threads ``dds.*``) to "middleware
  threads", others to "native threads". A C extension's own threads are
  the process's, never a node's: nothing in them says whose work they do.

Reading a thread's CPU clock is one system call (about 0.9 us here); a
window of 40 threads costs some 40 us.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Final

from ._owners import EXECUTOR, EXECUTOR_THREADS, OWNER, SEES_THREAD_STARTS, Owner

__all__ = ["ThreadLedger", "ThreadShares", "install", "owner_of"]

#: The audit events of a thread starting, whose first argument is the bound ``Thread._bootstrap``.
_STARTS: Final = frozenset({"_thread.start_new_thread", "_thread.start_joinable_thread"})
#: The compiled engine's fd watcher names its thread so (``fastpath/watcher.c``).
_WATCHER_NAME: Final = "fd-watcher"
#: Fast DDS's threads' names begin so (``dds.udp.7400``, ``dds.ev.0``, ``dds.shm.wdog``).
_MIDDLEWARE_PREFIX: Final = "dds."

#: Threads a node's code started, and whose.
_owners: weakref.WeakKeyDictionary[threading.Thread, Owner] = weakref.WeakKeyDictionary()
_installed = False
_install_lock = threading.Lock()


def install() -> None:
    """Start noting who starts each thread (once per process; audit hooks stay for good).

    The hook is called for every audit event of the process (opening a
    file, importing): it returns at once for all but a thread's start.
    """
    global _installed
    with _install_lock:
        if _installed or not SEES_THREAD_STARTS:
            return
        sys.addaudithook(_on_audit)
        _installed = True


def _on_audit(event: str, args: tuple[Any, ...]) -> None:
    if event in _STARTS:
        # An audit hook that raises would refuse the thread its start.
        with contextlib.suppress(Exception):
            _started(args[0])


def _started(bootstrap: object) -> None:
    """In the starting thread: ``bootstrap`` (a ``Thread``'s bound ``_bootstrap``) is about to run."""
    thread = getattr(bootstrap, "__self__", None)
    if not isinstance(thread, threading.Thread):
        return
    owner = OWNER.get()
    if owner is EXECUTOR:
        EXECUTOR_THREADS.add(thread)
    elif isinstance(owner, Owner):
        _owners[thread] = owner
        # An instance attribute: Thread._bootstrap_inner calls self.run().
        thread.run = _run_as(owner, thread.run)  # type: ignore[method-assign]


def _run_as(owner: Owner, run: Callable[[], object]) -> Callable[[], None]:
    def run_as_owner() -> None:
        OWNER.set(owner)  # this thread's own context: what it starts and schedules is the owner's
        try:
            run()
        finally:
            owner.thread_ended(owner, threading.get_native_id(), time.thread_time_ns())
            # The thread held itself through this wrapper (its bound run): let go, for refcounting.
            threading.current_thread().__dict__.pop("run", None)

    return run_as_owner


def owner_of(thread: threading.Thread) -> Owner | None:
    """The owner of ``thread`` if a node's code started it."""
    return _owners.get(thread)


def _thread_cpu_ns(tid: int) -> int | None:
    """The CPU time of thread ``tid`` of this process (``None``: it is gone).

    Linux's per-thread CPU clock id for a kernel thread id, as glibc's
    ``pthread_getcpuclockid`` builds it (CPUCLOCK_SCHED for a thread): one
    system call, in ns, for any thread of the process, Python's or not.
    The kernel refuses a thread of another process.
    """
    try:
        return time.clock_gettime_ns(((~tid) << 3) | 6)
    except OSError:
        return None


def _name_of(tid: int) -> str:
    try:
        with open(f"/proc/self/task/{tid}/comm", encoding="utf-8", errors="replace") as comm:
            return comm.read().strip()
    except OSError:
        return ""


@dataclass(slots=True)
class ThreadShares:
    """What the process's threads spent in one window (ns), by whose they are."""

    #: A node's threads, by owner.
    owners: dict[Owner, int] = field(default_factory=dict)
    #: Live threads each owner started.
    running: dict[Owner, int] = field(default_factory=dict)
    #: The executor's threads and the loop's.
    executor: int = 0
    #: ``python threads``, ``middleware threads``, ``native threads``.
    unattributed: dict[str, int] = field(
        default_factory=lambda: {"python threads": 0, "middleware threads": 0, "native threads": 0}
    )


class ThreadLedger:
    """Every thread's CPU clock, read once a window (and a node's thread's once more as it ends)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        #: Thread id -> its CPU clock at the last read.
        self._last: dict[int, int] = {}
        #: What threads of each owner spent between their last read and their end.
        self._ended: dict[Owner, int] = {}
        #: Names of threads Python does not know, by id.
        self._names: dict[int, str] = {}
        #: Threads first seen in the last window: their names are read once more.
        self._recheck: set[int] = set()
        self.sample(loop_threads=frozenset())  # the first window starts now

    def ended(self, owner: Owner, tid: int, cpu_ns: int) -> None:
        """A thread of ``owner`` ends, its clock at ``cpu_ns``: what it spent since its last read is the owner's."""
        with self._lock:
            spent = cpu_ns - self._last.pop(tid, 0)  # never read: born in this window, all of it
            self._ended[owner] = self._ended.get(owner, 0) + max(0, spent)

    def sample(self, *, loop_threads: frozenset[int]) -> ThreadShares:
        """Close the window: what each thread spent since the last one, credited.

        :param loop_threads: native ids of the threads that run the executor's loop.
        """
        python = {thread.native_id: thread for thread in threading.enumerate() if thread.native_id is not None}
        shares = ThreadShares()
        try:
            tids = [int(entry) for entry in os.listdir("/proc/self/task")]
        except OSError:
            tids = []
        with self._lock:
            last, self._last = self._last, {}
            recheck, self._recheck = self._recheck, set()
            shares.owners, self._ended = self._ended, {}
            for tid in tids:
                cpu = _thread_cpu_ns(tid)
                if cpu is None:
                    continue
                self._last[tid] = cpu
                spent = max(0, cpu - last.get(tid, 0))
                thread = python.get(tid)
                if thread is not None:
                    owner = _owners.get(thread)
                    if owner is not None:
                        shares.owners[owner] = shares.owners.get(owner, 0) + spent
                        shares.running[owner] = shares.running.get(owner, 0) + 1
                    elif tid in loop_threads or thread in EXECUTOR_THREADS:
                        shares.executor += spent
                    else:
                        shares.unattributed["python threads"] += spent
                    continue
                if tid in loop_threads:
                    shares.executor += spent
                    continue
                name = self._names.get(tid)
                if name is None or tid in recheck:
                    # Read as a thread first shows up, and once more the window after (one
                    # that names itself as it starts may not have done so by the first read).
                    name = self._names[tid] = _name_of(tid)
                    if tid not in recheck:
                        self._recheck.add(tid)
                if name == _WATCHER_NAME:
                    shares.executor += spent
                elif name.startswith(_MIDDLEWARE_PREFIX):
                    shares.unattributed["middleware threads"] += spent
                else:
                    shares.unattributed["native threads"] += spent
            for gone in set(self._names) - set(self._last):
                del self._names[gone]
        return shares
