"""A watchdog for the event loop's thread: when one callback blocks it, say so and keep ROS moving.

``async def`` callbacks share one thread; one that blocks (``time.sleep``, a
busy loop, a blocking read) stops the loop and, with it, the rcl wait that
feeds every node. The watchdog thread notices within ``stall_after``
seconds that the loop thread has not come back to wait, logs the node, the
callback and the loop thread's stack (and again every ``report_every``
seconds while it stays stuck). Long before reporting, once the loop has been
away for ``relieve_after``, it waits in rcl in the loop's place: plain
callbacks of every node keep their rate on their lanes' threads, and
``async def`` work waits in the loop's inbox for the loop to come back.
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass

from .._compat import thread_frame

__all__ = ["LoopWatchdog", "Stall"]

_log = logging.getLogger("container.executor")

#: The longest the watchdog waits in rcl at once while relieving the loop.
_TICK_S = 0.05
#: The shortest it sleeps between looks.
_MIN_SLEEP_S = 0.005


@dataclass(frozen=True, slots=True)
class Stall:
    """The loop thread stuck in one callback: since when, and in what."""

    since: float
    what: str


class LoopWatchdog:
    """Watch one loop thread through the stamps the dispatcher leaves.

    :param busy_since: when the loop thread last came back from waiting in
        rcl (``time.monotonic()``), or ``None`` while it waits there.
    :param loop_thread: the loop thread's ident while it spins.
    :param relieve: wait in rcl for up to the given nanoseconds and
        dispatch, from the watchdog's thread; returns the executor's own
        wake-up flags it consumed.
    :param rewake: hand such a consumed wake-up back to the loop.
    :param describe: what the loop thread is running (node and callback).
    """

    def __init__(
        self,
        *,
        busy_since: Callable[[], float | None],
        loop_thread: Callable[[], int | None],
        relieve: Callable[[int], int],
        rewake: Callable[[], None],
        describe: Callable[[], str],
        stall_after: float = 1.0,
        relieve_after: float = 0.1,
        report_every: float = 5.0,
    ) -> None:
        self._busy_since = busy_since
        self._loop_thread = loop_thread
        self._relieve = relieve
        self._rewake = rewake
        self._describe = describe
        self.stall_after = stall_after
        self.relieve_after = min(relieve_after, stall_after)
        self.report_every = report_every
        #: Stalls seen so far, and the longest one's duration in seconds.
        self.stalls = 0
        self.longest = 0.0
        self._stall: Stall | None = None
        #: Held by the watching thread whenever it is not asleep; guards the rest.
        self._changed = threading.Condition()
        self._watching = False
        self._closed = False
        self._thread = threading.Thread(target=self._watch, name="loop-watchdog", daemon=True)
        self._thread.start()

    @property
    def stall(self) -> Stall | None:
        """The stall in progress, if the loop is stuck now."""
        return self._stall

    def resume(self) -> None:
        """Watch the loop: it spins (again).

        One thread for the executor's life, parked between spins: a
        ``spin_once()`` loop pays no thread start per call.
        """
        with self._changed:
            self._watching = True
            self._changed.notify()

    def pause(self) -> None:
        """Stop watching until :meth:`resume`. Once this returns the
        thread no longer waits in rcl in the loop's place, nor reports."""
        with self._changed:
            self._watching = False
            if self._stall is not None:
                self._end_stall(time.monotonic())
            self._changed.notify()

    def stop(self) -> None:
        with self._changed:
            self._watching = False
            self._closed = True
            self._changed.notify()
        if self._thread is not threading.current_thread():
            self._thread.join(5.0)

    def _watch(self) -> None:
        next_report = 0.0
        woken = 0
        with self._changed:
            while not self._closed:
                since = self._busy_since() if self._watching else None
                now = time.monotonic()
                if self._stall is not None and since != self._stall.since:
                    self._end_stall(now)
                if since is None or now - since < self.relieve_after:
                    if woken:
                        self._rewake()
                        woken = 0
                    if not self._watching:
                        self._changed.wait()
                        continue
                    # Sleep until the loop could first count as stuck: while
                    # it waits in rcl, one relieve_after from now; while it
                    # works, until its current turn reaches relieve_after. An
                    # idle container costs this thread a wake-up every
                    # relieve_after.
                    left = self.relieve_after if since is None else since + self.relieve_after - now
                    self._changed.wait(max(left, _MIN_SLEEP_S))
                    continue
                if now - since >= self.stall_after:
                    if self._stall is None:
                        self._stall = Stall(since, self._describe())
                        self.stalls += 1
                        next_report = now
                    if now >= next_report:
                        self._report(now)
                        next_report = now + self.report_every
                # Under the lock: pause() returns only once this wait is over.
                woken |= self._relieve(int(_TICK_S * 1e9))

    def _report(self, now: float) -> None:
        stall = self._stall
        assert stall is not None
        ident = self._loop_thread()
        frame = thread_frame(ident) if ident is not None else None
        stack = "".join(traceback.format_stack(frame)).rstrip() if frame is not None else "(no stack)"
        _log.error(
            f"event loop stuck for {now - stall.since:.1f} s in {stall.what}: async def callbacks "
            f"wait; plain callbacks and services keep running. Loop thread's stack:\n{stack}"
        )

    def _end_stall(self, now: float) -> None:
        stall = self._stall
        assert stall is not None
        self._stall = None
        duration = now - stall.since
        self.longest = max(self.longest, duration)
        _log.warning(f"event loop free again after {duration:.1f} s in {stall.what}")
