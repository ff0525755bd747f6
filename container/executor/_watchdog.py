"""A watchdog for the event loop's thread: when a plugin's callback blocks it, say so and keep ROS moving.

``async def`` callbacks share one thread; one that blocks (``time.sleep``, a
busy loop, a blocking read) stops the loop and, with it, the rcl wait that
feeds every node. The watchdog thread notices within ``stall_after``
seconds that the loop thread has not come back to wait. Two duties, for
different stalls:

* *Relieving*, for every stall: once the loop has been away for
  ``relieve_after`` it waits in rcl in the loop's place, so plain callbacks
  of every node keep their rate on their lanes' threads (``async def``
  work waits in the loop's inbox for the loop to come back). :attr:`stall`,
  :attr:`stalls` and :attr:`longest` count every stall too: the container's
  ``/diagnostics`` and the hard stop on a signal need to know the loop is
  stuck whoever holds it.
* *Reporting*, only for a plugin's work (see ``_culprit``): the container's
  own start-up, imports and services are slow on a loaded machine, which
  is not a plugin's fault to report. Reports follow *episodes*: repeated
  stalls of one callback (an ``async def`` timer that sleeps every tick) are
  one. Its first stall is reported at once (ERROR, the node, the callback,
  the plugin's own frames, see ``_frames``), and as one WARN line when it
  ends; a stall that lasts gets a WARN line a ``summary_every`` (a minute);
  further stalls of the callback are counted and summarised at most once a
  ``summary_every``. An episode with no stall for ``summary_every`` is
  over: the callback's next stall is reported in full again.
"""

from __future__ import annotations

import logging
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass

from .._compat import thread_frame
from ._culprit import Culprit
from ._frames import format_plugin_frames
from ._owners import executor_work

__all__ = ["LoopWatchdog", "Stall"]

_log = logging.getLogger("container.executor")

#: The longest the watchdog waits in rcl at once while relieving the loop.
_TICK_S = 0.05
#: The shortest it sleeps between looks.
_MIN_SLEEP_S = 0.005


@dataclass(frozen=True, slots=True)
class Stall:
    """The loop thread stuck in one callback: since when, in what, and whose it is."""

    since: float
    what: str
    #: A plugin's work (reported), or the platform's (counted only).
    plugin: bool = True


@dataclass(slots=True)
class _Episode:
    """Stalls of one plugin callback, reported once and then summarised."""

    what: str
    #: When the latest log line about this episode went out.
    line_at: float
    #: When its latest stall ended (or began, while one lasts).
    last_at: float
    #: Whether the stall in progress is the one reported in full.
    reported_now: bool = True
    #: Stalls ended since the latest line and not yet told.
    untold: int = 0
    untold_s: float = 0.0
    untold_longest: float = 0.0


