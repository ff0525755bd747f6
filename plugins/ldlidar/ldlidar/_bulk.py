"""Vectorised decoder for whole captures.

It applies the streaming parser's rule (a frame is accepted when its CRC is
valid and it does not start inside an accepted frame; everything else costs
one byte) to a whole buffer at once, so both give the same packets and the
same counters. The work is done in blocks small enough to stay in the CPU
cache, on a couple of threads (NumPy releases the GIL in the loops used):

1. find every ``54 2C`` / ``54 E0`` / ``54 0F`` candidate and check its CRC;
   the CRC is linear over GF(2), so a window's syndrome is the XOR of one
   table lookup per byte pair;
2. resolve the rare valid frames that start inside other valid frames;
3. gather the accepted packets' fields and per-point angles.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from ._errors import DeviceError
from ._parser import MAX_SPAN, ParserStats
from ._protocol import (
    ANGLE_UNITS,
    CRC_TABLE,
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

__all__ = ["DecodedStream", "crc_rows", "decode_bytes", "decode_file"]

_ROW = PACKET_SIZE + 1
"""Packets are gathered into 48-byte rows so that every u16 field is aligned."""
_BLOCK = 1 << 20
_SUB = SUBUNITS
_TURN = TURN_SUBUNITS
_T = TypeVar("_T")


def _pair_tables() -> NDArray[np.uint8]:
    """Syndrome contribution of each aligned byte pair of a 48-byte row, flattened.

    Row byte 46 is the CRC itself (contributing its own value) and byte 47
    belongs to the next packet (contributing nothing), so a row is valid
    exactly when the XOR of the 24 lookups is zero. Pair ``j`` with value
    ``w`` is at ``(j << 16) + w``.
    """
    table = np.array(CRC_TABLE, dtype=np.uint8)
    single = np.zeros((_ROW, 256), dtype=np.uint8)
    cur = np.arange(256, dtype=np.uint8)
    single[PACKET_SIZE - 1] = cur
    for i in range(PACKET_SIZE - 2, -1, -1):
        cur = table[cur]
        single[i] = cur
    lo = np.arange(1 << 16) & 0xFF
    hi = np.arange(1 << 16) >> 8
    return (single[0::2][:, lo] ^ single[1::2][:, hi]).reshape(-1)


_PAIR_BASE = np.arange(_ROW // 2, dtype=np.intp) << 16
"""Offset of each pair's table in the flattened tables."""


_PAIRS: NDArray[np.uint8] | None = None


def _pairs() -> NDArray[np.uint8]:
    global _PAIRS
    if _PAIRS is None:
        _PAIRS = _pair_tables()
    return _PAIRS


