"""One of asyncio's file descriptors became readable: the loop's rcl wait wakes (``fastpath/watcher.c``).

The loop's thread sleeps in ``rcl_wait`` (see ``_selector.py``), which knows
no file descriptors; a thread of this object's own polls the selector's
epoll descriptor while the loop sleeps and triggers an rcl guard condition
the wait set holds (its handle held here until the thread is joined).

Armed: watching the epoll descriptor. The thread disarms itself when that
becomes readable (epoll is level-triggered: staying armed would spin until
the loop has read), and the loop re-arms it before its next sleep.
:meth:`FdWatcher.arm` and :meth:`FdWatcher.close` wake the thread through
an eventfd.

Differences: the compiled thread never touches Python; this one needs the
GIL to wake up and trigger, which measured in the design notes as 356 us
from a byte on a pseudo-terminal to its reader, against 258-294 us
compiled. And :meth:`FdWatcher.pending` lets go of the GIL for its
zero-timeout poll (Python's ``poll`` always does), where the compiled one
keeps it so that a busy loop does not restart a waiting thread's wait for
CPython's forced switch on every iteration.
"""

from __future__ import annotations

import contextlib
import operator
import os
import select
import threading
from typing import Any

from ..._compat import RCLError
from .held import Held

__all__ = ["FdWatcher"]


class _Shared:
    """What the watching thread and its owner share (the thread holds this, not the owner,
    so that an owner nobody closed is still collected, and stops the thread then)."""

    __slots__ = ("armed", "ctl", "epfd", "guard", "lock", "ready", "stopping", "wakes")

    def __init__(self, epfd: int, ctl: int, guard: Any) -> None:
        #: The selector's epoll descriptor (not ours to close).
        self.epfd = epfd
        #: The eventfd that :meth:`FdWatcher.arm` and :meth:`FdWatcher.close` write to.
        self.ctl = ctl
        #: The guard condition's rclpy handle (held by the owner until the thread is joined).
        self.guard = guard
        #: Makes the flags' read-and-set one step, as the compiled one's atomics do.
        self.lock = threading.Lock()
        self.armed = False
        self.ready = False
        self.stopping = False
        self.wakes = 0

    def exchange_armed(self, value: bool) -> bool:
        with self.lock:
            was, self.armed = self.armed, value
        return was


def _watch(shared: _Shared) -> None:
    """The watching thread: poll the eventfd, and the epoll descriptor while armed."""
    poller = select.poll()
    poller.register(shared.ctl, select.POLLIN)
    watching = False
    while True:
        armed = shared.armed
        if armed != watching:
            if armed:
                poller.register(shared.epfd, select.POLLIN)
            else:
                poller.unregister(shared.epfd)
            watching = armed
        try:
            events = dict(poller.poll())
        except OSError:
            return  # only a closed descriptor gets here: the selector is going away
        if events.get(shared.ctl):
            with contextlib.suppress(BlockingIOError):
                os.eventfd_read(shared.ctl)
            if shared.stopping:
                return
        if armed and events.get(shared.epfd) and shared.exchange_armed(False):
            # Disarmed before the loop can see ready: its next sleep re-arms.
            shared.ready = True
            shared.wakes += 1
            with contextlib.suppress(RCLError):
                shared.guard.trigger_guard_condition()


class FdWatcher:
    """A thread that triggers the rcl guard condition ``guard`` (held until :meth:`close`)
    once, each time it is armed, when ``epoll`` becomes readable."""

    __slots__ = ("_guard", "_shared", "_thread")

    def __init__(self, *, epoll: int, guard: Any) -> None:
        if getattr(self, "_thread", None) is not None or getattr(self, "_guard", None) is not None:
            raise RuntimeError("FdWatcher already started")
        self._thread: threading.Thread | None = None
        self._guard: Held | None = None
        epfd = operator.index(epoll)
        guard_held = Held(guard)
        try:
            ctl = os.eventfd(0, os.EFD_CLOEXEC | os.EFD_NONBLOCK)
        except BaseException:
            guard_held.exit()
            raise
        shared = _Shared(epfd, ctl, guard_held.handle)
        thread = threading.Thread(target=_watch, args=(shared,), name="fd-watcher", daemon=True)
        try:
            thread.start()
        except BaseException:
            os.close(ctl)
            guard_held.exit()
            raise
        self._shared = shared
        self._guard = guard_held
        self._thread = thread

    def _poke(self) -> None:
        with contextlib.suppress(BlockingIOError):  # a full counter already wakes the thread
            os.eventfd_write(self._shared.ctl, 1)

    def arm(self) -> None:
        """About to sleep in rcl: trigger the guard once the epoll descriptor is readable."""
        if self._thread is None:
            raise RuntimeError("FdWatcher is closed")
        if not self._shared.exchange_armed(True):
            self._poke()

    def take(self) -> bool:
        """Whether it fired since the last take (and forget that it did)."""
        shared = self._shared
        with shared.lock:
            ready, shared.ready = shared.ready, False
        return ready

    def pending(self) -> bool:
        """Whether the epoll descriptor is readable now (an error too: let the selector tell)."""
        poller = select.poll()
        poller.register(self._shared.epfd, select.POLLIN)
        try:
            return bool(poller.poll(0))
        except OSError:
            return True

    def close(self) -> None:
        """Stop and join the thread; the guard is never triggered after this returns."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._shared.stopping = True
            self._poke()
            # Collected on the watching thread itself, it returns by itself (its eventfd stays open).
            if thread is not threading.current_thread():
                thread.join()
                os.close(self._shared.ctl)
        guard, self._guard = self._guard, None
        if guard is not None:
            guard.exit()

    def __del__(self) -> None:
        self.close()

    @property
    def armed(self) -> bool:
        """Whether it watches (the loop need not poll epoll itself)."""
        return self._shared.armed

    @property
    def wakes(self) -> int:
        """How often it triggered the guard."""
        return self._shared.wakes