class LoopWatchdog:
    """Watch one loop thread through the stamps the dispatcher leaves.

    :param busy_since: when the loop thread last came back from waiting in
        rcl (``time.monotonic()``), or ``None`` while it waits there.
    :param loop_thread: the loop thread's ident while it spins.
    :param relieve: wait in rcl for up to the given nanoseconds and
        dispatch, from the watchdog's thread; returns the executor's own
        wake-up flags it consumed.
    :param rewake: hand such a consumed wake-up back to the loop.
    :param describe: what the loop thread is running, and whose it is.
    :param reports: log stalls of plugin work (``False``: relieve and
        count only, log nothing; a client command's output stays clean).
    :param summary_every: the least time in seconds between two lines about
        one episode after its first report.
    """

    def __init__(
        self,
        *,
        busy_since: Callable[[], float | None],
        loop_thread: Callable[[], int | None],
        relieve: Callable[[int], int],
        rewake: Callable[[], None],
        describe: Callable[[], Culprit],
        stall_after: float = 1.0,
        relieve_after: float = 0.1,
        reports: bool = True,
        summary_every: float = 60.0,
    ) -> None:
        self._busy_since = busy_since
        self._loop_thread = loop_thread
        self._relieve = relieve
        self._rewake = rewake
        self._describe = describe
        self.stall_after = stall_after
        self.relieve_after = min(relieve_after, stall_after)
        self.reports = reports
        self.summary_every = summary_every
        #: Stalls seen so far (plugin's or not), and the longest one's duration in seconds.
        self.stalls = 0
        self.longest = 0.0
        self._stall: Stall | None = None
        self._key: tuple[str, ...] = ()
        #: Open episodes by callback (``Culprit.key``).
        self._episodes: dict[tuple[str, ...], _Episode] = {}
        #: Held by the watching thread whenever it is not asleep; guards the rest.
        self._changed = threading.Condition()
        self._watching = False
        self._closed = False
        self._thread = threading.Thread(target=self._watch, name="loop-watchdog", daemon=True)
        with executor_work():
            self._thread.start()

    @property
    def stall(self) -> Stall | None:
        """The stall in progress (any, a plugin's or not), if the loop is stuck now."""
        return self._stall

    def resume(self) -> None:
        """Watch the loop: it spins (again).

        One thread for the executor's life, parked between spins: a
        ``spin_once()`` loop pays no thread start per call, and its
        stalls of one callback stay one episode.
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
        """End the thread; stalls counted but not yet told are summarised first."""
        with self._changed:
            self._watching = False
            self._closed = True
            self._changed.notify()
        if self._thread is not threading.current_thread():
            self._thread.join(5.0)

    def _watch(self) -> None:
        woken = 0
        with self._changed:
            while not self._closed:
                since = self._busy_since() if self._watching else None
                now = time.monotonic()
                if self._stall is not None and since != self._stall.since:
                    self._end_stall(now)
                if self._episodes:
                    self._summarise(now)
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
                        self._begin_stall(since, now)
                    else:
                        self._still_stuck(now)
                # Under the lock: pause() returns only once this wait is over.
                woken |= self._relieve(int(_TICK_S * 1e9))
            self._summarise(time.monotonic(), final=True)

    # -- episodes and their log lines ---------------------------------------------
    def _begin_stall(self, since: float, now: float) -> None:
        culprit = self._describe()
        self._stall = Stall(since, culprit.what, plugin=culprit.plugin)
        self._key = culprit.key
        self.stalls += 1
        if not (self.reports and culprit.plugin):
            if self.reports:
                _log.debug(f"event loop busy for {now - since:.1f} s in {culprit.what} (the container's own work)")
            return
        episode = self._episodes.get(culprit.key)
        if episode is not None:
            episode.reported_now = False  # a repeat: counted when it ends
            episode.last_at = now
            return
        self._episodes[culprit.key] = _Episode(culprit.what, line_at=now, last_at=now)
        _log.error(
            f"{culprit.what}: event loop stuck for {now - since:.1f} s: async def callbacks wait; "
            f"plain callbacks and services keep running. Stack, most recent call first:\n{self._stack()}"
        )

    def _still_stuck(self, now: float) -> None:
        stall = self._stall
        assert stall is not None
        episode = self._episodes.get(self._key) if stall.plugin else None
        if episode is None:
            return
        episode.last_at = now
        if now - episode.line_at >= self.summary_every:
            episode.line_at = now
            _log.warning(f"{stall.what}: event loop still stuck, for {now - stall.since:.0f} s now")

    def _end_stall(self, now: float) -> None:
        stall = self._stall
        assert stall is not None
        self._stall = None
        duration = now - stall.since
        self.longest = max(self.longest, duration)
        episode = self._episodes.get(self._key) if stall.plugin else None
        if episode is None:
            return
        episode.last_at = now
        if episode.reported_now:
            episode.reported_now = False
            episode.line_at = now
            _log.warning(f"{stall.what}: event loop free again after {duration:.1f} s")
            return
        episode.untold += 1
        episode.untold_s += duration
        episode.untold_longest = max(episode.untold_longest, duration)

    def _summarise(self, now: float, *, final: bool = False) -> None:
        """Tell what episodes counted for ``summary_every``; close quiet ones."""
        current = self._key if self._stall is not None else None
        for key, episode in list(self._episodes.items()):
            if key == current:
                continue
            if episode.untold and (final or now - episode.line_at >= self.summary_every):
                _log.warning(
                    f"{episode.what}: stuck {episode.untold} more time{'s' if episode.untold != 1 else ''} "
                    f"in the last {now - episode.line_at:.0f} s, {episode.untold_s:.1f} s in all, "
                    f"longest {episode.untold_longest:.1f} s"
                )
                episode.line_at = now
                episode.untold, episode.untold_s, episode.untold_longest = 0, 0.0, 0.0
            elif not episode.untold and (final or now - episode.last_at >= self.summary_every):
                del self._episodes[key]

    def _stack(self) -> str:
        ident = self._loop_thread()
        frame = thread_frame(ident) if ident is not None else None
        if frame is None:
            return "  (no stack)"
        return format_plugin_frames(traceback.extract_stack(frame))