def crc_rows(rows: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Return the CRC of bytes 0..45 of each row of an ``(n, 47)`` or ``(n, 48)`` array."""
    padded = np.zeros((len(rows), _ROW), dtype=np.uint8)
    padded[:, : PACKET_SIZE - 1] = rows[:, : PACKET_SIZE - 1]
    index = np.add(padded.view("<u2"), _PAIR_BASE, dtype=np.intp)
    folded = _pairs().take(index).view(np.uint64)
    crc: NDArray[np.uint64] = folded[:, 0] ^ folded[:, 1]
    crc ^= folded[:, 2]
    crc ^= crc >> 32
    crc ^= crc >> 16
    crc ^= crc >> 8
    return crc.astype(np.uint8)


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

    def wraps(self) -> NDArray[np.int64]:
        """Return the flat point indices where a new revolution begins.

        A revolution begins where the angle drops by more than half a turn
        from one point to the next, the rule :class:`ScanAssembler` uses.
        """
        # Accepted packets have both angles below a full turn (see MAX_SPAN).
        start = self.start_angle.astype(np.int32)
        end = self.end_angle.astype(np.int32)
        span = end - start
        inside = np.flatnonzero(span < 0)
        span_in = span[inside].astype(np.int64) + ANGLE_UNITS
        # First point k whose position start*11 + span*k reaches a full turn.
        k = -((start[inside].astype(np.int64) * _SUB - _TURN) // span_in)
        between = np.flatnonzero(start[1:] < end[:-1] - ANGLE_UNITS // 2) + 1
        flat = np.concatenate((inside * POINTS_PER_PACKET + k, between * POINTS_PER_PACKET))
        flat.sort()
        return flat

    def revolutions(self) -> int:
        """Return the number of complete revolutions (between two wraps)."""
        return max(len(self.wraps()) - 1, 0)

    def device_times(self) -> NDArray[np.int64]:
        """Return each packet's device timestamp in ms, unwrapped from 0."""
        if not len(self):
            return np.zeros(0, dtype=np.int64)
        steps = np.mod(np.diff(self.timestamp.astype(np.int64)), TIMESTAMP_WRAP_MS)
        out = np.empty(len(self), dtype=np.int64)
        out[0] = 0
        np.cumsum(steps, out=out[1:])
        return out


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
    np.multiply(pos, np.float32(1 / (100 * _SUB)), out=out)


def _blockwise(fn: Callable[[int, int], _T], n: int, block: int) -> list[_T]:
    """Run ``fn(a, b)`` over consecutive ranges of ``range(n)``, on a few threads."""
    ranges = [(a, min(a + block, n)) for a in range(0, n, block)]
    if len(ranges) < 4 or _THREADS < 2:
        return [fn(a, b) for a, b in ranges]
    with ThreadPoolExecutor(_THREADS) as pool:
        return list(pool.map(lambda r: fn(*r), ranges))


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


def _find(
    b: NDArray[np.uint8], a: int, e: int
) -> tuple[NDArray[np.int64], NDArray[np.int64], list[int], list[int]]:
    """Check every candidate frame starting in ``b[a:e]``.

    Return valid packet offsets, bad-CRC packet offsets, and valid health and
    info frame offsets.
    """
    n = len(b)
    seg = b[a : min(e + 1, n)]
    heads = np.flatnonzero(seg[:-1] == HEADER)
    kinds = seg[heads + 1]
    heads += a
    cand = heads[kinds == PACKET_TYPE]
    cand = cand[cand <= n - PACKET_SIZE]
    rows = _rows(b, cand)
    words = rows.view("<u2")
    index = np.add(words, _PAIR_BASE, dtype=np.intp)
    lookups = _pairs().take(index)
    folded = lookups.view(np.uint64)
    syndrome = folded[:, 0] ^ folded[:, 1]
    syndrome ^= folded[:, 2]
    syndrome ^= syndrome >> 32
    syndrome ^= syndrome >> 16
    syndrome ^= syndrome >> 8
    syndrome &= 0xFF
    start = words[:, 2].astype(np.int32)
    end = words[:, 21].astype(np.int32)
    ok = (syndrome == 0) & (start < ANGLE_UNITS) & (end < ANGLE_UNITS) & ((end - start) % ANGLE_UNITS <= MAX_SPAN)
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


def decode_bytes(data: bytes | bytearray | memoryview | NDArray[np.uint8]) -> DecodedStream:
    """Decode every data packet in *data*, as the streaming parser would."""
    b = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    n = len(b)
    found = _blockwise(lambda a, e: _find(b, a, e), n, _BLOCK)
    good = [f[0] for f in found]
    bad = np.concatenate([f[1] for f in found]) if found else np.zeros(0, np.int64)
    health = _merge(f[2] for f in found)
    info = _merge(f[3] for f in found)
    packets = np.concatenate(good) if good else np.zeros(0, np.int64)

    extra = np.concatenate((health, info))
    if len(extra):
        extra_sizes = np.concatenate(
            (np.full(len(health), HEALTH_SIZE, np.uint8), np.full(len(info), INFO_SIZE, np.uint8))
        )
        order = np.argsort(extra)
        at = np.searchsorted(packets, extra[order])
        starts = np.insert(packets, at, extra[order])
        sizes = np.insert(np.full(len(packets), PACKET_SIZE, np.uint8), at, extra_sizes[order])
    else:
        starts = packets
        sizes = np.full(len(packets), PACKET_SIZE, np.uint8)
    step = np.diff(starts)
    if np.any(step < sizes[:-1]):
        accept = _resolve(starts, starts + sizes)
        starts = starts[accept]
        sizes = sizes[accept]
        step = np.diff(starts)
    packets = starts[sizes == PACKET_SIZE] if len(extra) else starts
    gaps = step > sizes[:-1]

    stats = ParserStats(packets=len(packets))
    stats.health_frames = int(np.count_nonzero(sizes == HEALTH_SIZE))
    stats.info_frames = int(np.count_nonzero(sizes == INFO_SIZE))
    if stats.health_frames:
        last = int(starts[np.flatnonzero(sizes == HEALTH_SIZE)[-1]])
        stats.last_health_code = int(b[last + 2])
    if len(starts):
        last_end = int(starts[-1] + sizes[-1])
        stats.skipped_bytes = n - int(sizes.sum(dtype=np.int64))
        stats.resyncs = int(np.count_nonzero(gaps)) + int(starts[0] > 0) + int(last_end < n)
        inside = np.searchsorted(starts, bad, side="right") - 1
        covered = (inside >= 0) & (bad < starts[inside] + sizes[inside])
        stats.crc_errors = int(len(bad) - np.count_nonzero(covered))
    else:
        stats.skipped_bytes = n
        stats.resyncs = int(n > 0)
        stats.crc_errors = len(bad)

    count = len(packets)
    offsets = packets
    speed = np.empty(count, np.uint16)
    start = np.empty(count, np.uint16)
    end = np.empty(count, np.uint16)
    stamp = np.empty(count, np.uint16)
    crc = np.empty(count, np.uint8)
    dist = np.empty((count, POINTS_PER_PACKET), np.uint16)
    inten = np.empty((count, POINTS_PER_PACKET), np.uint8)

    def fields(a: int, e: int) -> None:
        rows = _rows(b, offsets[a:e])
        words = rows.view("<u2")
        speed[a:e] = words[:, 1]
        start[a:e] = words[:, 2]
        end[a:e] = words[:, 21]
        stamp[a:e] = words[:, 22]
        crc[a:e] = rows[:, PACKET_SIZE - 1]
        dist[a:e] = np.ndarray(
            (e - a, POINTS_PER_PACKET), dtype="<u2", buffer=rows, offset=6, strides=(_ROW, 3)
        )
        inten[a:e] = rows[:, 8:42:3]

    _blockwise(fields, count, _BLOCK // PACKET_SIZE)
    return DecodedStream(offsets, speed, start, end, stamp, dist, inten, crc, stats, n)


def decode_file(path: str | os.PathLike[str]) -> DecodedStream:
    """Decode a capture file.

    :raises DeviceError: the file cannot be read.
    """
    try:
        data = np.fromfile(Path(path), dtype=np.uint8)
    except OSError as exc:
        raise DeviceError(f"cannot read capture: {exc.strerror or exc}", device=os.fspath(path)) from exc
    return decode_bytes(data)
