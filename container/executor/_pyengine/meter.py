"""What one entity's callbacks cost, per window (``fastpath/meter.c``).

Why here: every path that runs a callback (the async chain, the lanes'
first and later steps, the worker threads' plain calls) is timed at the
same two points, with the GIL held, so a meter needs no lock of its own.

CPU time: the thread's own CPU clock (``time.thread_time_ns()``, a system
call) is read only at the end of a step that lasted :data:`CPU_READ_NS` or
more, and at the start of a step when :data:`CPU_READ_PERIOD_NS` passed
since the thread's last read (what it spent since then was spent outside
steps). Other steps are credited their wall time. A step that ends with a
read gets what the thread really spent since the last read, less what the
steps in between were credited, at most its wall time and at least zero.
What a thread spends outside steps is nobody's callback: the executor's own.

Lateness is from when the work arrived (a message taken, a timer's due
time) to its first step's start; duration from that start to the end of
its last step (an async callback's awaits included). Both go into
log-linear histograms (:data:`METER_SUB` buckets per power of two, about 9%
wide) that :meth:`Meter.take` turns into p50, p99 and max and clears.

Stuck: a step running for :func:`stuck_after` nanoseconds or more (a plain
callback blocked on its worker, an async one holding the loop). Counted
once per step, by :meth:`Meter.take` while it lasts or at its end.

The same rules as the compiled meter, read with ``time.monotonic_ns()`` and
``time.thread_time_ns()`` (the same clocks). Difference: the compiled meter
needs no lock, each of its changes being one stretch of C under the GIL;
here a change is several bytecodes another thread may come between (two
workers ending steps of one entity, the accounting's window closing), so
each meter has a lock of its own, taken for every change and window.
"""

from __future__ import annotations

import operator
import threading
import time
from typing import Any, Final

__all__ = ["Meter", "begin", "count_dropped", "end", "pause", "resume", "stuck_after"]

#: Buckets per power of two.
METER_SUB = 8
#: Buckets in all: up to 2**41 ns (36 minutes), the last taking anything longer.
METER_BUCKETS = 40 * METER_SUB
#: A step this long or longer ends with a read of its thread's CPU clock.
CPU_READ_NS = 1_000_000
#: A step starts with one when the thread's last read is this old.
CPU_READ_PERIOD_NS = 10_000_000

_monotonic_ns = time.monotonic_ns
_thread_cpu_ns = time.thread_time_ns


class _Limits:
    """What :func:`stuck_after` sets, for every meter."""

    stuck_after_ns = 1_000_000_000


class _ThreadClock(threading.local):
    """Per thread: its last CPU clock read, and the wall time credited to steps since."""

    #: Monotonic ns of this thread's last CPU read.
    read_at = 0
    #: Its CPU clock then.
    at_read = 0
    #: Wall time credited to steps since.
    credited = 0


_clock = _ThreadClock()


def stuck_after(ns: int, /) -> None:
    """How long one step of a callback runs before its meter counts it stuck (every meter)."""
    ns = int(ns)
    if ns <= 0:
        raise ValueError("stuck_after: a positive number of nanoseconds")
    _Limits.stuck_after_ns = ns


def _bucket_of(value: int) -> int:
    if value < METER_SUB:
        return max(value, 0)
    exponent = value.bit_length() - 1
    index = (exponent - 2) * METER_SUB + ((value >> (exponent - 3)) & (METER_SUB - 1))
    return min(index, METER_BUCKETS - 1)


def _bucket_value(index: int) -> int:
    """The middle of bucket ``index``'s range."""
    if index < METER_SUB:
        return index
    exponent = index // METER_SUB + 2
    width = 1 << (exponent - 3)
    return (1 << exponent) + (index % METER_SUB) * width + width // 2


def _quantile(histogram: list[int], count: int, largest: int, q: float) -> int:
    """The value at quantile ``q`` (0..1) of a histogram of ``count`` values, at most ``largest``."""
    if count == 0:
        return 0
    rank = int(q * (count - 1)) + 1
    seen = 0
    for index, hits in enumerate(histogram):
        seen += hits
        if seen >= rank:
            return min(_bucket_value(index), largest)
    return largest


