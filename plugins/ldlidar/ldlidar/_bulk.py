"""Vectorised decoder for whole captures.

It applies the streaming parser's rule (a frame is accepted when its CRC is
valid and it does not start inside an accepted frame; everything else costs
one byte) to a whole buffer at once, so both give the same packets and the
same counters. The work is done in blocks small enough to stay in the CPU
cache, on a couple of threads (NumPy releases the GIL in the loops used):

1. follow the chain of back-to-back packets (a clean stream is nothing
   else) and check each link's CRC in place, through strided views; scan
   every byte that no valid link covers for ``54 2C`` / ``54 E0`` / ``54 0F``
   candidates and check those. The CRC is linear over GF(2), so a packet's
   CRC is the XOR of one table lookup per byte pair;
2. resolve the rare valid frames that start inside other valid frames, and
   re-scan in full any block where that unseated a link of a chain;
3. copy the accepted packets' fields out, again through strided views.

Skipping the bytes inside chain links is exact, not a heuristic: see
:func:`_find`.
"""

from __future__ import annotations

import mmap
import os
import stat
import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import TYPE_CHECKING, NamedTuple, TypeVar, cast

import numpy as np

from ._crc import crc_ok, position_tables
from ._errors import DeviceError
from ._parser import MAX_SPAN, ParserStats
from ._protocol import (
    ANGLE_UNITS,
    BOUNDARY,
    HEADER,
    HEALTH_SIZE,
    HEALTH_TYPE,
    INFO_SIZE,
    INFO_TYPE,
    PACKET_SIZE,
    PACKET_TYPE,
    POINTS_PER_PACKET,
    SUBUNITS,
    TIMESTAMP_WRAP_MS,
    TURN_SUBUNITS,
    Packet,
    crc8,
)

if TYPE_CHECKING:
    # Only for annotations: importing numpy.typing costs start-up time.
    from numpy.typing import NDArray

__all__ = ["DecodedStream", "crc_rows", "decode_bytes", "decode_file"]

_ROW = PACKET_SIZE + 1
"""Scattered packets are gathered into 48-byte rows so that every u16 field is aligned."""
_PAIRS_PER_PACKET = (PACKET_SIZE - 1) // 2
"""Byte pairs before the CRC byte: bytes 0..45."""
_BLOCK = 1 << 20
"""Bytes per block of work: about 22,000 packets, whose per-column temporaries
(one intp and one byte per packet) stay in the L2 cache."""
_SEEK = 64
"""Bytes first searched for the next header; a clean stream has one within 47."""
_FREE_CHAINS = 16
"""Chains a block may start before the rest of it is just scanned. Each chain
costs a few dozen NumPy calls, so noise (a false start at every ``54 2C``)
or frames between every few packets would otherwise cost more than a scan."""
_LINKS_PER_CHAIN = 1024
"""One more chain is allowed per this many valid links found in the block."""
_HEADER_WORD = HEADER | PACKET_TYPE << 8
"""``54 2C`` read as a little-endian u16."""
_CHUNK = 1 << 16
"""Packets per chunk of the per-packet summaries (see :func:`_where`)."""
_HALF_TURN = ANGLE_UNITS // 2
_SUB = SUBUNITS
_TURN = TURN_SUBUNITS
_T = TypeVar("_T")


