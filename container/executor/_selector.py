"""An asyncio selector that sleeps inside the rcl wait set.

DDS offers no file descriptor to hand to asyncio, and a thread hand-over
per message costs several times a whole round trip here. So the event loop's
thread itself blocks in ``rcl_wait`` and takes ROS work without any hop;
asyncio's own file descriptors (serial ports, sockets, the loop's self-pipe
that signals and asyncio's ``call_soon_threadsafe`` write to; the
container's own posts from other threads go through ``_inbox`` instead,
one guard-condition trigger) are watched by a small
compiled thread (``_fastpath.FdWatcher``) that only triggers an rcl guard
condition when one becomes readable. That thread stays parked while nothing
but ROS traffic flows.
"""

from __future__ import annotations

import selectors
import time
from collections.abc import Callable, Mapping
from typing import Any

from rclpy.guard_condition import GuardCondition

from ._engine import FdWatcher, Handoff

__all__: list[str] = []

#: Waits in rcl for at most the given nanoseconds (``-1``: forever) and
#: dispatches what became ready.
WaitAndDispatch = Callable[[int], object]

#: How long a busy loop waits, without the GIL, for the worker threads it
#: woke to start (see :class:`~._fastpath.Handoff`): a wake-up takes
#: 50-200 us here; one that takes longer (a thread starting, a starved
#: core) is left to CPython's forced switch.
#:
#: Measured against: ``bench_busy.py`` on the project's 2-core shared KVM
#: VM (commit 61a2a46), where this wait, with asyncio's descriptors looked
#: at without letting the GIL go, took an intra-process plain subscriber
#: beside a busy ``async def`` publisher from 4 to 2,400-2,900 1080p frames
#: a second. The 1 ms bound was not measured against others, and the
#: 50-200 us wake-up is stated there without the measurement behind it
#: (the LiDAR benchmark's notes in ``docs/benchmarks.md`` record 75-200 us
#: of CPU charged to each wake-up of a sleeping thread on that VM, as
#: ``/proc`` counts it). On one CPU the wait stays: it sleeps on a
#: condition variable, which is what gives the woken worker the CPU and
#: the GIL; it has not been measured there.
HANDOFF_WAIT_NS = 1_000_000
#: How long it then stays awake (spinning) for them to finish: a short
#: callback's worker lets the GIL go within that, and the loop's core never
#: went idle (waking an idle core of a virtual machine costs 50-200 us).
#:
#: Measured against: ``bench_busy.py`` on the 2-core shared KVM VM, quiet,
#: one run each side by side within minutes (commit 004b54c): the plain
#: intra-process subscriber went from 1,712 to 2,492 frames a second (5.0x
#: to 6.4x its DDS rate), its latency from 1.99x to 1.50x the ``async def``
#: one's. No other bound was measured. Not used on one CPU
#: (``Handoff.spin`` is false there: the worker could only finish once the
#: loop's thread gave the CPU back).
HANDOFF_SPIN_NS = 200_000


class RclSelector(selectors.BaseSelector):
    """Delegate file descriptors to epoll; block in rcl instead of epoll.

    :param guard: the guard condition the rcl wait set holds, which the
        watcher's thread triggers (the watcher holds its handle until
        :meth:`close`).
    """

    def __init__(self, *, guard: GuardCondition) -> None:
        self._inner = selectors.DefaultSelector()
        self._wait: WaitAndDispatch | None = None
        self._idle: Callable[[], bool] | None = None
        self._ros_turn_due: Callable[[], bool] | None = None
        self._handoff: Handoff | None = None
        try:
            self._watcher = FdWatcher(epoll=self._inner.fileno(), guard=guard.handle)
        except BaseException:
            self._inner.close()
            raise

    def attach(
        self,
        wait: WaitAndDispatch | None,
        *,
        idle: Callable[[], bool] | None = None,
        ros_turn_due: Callable[[], bool] | None = None,
        handoff: Handoff | None = None,
    ) -> None:
        """Route blocking selects through ``wait`` (``None``: plain epoll).

        :param idle: tells whether asyncio still has nothing to run after a
            wait; while it has not, a select waits in rcl again instead of
            returning: under steady ROS traffic whose callbacks finish in
            their first step, the loop's own iteration is skipped.
        :param ros_turn_due: tells whether a select that must not block
            (asyncio has work, or a file descriptor is ready) should still
            give ROS a turn: an rcl wait costs tens of microseconds, and a
            busy asyncio loop iterates far more often than timers and guard
            conditions need looking at (new messages are reported anyway).
        :param handoff: the worker threads the loop's thread woke with plain
            work; a select that must not block lets go of the GIL until
            they have started, or a busy loop would hold it for CPython's
            whole switch interval (5 ms) each time.
        """
        self._wait = wait
        self._idle = idle
        self._ros_turn_due = ros_turn_due
        self._handoff = handoff

    # -- selectors.BaseSelector -----------------------------------------------
    def register(
        self, fileobj: Any, events: int, data: Any = None
    ) -> selectors.SelectorKey:
        return self._inner.register(fileobj, events, data)

    def unregister(self, fileobj: Any) -> selectors.SelectorKey:
        return self._inner.unregister(fileobj)

    def modify(self, fileobj: Any, events: int, data: Any = None) -> selectors.SelectorKey:
        return self._inner.modify(fileobj, events, data)

    def get_map(self) -> Mapping[Any, selectors.SelectorKey]:
        return self._inner.get_map()

    def select(
        self, timeout: float | None = None
    ) -> list[tuple[selectors.SelectorKey, int]]:
        wait = self._wait
        if wait is None:
            return self._inner.select(timeout)
        # While the watcher is armed it would have woken rcl for a ready fd,
        # so pure ROS traffic costs no epoll call at all. Otherwise a look
        # that keeps the GIL first: epoll's own lets it go even for a
        # zero timeout, which restarts a waiting thread's wait for a
        # forced switch, every iteration of a busy loop.
        watcher = self._watcher
        ready = [] if watcher.armed or not watcher.pending() else self._inner.select(0)
        if ready or (timeout is not None and timeout <= 0):
            # Still give ROS a turn so a busy fd cannot starve it.
            due = self._ros_turn_due
            if due is None or due():
                wait(0)
            if self._handoff is not None:
                self._handoff.give(HANDOFF_WAIT_NS, HANDOFF_SPIN_NS)
            return ready or self._fds_if_woken()
        watcher.arm()
        idle = self._idle
        if idle is None:
            wait(-1 if timeout is None else int(timeout * 1e9))
            return self._fds_if_woken()
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if deadline is None:
                wait(-1)
            else:
                left = deadline - time.monotonic()
                if left <= 0:
                    return []
                wait(int(left * 1e9))
            if watcher.take():
                return self._inner.select(0)
            if not idle():
                return self._fds_if_woken()

    def _fds_if_woken(self) -> list[tuple[selectors.SelectorKey, int]]:
        return self._inner.select(0) if self._watcher.take() else []

    def close(self) -> None:
        self._watcher.close()
        self._inner.close()