class Meter:
    """What one entity's callbacks cost, per window (runs, CPU, lateness, duration, drops, stuck).

    Its figures are changed by this module's functions only, each called
    with the GIL held where a step starts or ends.
    """

    __slots__ = (
        "_busy_ns", "_cpu_ns", "_dropped", "_dur", "_dur_max", "_dur_n", "_finished", "_in_step",
        "_late", "_late_max", "_late_n", "_lock", "_runs", "_step_since", "_stuck", "_stuck_counted",
    )  # fmt: skip

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._runs = self._finished = self._dropped = self._stuck = 0
        self._late_n = self._dur_n = 0
        self._busy_ns = self._cpu_ns = self._late_max = self._dur_max = 0
        #: When ``_in_step`` last went from 0 to 1.
        self._step_since = 0
        #: Steps running now.
        self._in_step = 0
        #: The step running now was counted stuck.
        self._stuck_counted = False
        self._late = [0] * METER_BUCKETS
        self._dur = [0] * METER_BUCKETS

    @property
    def running(self) -> int:
        """How long the step running now has run (ns; 0: none runs)."""
        with self._lock:
            return _monotonic_ns() - self._step_since if self._in_step > 0 else 0

    def call(self, *args: Any) -> Any:
        """``call(arrived, call, *args)``: ``call(*args)`` as one run of this meter, begun (its
        lateness from ``arrived``, monotonic ns; 0 unknown) and ended when it returns or raises."""
        if len(args) < 2:
            raise TypeError("call(arrived, call, *args)")
        arrived = operator.index(args[0])
        start = begin(self, arrived)
        try:
            return args[1](*args[2:])
        finally:
            end(self, start, start)

    def take(self) -> tuple[int, int, int, int, int, int, int, int, int, int, int, int, int]:
        """``(runs, finished, busy_ns, cpu_ns, late_p50, late_p99, late_max, duration_p50,
        duration_p99, duration_max, dropped, stuck, running_ns)``: this window's (ns), then a new one."""
        with self._lock:
            return self._take()

    def _take(self) -> tuple[int, int, int, int, int, int, int, int, int, int, int, int, int]:
        if not (
            self._in_step or self._runs or self._finished or self._busy_ns or self._cpu_ns or self._late_n
            or self._dur_n or self._dropped or self._stuck
        ):  # fmt: skip
            return _IDLE_FIGURES  # nothing ran: nothing to build or clear (most meters' windows)
        now = _monotonic_ns()
        running = now - self._step_since if self._in_step > 0 else 0
        if running >= _Limits.stuck_after_ns and not self._stuck_counted:
            self._stuck += 1
            self._stuck_counted = True
        late, dur = self._late, self._dur
        figures = (
            self._runs, self._finished, self._busy_ns, self._cpu_ns,
            _quantile(late, self._late_n, self._late_max, 0.5), _quantile(late, self._late_n, self._late_max, 0.99),
            self._late_max, _quantile(dur, self._dur_n, self._dur_max, 0.5),
            _quantile(dur, self._dur_n, self._dur_max, 0.99), self._dur_max, self._dropped, self._stuck, running,
        )  # fmt: skip
        self._runs = self._finished = self._dropped = self._stuck = 0
        self._busy_ns = self._cpu_ns = self._late_max = self._dur_max = 0
        self._late_n = self._dur_n = 0
        self._late = [0] * METER_BUCKETS
        self._dur = [0] * METER_BUCKETS
        return figures


#: What :meth:`Meter.take` gives for a window in which nothing ran or runs.
_IDLE_FIGURES: Final = (0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)


def _record_late(meter: Meter, value: int) -> None:
    value = max(value, 0)
    meter._late[_bucket_of(value)] += 1
    meter._late_n += 1
    meter._late_max = max(meter._late_max, value)


def _record_duration(meter: Meter, value: int) -> None:
    value = max(value, 0)
    meter._dur[_bucket_of(value)] += 1
    meter._dur_n += 1
    meter._dur_max = max(meter._dur_max, value)


def _step_in(meter: Meter, now: int) -> None:
    clock = _clock
    if now - clock.read_at >= CPU_READ_PERIOD_NS:
        # What the thread spent since its last read was spent outside steps.
        clock.at_read = _thread_cpu_ns()
        clock.read_at = now
        clock.credited = 0
    meter._in_step += 1
    if meter._in_step == 1:
        meter._step_since = now
        meter._stuck_counted = False


def _step_out(meter: Meter, step_start: int) -> int:
    now = _monotonic_ns()
    wall = max(now - step_start, 0)
    meter._busy_ns += wall
    clock = _clock
    if wall >= CPU_READ_NS:
        cpu = _thread_cpu_ns()
        spent = min(max(cpu - clock.at_read - clock.credited, 0), wall)
        clock.read_at = now
        clock.at_read = cpu
        clock.credited = 0
    else:
        spent = wall
        clock.credited += wall
    meter._cpu_ns += spent
    if wall >= _Limits.stuck_after_ns and not meter._stuck_counted:
        meter._stuck += 1
        meter._stuck_counted = True
    if meter._in_step > 0:
        meter._in_step -= 1
    return now


def begin(meter: Meter, arrived: int) -> int:
    """A callback's first step starts (``arrived``: when its work arrived, 0 unknown): its start (ns)."""
    now = _monotonic_ns()
    with meter._lock:
        meter._runs += 1
        if arrived > 0:
            _record_late(meter, now - arrived)
        _step_in(meter, now)
    return now


def resume(meter: Meter) -> int:
    """A later step of a suspended callback starts: its start (ns)."""
    now = _monotonic_ns()
    with meter._lock:
        _step_in(meter, now)
    return now


def pause(meter: Meter, step_start: int) -> None:
    """The step that started at ``step_start`` suspended."""
    with meter._lock:
        _step_out(meter, step_start)


def end(meter: Meter, step_start: int, started: int) -> None:
    """The step that started at ``step_start`` ended the callback, whose first step started at ``started``."""
    with meter._lock:
        now = _step_out(meter, step_start)
        meter._finished += 1
        _record_duration(meter, now - started)


def count_dropped(meter: Meter) -> None:
    """A waiting invocation of the meter's entity was dropped for a newer one (keep-last)."""
    with meter._lock:
        meter._dropped += 1