def _pair_tables() -> NDArray[np.uint8]:
    """Return the ``(24, 65536)`` CRC contribution of each aligned byte pair of a packet.

    Pair ``j`` holds bytes ``2j`` and ``2j + 1``. Row 23 covers the CRC byte
    itself (contributing its own value) and a byte past the packet
    (contributing nothing), so the XOR of all 24 lookups over a valid packet
    is zero, and that of the first 23 is the CRC of bytes 0..45. A table per
    pair (64 KB, contiguous) is used one at a time, column by column, so it
    stays in cache.
    """
    single = position_tables()
    # Pair value w = lo | hi << 8 sits at [hi, lo] of a 256 x 256 outer XOR.
    pairs = single[1::2, :, None] ^ single[0::2, None, :]
    return pairs.reshape(_ROW // 2, 1 << 16)


_PAIRS: NDArray[np.uint8] | None = None


def _pairs() -> NDArray[np.uint8]:
    """Return the pair tables, built on first use (about 1 ms), not on import."""
    global _PAIRS
    if _PAIRS is None:
        _PAIRS = _pair_tables()
    return _PAIRS


def _column(
    buf: NDArray[np.uint8], base: int, stride: int, count: int, at: int, dtype: str = "<u2"
) -> NDArray[np.generic]:
    """View field *at* of *count* packets laid *stride* bytes apart from *base*.

    No copy: a chain of back-to-back packets is read in place (u16 fields at
    odd addresses included, which NumPy handles as unaligned data).
    """
    return np.ndarray((count,), dtype=dtype, buffer=buf, offset=base + at, strides=(stride,))


def _points(
    buf: NDArray[np.uint8], base: int, stride: int, count: int, at: int, dtype: str
) -> NDArray[np.generic]:
    """View the 12 per-point fields at *at* (distance 6, intensity 8) as ``(count, 12)``."""
    return np.ndarray(
        (count, POINTS_PER_PACKET), dtype=dtype, buffer=buf, offset=base + at, strides=(stride, 3)
    )


def _crc(buf: NDArray[np.uint8], base: int, stride: int, count: int, *, header: bool) -> NDArray[np.uint8]:
    """Return the CRC of bytes 0..45 of *count* packets laid *stride* bytes apart.

    One pass per byte pair over all packets, each with its own 64 KB table,
    which stays in cache: about twice as fast as one gather of 24 lookups
    per packet across all 24 tables (1.5 MB, and 192 bytes of intp index
    per packet).

    :param header: the packets are known to start with ``54 2C``, so the
        first pair's lookup is a constant.
    """
    tables = _pairs()
    if header:
        crc = np.full(count, tables[0, _HEADER_WORD], dtype=np.uint8)
    else:
        crc = _lookup(tables[0], _column(buf, base, stride, count, 0))
    for j in range(1, _PAIRS_PER_PACKET):
        crc ^= _lookup(tables[j], _column(buf, base, stride, count, 2 * j))
    return crc


def _lookup(table: NDArray[np.uint8], words: NDArray[np.generic]) -> NDArray[np.uint8]:
    """Return ``table[words]`` for u16 *words* and a 65536-entry table.

    ``mode="clip"`` only skips the bounds check (a u16 is always in range),
    which is a fifth of the lookup's cost.
    """
    return table.take(words.astype(np.intp), mode="clip")


def _valid(buf: NDArray[np.uint8], base: int, stride: int, count: int) -> NDArray[np.bool_]:
    """Return which of *count* data packets (headers known) the parser would accept.

    Valid means the CRC matches and the angles are possible (see
    :data:`MAX_SPAN`), the streaming parser's test.
    """
    if not count:
        return np.zeros(0, dtype=bool)
    crc = _crc(buf, base, stride, count, header=True)
    ok: NDArray[np.bool_] = crc == _column(buf, base, stride, count, PACKET_SIZE - 1, "u1")
    start = _column(buf, base, stride, count, 4).astype(np.int32)
    end = _column(buf, base, stride, count, 42).astype(np.int32)
    ok &= start < ANGLE_UNITS
    ok &= end < ANGLE_UNITS
    # (end - start) mod a turn <= MAX_SPAN, for end - start in (-turn, turn).
    end -= start
    ok &= end <= MAX_SPAN
    ok &= (end >= 0) | (end <= MAX_SPAN - ANGLE_UNITS)
    return ok


def crc_rows(rows: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Return the CRC of bytes 0..45 of each row of an ``(n, 47)`` or ``(n, 48)`` array."""
    padded = np.zeros((len(rows), _ROW), dtype=np.uint8)
    padded[:, : PACKET_SIZE - 1] = rows[:, : PACKET_SIZE - 1]
    return _crc(padded, 0, _ROW, len(rows), header=False)


@dataclass(frozen=True, eq=False, slots=True)
class DecodedStream:
    """Every data packet of a byte stream, as columns.

    :param offsets: byte offset of each packet in the stream.
    :param speed: degrees per second.
    :param start_angle: hundredths of a degree.
    :param end_angle: hundredths of a degree.
    :param timestamp: device milliseconds, wrapping at 30000.
    :param distances: ``(n, 12)`` millimetres.
    :param intensities: ``(n, 12)``.
    :param crc: each packet's CRC byte.
    :param stats: the same counters a :class:`StreamParser` would report
        after :meth:`~StreamParser.flush`.
    :param size: bytes decoded.
    """

    offsets: NDArray[np.int64]
    speed: NDArray[np.uint16]
    start_angle: NDArray[np.uint16]
    end_angle: NDArray[np.uint16]
    timestamp: NDArray[np.uint16]
    distances: NDArray[np.uint16]
    intensities: NDArray[np.uint8]
    crc: NDArray[np.uint8]
    stats: ParserStats
    size: int

    def __len__(self) -> int:
        return len(self.offsets)

    def packets(self) -> list[Packet]:
        """Return the packets as :class:`Packet` objects (slow; for tests and tools)."""
        return [
            Packet(
                speed=int(self.speed[i]),
                start_angle=int(self.start_angle[i]),
                end_angle=int(self.end_angle[i]),
                timestamp=int(self.timestamp[i]),
                distances=tuple(int(d) for d in self.distances[i]),
                intensities=tuple(int(v) for v in self.intensities[i]),
                crc=int(self.crc[i]),
            )
            for i in range(len(self))
        ]

    def point_angles(self) -> NDArray[np.float32]:
        """Return ``(n, 12)`` point angles in degrees, clockwise, in [0, 360)."""
        out = np.empty((len(self), POINTS_PER_PACKET), dtype=np.float32)
        _blockwise(
            lambda a, b: _angles_into(self.start_angle[a:b], self.end_angle[a:b], out[a:b]),
            len(self),
            _BLOCK // PACKET_SIZE,
        )
        return out

    def angle_range(self) -> tuple[float, float] | None:
        """Return the smallest and largest of :meth:`point_angles`, or None when empty.

        Equal to ``point_angles().min()`` and ``.max()``, without building the
        ``(n, 12)`` array: points of a packet are evenly spaced, so a packet's
        extremes are its first and last point, or, when it crosses 0, the
        points either side of the crossing.
        """
        if not len(self):
            return None
        inside, first, span = self._crossings()
        # Within a packet that crosses 0 both its start and end lie between
        # its two extremes, so they can be taken with all the others.
        low = int(self.start_angle.min()) * _SUB
        high = int(self.end_angle.max()) * _SUB
        if len(inside):
            at = self.start_angle[inside].astype(np.int64) * _SUB + span * first
            low = min(low, int((at - _TURN).min()))
            high = max(high, int((at - span).max()))
        out = np.empty(2, dtype=np.float32)
        _degrees_into(np.array([low, high], dtype=np.int32), out)
        return float(out[0]), float(out[1])

    def _crossings(self, boundary: int = 0) -> tuple[NDArray[np.intp], NDArray[np.int64], NDArray[np.int64]]:
        """Return the packets whose points cross *boundary*, their first point past it, and their spans.

        Accepted packets have both angles below a full turn (see MAX_SPAN),
        so a packet crosses the boundary exactly when its end angle, measured
        from the boundary, is below its start.
        """
        if boundary:

            def crosses(a: int, b: int) -> NDArray[np.bool_]:
                # A packet spans at most MAX_SPAN (a quarter turn), so one
                # that crosses the back cannot also cross the front.
                ok: NDArray[np.bool_] = self.start_angle[a:b] < boundary
                ok &= self.end_angle[a:b] >= boundary
                return ok

            inside = _where(crosses, len(self))
            start = (self.start_angle[inside].astype(np.int64) - boundary) % ANGLE_UNITS
            end = (self.end_angle[inside].astype(np.int64) - boundary) % ANGLE_UNITS
        else:
            inside = _where(lambda a, b: self.end_angle[a:b] < self.start_angle[a:b], len(self))
            start = self.start_angle[inside].astype(np.int64)
            end = self.end_angle[inside].astype(np.int64)
        span = end - start + ANGLE_UNITS
        # First point k whose position start*11 + span*k reaches a full turn.
        first = -((start * _SUB - _TURN) // span)
        return inside, first, span

    def wraps(self) -> NDArray[np.int64]:
        """Return the flat point indices where a new revolution begins.

        A revolution begins at the back of the sensor (device 180 degrees,
        :data:`~ldlidar._protocol.BOUNDARY`): where the angle past it drops by
        more than half a turn from one point to the next, the rule
        :class:`ScanAssembler` uses.
        """
        inside, first, _ = self._crossings(BOUNDARY)

        def drops(a: int, b: int) -> NDArray[np.bool_]:
            start = (self.start_angle[a + 1 : b + 1].astype(np.int32) - BOUNDARY) % ANGLE_UNITS
            end = (self.end_angle[a:b].astype(np.int32) - BOUNDARY) % ANGLE_UNITS
            return start < end - _HALF_TURN

        between = _where(drops, len(self) - 1) + 1
        flat = np.concatenate((inside * POINTS_PER_PACKET + first, between * POINTS_PER_PACKET))
        flat.sort()
        return flat

    def revolutions(self) -> int:
        """Return the number of complete revolutions (between two wraps)."""
        return max(len(self.wraps()) - 1, 0)

    def device_steps(self) -> NDArray[np.int32]:
        """Return the device milliseconds from each packet to the next (one fewer than packets).

        The device clock wraps at :data:`TIMESTAMP_WRAP_MS`, so a step is the
        difference of two stamps modulo that. A step longer than one
        revolution at the packet's speed is a jump of the device's clock (a
        backward jump reads as nearly 30 s), not time that passed: it is
        replaced by the time the rotation took from one start angle to the
        next, as :class:`ScanAssembler` does without a host clock.
        """
        out = np.empty(max(len(self) - 1, 0), dtype=np.int32)
        for a in range(0, len(out), _CHUNK):
            b = min(a + _CHUNK, len(out))
            self._steps(a, b, out[a:b])
        return out

    def device_elapsed(self, start: int = 0, stop: int | None = None) -> int:
        """Return the device milliseconds from packet *start* to packet *stop* (default: the last).

        The sum of :meth:`device_steps` between them, without an array of
        every step (a summary needs only a few such spans).
        """
        stop = max(len(self) - 1, 0) if stop is None else stop
        spans = range(start, stop, _CHUNK)
        return sum(int(self._steps(a, min(a + _CHUNK, stop)).sum(dtype=np.int64)) for a in spans)

    def _steps(self, a: int, b: int, out: NDArray[np.int32] | None = None) -> NDArray[np.int32]:
        """Return the steps from packet ``i`` to ``i + 1`` for ``i`` in ``[a, b)``."""
        stamps = self.timestamp[a : b + 1]
        steps: NDArray[np.int32] = np.subtract(stamps[1:], stamps[:-1], dtype=np.int32, out=out)
        if int(stamps.max()) < TIMESTAMP_WRAP_MS:
            # Stamps on the clock differ by less than one wrap: the modulo is
            # one conditional add (the general remainder costs a division).
            np.add(steps, TIMESTAMP_WRAP_MS, out=steps, where=steps < 0)
        else:
            np.remainder(steps, TIMESTAMP_WRAP_MS, out=steps)
        # step > 360,000 / speed, without a division (both fit an int32);
        # the whole check only where the largest step could be one.
        speed = self.speed[a + 1 : b + 1]
        if not len(steps) or int(steps.max()) * int(speed.max()) <= 360_000:
            return steps
        jumps = np.flatnonzero(steps * speed.astype(np.int32) > 360_000)
        if len(jumps):
            turned = (self.start_angle[a + 1 + jumps].astype(np.int64) - self.start_angle[a + jumps]) % ANGLE_UNITS
            steps[jumps] = np.rint(turned * 10 / speed[jumps])
        return steps

    def device_times(self) -> NDArray[np.int64]:
        """Return each packet's device timestamp in ms, unwrapped from 0."""
        if not len(self):
            return np.zeros(0, dtype=np.int64)
        out = np.empty(len(self), dtype=np.int64)
        out[0] = 0
        np.cumsum(self.device_steps(), out=out[1:])
        return out


def _where(test: Callable[[int, int], NDArray[np.bool_]], n: int) -> NDArray[np.intp]:
    """Return ``np.flatnonzero`` of ``test(a, b)`` over ``range(n)``, evaluated in chunks.

    The chunks' temporaries stay in cache and are reused; temporaries the
    size of the whole stream would be fresh memory, slow to fault in.
    """
    parts = [np.flatnonzero(test(a, min(a + _CHUNK, n))) + a for a in range(0, n, _CHUNK)]
    return np.concatenate(parts) if parts else np.zeros(0, dtype=np.intp)


def _degrees_into(pos: NDArray[np.int32], out: NDArray[np.float32]) -> None:
    """Convert positions in 1/11 of 0.01 degree to degrees, the one rounding both angle methods share."""
    np.multiply(pos, np.float32(1 / (100 * _SUB)), out=out)


def _angles_into(
    start: NDArray[np.uint16], end: NDArray[np.uint16], out: NDArray[np.float32]
) -> None:
    # Accepted packets have both angles below a full turn (see MAX_SPAN).
    s = start.astype(np.int32)
    span = end.astype(np.int32) - s
    span += (span < 0) * np.int32(ANGLE_UNITS)
    pos = np.arange(POINTS_PER_PACKET, dtype=np.int32) * span[:, None]
    pos += (s * _SUB)[:, None]
    np.subtract(pos, _TURN, out=pos, where=pos >= _TURN)
    _degrees_into(pos, out)


def _blockwise(fn: Callable[[int, int], _T], n: int, block: int) -> list[_T]:
    """Run ``fn(a, b)`` over consecutive ranges of ``range(n)``, on a few threads.

    Ranges are handed out one at a time, so a thread on a core that another
    process keeps busy simply takes fewer. Plain threads, not
    ``concurrent.futures``, whose imports (logging and more) would cost a
    visible share of a short command's start-up.
    """
    block = max(block, 1)
    ranges = [(a, min(a + block, n)) for a in range(0, n, block)]
    if len(ranges) < 4 or _THREADS < 2:
        return [fn(a, b) for a, b in ranges]
    results: list[_T | None] = [None] * len(ranges)
    todo = iter(range(len(ranges)))
    lock = threading.Lock()
    errors: list[BaseException] = []

    def work() -> None:
        while not errors:
            with lock:
                i = next(todo, None)
            if i is None:
                return
            try:
                results[i] = fn(*ranges[i])
            except BaseException as exc:  # re-raised in the calling thread
                errors.append(exc)

    threads = [threading.Thread(target=work, daemon=True) for _ in range(_THREADS - 1)]
    for thread in threads:
        thread.start()
    work()
    for thread in threads:
        thread.join()
    if errors:
        raise errors[0]
    return cast("list[_T]", results)


_THREADS = min(os.cpu_count() or 1, 4)


def _rows(b: NDArray[np.uint8], pos: NDArray[np.int64]) -> NDArray[np.uint8]:
    """Gather ``(len(pos), 48)`` rows starting at *pos* (the last byte may be padding)."""
    n = len(b)
    if len(pos) and pos[-1] + _ROW > n:
        tail = np.zeros(_ROW, dtype=np.uint8)
        tail[: n - pos[-1]] = b[pos[-1] :]
        head = _rows(b, pos[:-1])
        return np.concatenate((head, tail[None, :]))
    if not len(pos):
        return np.zeros((0, _ROW), dtype=np.uint8)
    windows = np.lib.stride_tricks.sliding_window_view(b, _ROW)
    return windows[pos]


class _Found(NamedTuple):
    """Valid frames and failed data-packet candidates of one block.

    :param packets: sorted offsets of valid data packets: chain links and
        scanned ones.
    :param scanned: the scanned ones alone (not links of a chain).
    :param bad: data-packet candidates that failed.
    :param health: valid health frames.
    :param info: valid information frames.
    :param shortest: the smallest step from one packet to the next (below
        47 when two overlap).
    :param abutting: how many packets start where the one before ends.
    """

    packets: NDArray[np.int64]
    scanned: NDArray[np.int64]
    bad: NDArray[np.int64]
    health: list[int]
    info: list[int]
    shortest: int
    abutting: int


def _next_header(b: NDArray[np.uint8], pos: int, e: int) -> int:
    """Return the first offset in ``[pos, e)`` holding ``54 2C``, or *e*."""
    width = _SEEK
    while pos < e:
        hi = min(pos + width, e)
        window = b[pos : hi + 1]
        hits = np.flatnonzero((window[:-1] == HEADER) & (window[1:] == PACKET_TYPE))
        if len(hits):
            return pos + int(hits[0])
        pos = hi
        width *= 8
    return e


def _chains(b: NDArray[np.uint8], a: int, e: int) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """Follow chains of back-to-back packets through ``b[a:e]``.

    Return runs of valid links ``(offset, count)`` starting in the block, and
    the ranges ``[lo, hi)`` of offsets that no valid link covers, to be
    scanned. A chain starts at a ``54 2C`` and goes on while every 47 bytes
    hold another; links that fail their CRC or angles leave their 47 bytes
    to the scan. Where a chain stops, the next starts at the next header,
    within the budget of :data:`_FREE_CHAINS`.
    """
    runs: list[tuple[int, int]] = []
    gaps: list[tuple[int, int]] = []
    pos = a
    chains = links = 0
    while pos < e and chains < _FREE_CHAINS + links // _LINKS_PER_CHAIN:
        chains += 1
        p = _next_header(b, pos, e)
        if p > pos:
            gaps.append((pos, p))
        pos = p
        ok = _chain(b, p, e)
        if not len(ok):
            break
        links += int(np.count_nonzero(ok))
        _split(p, ok, e, runs, gaps)
        pos = p + len(ok) * PACKET_SIZE
    if pos < e:
        gaps.append((pos, e))
    return runs, gaps


def _chain(b: NDArray[np.uint8], p: int, e: int) -> NDArray[np.bool_]:
    """Return which links of the chain from header *p* are valid.

    The chain holds the 47-byte steps from *p* that start before *e*, fit in
    the buffer, and all start with ``54 2C``; it is empty past the buffer's
    last possible packet.
    """
    count = min(-((p - e) // PACKET_SIZE), (len(b) - p) // PACKET_SIZE)
    if count <= 0:
        return np.zeros(0, dtype=bool)
    linked = _column(b, p, PACKET_SIZE, count, 0) == _HEADER_WORD
    length = int(linked.argmin()) if not linked.all() else count
    return _valid(b, p, PACKET_SIZE, length)


def _split(
    p: int, ok: NDArray[np.bool_], e: int, runs: list[tuple[int, int]], gaps: list[tuple[int, int]]
) -> None:
    """Append the runs of valid links of the chain from *p* to *runs*, the rest (before *e*) to *gaps*."""
    bounds = [0, *(np.flatnonzero(ok[1:] != ok[:-1]) + 1).tolist(), len(ok)]
    good = bool(ok[0])
    for lo, hi in pairwise(bounds):
        if good:
            runs.append((p + lo * PACKET_SIZE, hi - lo))
        else:
            gaps.append((p + lo * PACKET_SIZE, min(p + hi * PACKET_SIZE, e)))
        good = not good


def _scan(
    b: NDArray[np.uint8], gaps: Iterable[tuple[int, int]]
) -> tuple[NDArray[np.int64], NDArray[np.int64], list[int], list[int]]:
    """Check every candidate frame starting in the ranges *gaps*.

    Return valid and failed data-packet offsets, and valid health and info
    frame offsets.
    """
    n = len(b)
    found = []
    for lo, hi in gaps:
        seg = b[lo : min(hi + 1, n)]
        found.append(np.flatnonzero(seg[:-1] == HEADER) + lo)
    heads = np.concatenate(found) if found else np.zeros(0, np.int64)
    kinds = b[heads + 1]
    cand = heads[kinds == PACKET_TYPE]
    cand = cand[cand <= n - PACKET_SIZE]
    ok = _valid(_rows(b, cand), 0, _ROW, len(cand))
    health = [
        int(p)
        for p in heads[kinds == HEALTH_TYPE]
        if p + HEALTH_SIZE <= n and crc8(b[p : p + HEALTH_SIZE - 1].tobytes()) == b[p + HEALTH_SIZE - 1]
    ]
    info = [
        int(p)
        for p in heads[kinds == INFO_TYPE]
        if p + INFO_SIZE <= n and crc8(b[p : p + INFO_SIZE - 1].tobytes()) == b[p + INFO_SIZE - 1]
    ]
    return cand[ok], cand[~ok], health, info


def _find(b: NDArray[np.uint8], a: int, e: int, *, full: bool = False) -> _Found:
    """Find the valid frames starting in ``b[a:e]`` that can matter.

    Chain links are trusted and the offsets inside them are not scanned
    (unless *full*). That gives the streaming rule's answer as long as every
    link is accepted: a frame starting inside an accepted link is rejected,
    and a rejected frame changes nothing for any other; so the first frame
    on which a full scan could differ would sit inside a link that had been
    accepted. :func:`decode_bytes` checks that every link was accepted and
    otherwise calls again with *full* for the block.
    """
    runs, gaps = ([], [(a, e)]) if full else _chains(b, a, e)
    scanned, bad, health, info = _scan(b, gaps)
    links = [p + PACKET_SIZE * np.arange(count, dtype=np.int64) for p, count in runs]
    packets = np.concatenate((*links, scanned)) if links else scanned
    if len(links) > 1 or len(scanned):
        packets.sort(kind="stable")  # a merge of sorted runs
    # Summarised here, on the block's thread, so that the merge need not
    # walk every packet again.
    steps = np.diff(packets)
    shortest = int(steps.min()) if len(steps) else PACKET_SIZE
    abutting = int(np.count_nonzero(steps == PACKET_SIZE))
    return _Found(packets, scanned, bad, health, info, shortest, abutting)


def _resolve(starts: NDArray[np.int64], ends: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Return which of the sorted valid frames the streaming rule accepts.

    A frame is accepted unless it starts inside an accepted frame. One that
    starts at or after every earlier frame's end is accepted whatever was
    decided before it; only the rare clusters of overlapping frames need a
    sequential pass.
    """
    if not len(starts):
        return np.zeros(0, dtype=bool)
    reach = np.maximum.accumulate(ends)
    accept = np.ones(len(starts), dtype=bool)
    accept[1:] = starts[1:] >= reach[:-1]
    end = 0
    prev = -2
    for i in np.flatnonzero(~accept).tolist():
        if i != prev + 1:
            end = int(ends[i - 1])
        if starts[i] >= end:
            accept[i] = True
            end = max(end, int(ends[i]))
        prev = i
    return accept


def _merge(parts: Iterable[Sequence[int]]) -> NDArray[np.int64]:
    return np.array([p for part in parts for p in part], dtype=np.int64)


class _Frames(NamedTuple):
    """The accepted frames and what the counters need besides.

    :param packets: accepted data packets, in stream order.
    :param extras: accepted health and info frames, in stream order.
    :param extra_sizes: their sizes.
    :param gaps: runs of skipped bytes between two accepted frames.
    :param bad: failed data-packet candidates.
    :param unseated: chain links that were not accepted (their blocks need
        a full scan, see :func:`_find`).
    """

    packets: NDArray[np.int64]
    extras: NDArray[np.int64]
    extra_sizes: NDArray[np.uint8]
    gaps: int
    bad: NDArray[np.int64]
    unseated: NDArray[np.int64]


def _extras(found: Sequence[_Found], packets: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
    """Return the blocks' health and info frames in stream order, and their sizes.

    A frame inside which a valid data packet starts is not one (the packet
    wins, as in the streaming parser). *packets* holds every valid data
    packet: one starting inside a frame found in a gap is either scanned too
    or the first link of a chain, never inside another link.
    """
    health = _merge(f.health for f in found)
    info = _merge(f.info for f in found)
    starts = np.concatenate((health, info))
    sizes = np.concatenate(
        (np.full(len(health), HEALTH_SIZE, np.uint8), np.full(len(info), INFO_SIZE, np.uint8))
    )
    if len(starts):
        after = np.searchsorted(packets, starts, side="right")
        nxt = packets[np.minimum(after, len(packets) - 1)] if len(packets) else starts + 256
        alone = (after >= len(packets)) | (nxt >= starts + sizes)
        starts, sizes = starts[alone], sizes[alone]
    order = np.argsort(starts, kind="stable")
    return starts[order], sizes[order]


def _around(
    packets: NDArray[np.int64], extras: NDArray[np.int64], sizes: NDArray[np.uint8]
) -> tuple[NDArray[np.int64], NDArray[np.uint8]]:
    """Return the extra frames and the packets either side of each, in stream order, with sizes."""
    at = np.searchsorted(packets, extras).tolist()
    # (Not np.unique: its first call imports numpy.ma, 40 ms.)
    near = packets[sorted({i - 1 for i in at if i > 0} | {i for i in at if i < len(packets)})]
    starts = np.concatenate((near, extras))
    order = np.argsort(starts, kind="stable")
    return starts[order], np.concatenate((np.full(len(near), PACKET_SIZE, np.uint8), sizes))[order]


def _accept(found: Sequence[_Found]) -> _Frames:
    """Merge the blocks' frames and apply the streaming rule to them.

    Usually no two valid frames overlap, so all are accepted. That is
    checked, and the gaps counted, from the blocks' summaries, the seams
    between blocks and the neighbourhoods of the few extra frames, without
    another pass over every packet.
    """
    packets = np.concatenate([f.packets for f in found]) if found else np.zeros(0, np.int64)
    bad = np.concatenate([f.bad for f in found]) if found else np.zeros(0, np.int64)
    extras, sizes = _extras(found, packets)
    filled = [f for f in found if len(f.packets)]
    seams = np.array([b.packets[0] - a.packets[-1] for a, b in pairwise(filled)], dtype=np.int64)
    near, near_sizes = _around(packets, extras, sizes)
    near_steps = np.diff(near)
    overlap = (
        any(f.shortest < PACKET_SIZE for f in found)
        or bool(np.any(seams < PACKET_SIZE))
        or bool(np.any(near_steps < near_sizes[:-1]))
    )
    if not overlap:
        touching = near_steps == near_sizes[:-1]
        touching &= (near_sizes[:-1] != PACKET_SIZE) | (near_sizes[1:] != PACKET_SIZE)
        abutting = sum(f.abutting for f in found) + np.count_nonzero(seams == PACKET_SIZE)
        abutting += np.count_nonzero(touching)
        gaps = max(len(packets) + len(extras) - 1 - int(abutting), 0)
        return _Frames(packets, extras, sizes, gaps, bad, np.zeros(0, np.int64))
    return _resolved(found, packets, extras, sizes, bad)


def _resolved(
    found: Sequence[_Found],
    packets: NDArray[np.int64],
    extras: NDArray[np.int64],
    extra_sizes: NDArray[np.uint8],
    bad: NDArray[np.int64],
) -> _Frames:
    """Apply the streaming rule to frames some of which overlap."""
    at = np.searchsorted(packets, extras)
    starts = np.insert(packets, at, extras)
    sizes = np.insert(np.full(len(packets), PACKET_SIZE, np.uint8), at, extra_sizes)
    accept = _resolve(starts, starts + sizes.astype(np.int64))
    rejected = starts[~accept]
    scanned = np.concatenate([f.scanned for f in found] + [extras])
    unseated = rejected[~np.isin(rejected, scanned)]
    starts = starts[accept]
    sizes = sizes[accept]
    gaps = int(np.count_nonzero(np.diff(starts) > sizes[:-1]))
    extra = sizes != PACKET_SIZE
    return _Frames(starts[~extra], starts[extra], sizes[extra], gaps, bad, unseated)


def _covered(
    points: NDArray[np.int64], starts: NDArray[np.int64], sizes: int | NDArray[np.uint8]
) -> NDArray[np.bool_]:
    """Return which *points* fall inside one of the sorted, disjoint frames at *starts*."""
    if not len(starts):
        return np.zeros(len(points), dtype=bool)
    inside = np.searchsorted(starts, points, side="right") - 1
    size = sizes if isinstance(sizes, int) else sizes[inside]
    covered: NDArray[np.bool_] = (inside >= 0) & (points < starts[inside] + size)
    return covered


def _stats(b: NDArray[np.uint8], frames: _Frames) -> ParserStats:
    """Count what the streaming parser would have counted."""
    n = len(b)
    packets, extras, sizes, gaps, bad, _ = frames
    health = extras[sizes == HEALTH_SIZE]
    stats = ParserStats(packets=len(packets), health_frames=len(health))
    stats.info_frames = len(extras) - len(health)
    if len(health):
        stats.last_health_code = int(b[health[-1] + 2])
    if not len(packets) and not len(extras):
        stats.skipped_bytes = n
        stats.resyncs = int(n > 0)
        _count_rejected(b, bad, stats)
        return stats
    ends = extras + sizes
    first = min(int(packets[0]) if len(packets) else n, int(extras[0]) if len(extras) else n)
    last_end = max(int(packets[-1]) + PACKET_SIZE if len(packets) else 0, int(ends[-1]) if len(ends) else 0)
    stats.skipped_bytes = n - PACKET_SIZE * len(packets) - int(sizes.sum(dtype=np.int64))
    stats.resyncs = gaps + int(first > 0) + int(last_end < n)
    covered = _covered(bad, packets, PACKET_SIZE) | _covered(bad, extras, sizes)
    _count_rejected(b, bad[~covered], stats)
    return stats


def _count_rejected(b: NDArray[np.uint8], rejected: NDArray[np.int64], stats: ParserStats) -> None:
    """Split rejected data-packet windows into CRC errors and implausible packets (CRC passed)."""
    implausible = int(np.count_nonzero(crc_ok(_rows(b, rejected)))) if len(rejected) else 0
    stats.crc_errors = len(rejected) - implausible
    stats.implausible = implausible


class _Columns(NamedTuple):
    speed: NDArray[np.uint16]
    start: NDArray[np.uint16]
    end: NDArray[np.uint16]
    stamp: NDArray[np.uint16]
    crc: NDArray[np.uint8]
    dist: NDArray[np.uint16]
    inten: NDArray[np.uint8]


def _fields_into(b: NDArray[np.uint8], offsets: NDArray[np.int64], out: _Columns, a: int, e: int) -> None:
    """Copy the fields of packets ``a:e`` into *out*.

    Back-to-back packets (all of them, in a clean stream) are read in place
    through strided views; others are gathered into rows first.
    """
    count = e - a
    if not count:
        return
    first = int(offsets[a])
    if int(offsets[e - 1]) - first == (count - 1) * PACKET_SIZE:
        buf, base, stride = b, first, PACKET_SIZE
    else:
        buf, base, stride = _rows(b, offsets[a:e]), 0, _ROW
    out.speed[a:e] = _column(buf, base, stride, count, 2)
    out.start[a:e] = _column(buf, base, stride, count, 4)
    out.end[a:e] = _column(buf, base, stride, count, 42)
    out.stamp[a:e] = _column(buf, base, stride, count, 44)
    out.crc[a:e] = _column(buf, base, stride, count, PACKET_SIZE - 1, "u1")
    out.dist[a:e] = _points(buf, base, stride, count, 6, "<u2")
    out.inten[a:e] = _points(buf, base, stride, count, 8, "u1")


def decode_bytes(data: bytes | bytearray | memoryview | NDArray[np.uint8]) -> DecodedStream:
    """Decode every data packet in *data*, as the streaming parser would."""
    b = np.ascontiguousarray(data) if isinstance(data, np.ndarray) else np.frombuffer(data, dtype=np.uint8)
    n = len(b)
    block = _BLOCK
    _pairs()  # built here once, rather than by each thread that first needs it
    found = _blockwise(lambda a, e: _find(b, a, e), n, block)
    frames = _accept(found)
    while len(frames.unseated):
        # Rare: a valid frame before a chain overlapped one of its links.
        for k in sorted(set((frames.unseated // block).tolist())):
            found[k] = _find(b, k * block, min(k * block + block, n), full=True)
        frames = _accept(found)
    stats = _stats(b, frames)
    offsets = frames.packets

    count = len(offsets)
    out = _Columns(
        np.empty(count, np.uint16),
        np.empty(count, np.uint16),
        np.empty(count, np.uint16),
        np.empty(count, np.uint16),
        np.empty(count, np.uint8),
        np.empty((count, POINTS_PER_PACKET), np.uint16),
        np.empty((count, POINTS_PER_PACKET), np.uint8),
    )
    _blockwise(lambda a, e: _fields_into(b, offsets, out, a, e), count, _BLOCK // PACKET_SIZE)
    return DecodedStream(
        offsets, out.speed, out.start, out.end, out.stamp, out.dist, out.inten, out.crc, stats, n
    )


def _read(path: str | os.PathLike[str]) -> NDArray[np.uint8]:
    """Return the file's bytes, memory-mapped when it is a regular file.

    Mapping skips a copy of the whole file into fresh memory (the page cache
    already holds it), which for a large capture costs about as much as
    decoding it. Pipes, devices and empty files are read instead. (Like any
    mapping, it assumes the file is not truncated while being decoded;
    bytes appended meanwhile are simply not seen.)
    """
    with open(path, "rb") as f:
        info = os.fstat(f.fileno())
        if stat.S_ISREG(info.st_mode) and info.st_size > 0:
            try:
                view = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
            except (OSError, ValueError):
                pass
            else:
                return np.frombuffer(view, dtype=np.uint8)
        return np.fromfile(f, dtype=np.uint8)


def decode_file(path: str | os.PathLike[str]) -> DecodedStream:
    """Decode a capture file.

    :raises DeviceError: the file cannot be read.
    """
    try:
        data = _read(path)
    except OSError as exc:
        raise DeviceError(f"cannot read capture: {exc.strerror or exc}", device=os.fspath(path)) from exc
    return decode_bytes(data)
