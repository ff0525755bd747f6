"""An asyncio selector that sleeps inside the rcl wait set.

DDS offers no file descriptor to hand to asyncio, and a thread hand-over
per message costs several times a whole round trip here. So the event loop's
thread itself blocks in ``rcl_wait`` and takes ROS work without any hop;
asyncio's own file descriptors (serial ports, sockets, the loop's self-pipe
that ``call_soon_threadsafe`` and signals write to) are watched by a small
thread that only triggers an rcl guard condition when one becomes readable.
That thread stays parked while nothing but ROS traffic flows.
"""

from __future__ import annotations

import os
import select
import selectors
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

__all__: list[str] = []

#: Waits in rcl for at most the given nanoseconds (``-1``: forever) and
#: dispatches what became ready.
WaitAndDispatch = Callable[[int], object]


class RclSelector(selectors.BaseSelector):
    """Delegate file descriptors to epoll; block in rcl instead of epoll.

    :param wake: triggers a guard condition that the rcl wait set holds.
    """

    def __init__(self, *, wake: Callable[[], None]) -> None:
        self._inner = selectors.DefaultSelector()
        self._wake = wake
        self._fds_ready = False
        self._wait: WaitAndDispatch | None = None
        self._idle: Callable[[], bool] | None = None
        self._ros_turn_due: Callable[[], bool] | None = None
        self._armed = False
        self._rearm = threading.Event()
        self._stop_r, self._stop_w = os.pipe()
        self._watcher = threading.Thread(
            target=self._watch, name="rcl-selector-fd-watcher", daemon=True
        )
        self._watcher.start()

    def attach(
        self,
        wait: WaitAndDispatch | None,
        *,
        idle: Callable[[], bool] | None = None,
        ros_turn_due: Callable[[], bool] | None = None,
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
        """
        self._wait = wait
        self._idle = idle
        self._ros_turn_due = ros_turn_due

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
        # so pure ROS traffic costs no epoll call at all.
        ready = [] if self._armed else self._inner.select(0)
        if ready or (timeout is not None and timeout <= 0):
            # Still give ROS a turn so a busy fd cannot starve it.
            due = self._ros_turn_due
            if due is None or due():
                wait(0)
            return ready or self._fds_if_woken()
        if not self._armed:
            self._armed = True
            self._rearm.set()
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
            if self._fds_ready or not idle():
                return self._fds_if_woken()

    def _fds_if_woken(self) -> list[tuple[selectors.SelectorKey, int]]:
        if not self._fds_ready:
            return []
        self._fds_ready = False
        return self._inner.select(0)

    def close(self) -> None:
        os.write(self._stop_w, b"x")
        self._rearm.set()
        self._watcher.join(timeout=5.0)
        os.close(self._stop_r)
        os.close(self._stop_w)
        self._inner.close()

    # -- the watcher thread ---------------------------------------------------
    def _watch(self) -> None:
        poller = select.poll()
        poller.register(self._inner.fileno(), select.POLLIN)
        poller.register(self._stop_r, select.POLLIN)
        while True:
            self._rearm.wait()
            self._rearm.clear()
            events = poller.poll()
            if any(fd == self._stop_r for fd, _ in events):
                return
            # Disarm before waking the loop so its next select re-arms us.
            self._armed = False
            self._fds_ready = True
            self._wake()
