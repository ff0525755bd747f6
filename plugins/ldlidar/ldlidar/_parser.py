"""Streaming parser: bytes in arbitrary chunks, packets out.

The vendor parser drops a whole 47-byte window when its CRC fails, losing a
good packet whose header hides inside a truncated one. This parser advances
one byte after any failed window and searches again, so every valid frame
that is not inside an accepted frame is found. (A data packet is valid when
its CRC matches and its angles are possible; see :data:`MAX_SPAN`.) The bulk decoder
(:func:`ldlidar.decode_bytes`) implements the same rule with NumPy and must
agree with this parser byte for byte.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

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
    Packet,
    _unpack,
)

__all__ = ["FRAME_SIZES", "MAX_SPAN", "ParserStats", "StreamParser"]

FRAME_SIZES = {PACKET_TYPE: PACKET_SIZE, HEALTH_TYPE: HEALTH_SIZE, INFO_TYPE: INFO_SIZE}
"""Length of each frame type the parser knows, keyed by the byte after the header."""


MAX_SPAN = 9000
"""Largest angle (0.01 degree) a packet's 12 points may cover.

An 8-bit CRC passes one random window in 256; a truncated packet glued to
the next one is such a window, and accepting it would swallow the good packet
behind it. Real packets cover a few degrees (about 10 on an LD06 at 13 Hz)
and both angles are below 360, so requiring that too rejects about 12 of 13
such false windows.
"""


def _plausible(buf: bytearray, pos: int) -> bool:
    start = buf[pos + 4] | buf[pos + 5] << 8
    end = buf[pos + 42] | buf[pos + 43] << 8
    return start < ANGLE_UNITS and end < ANGLE_UNITS and (end - start) % ANGLE_UNITS <= MAX_SPAN


@dataclass(slots=True)
class ParserStats:
    """What a parser has seen so far.

    :param packets: CRC-valid data packets delivered.
    :param crc_errors: 47-byte data-packet windows rejected, because their
        CRC failed or their angles are impossible (see :data:`MAX_SPAN`);
        each costs one byte of resync, not the window.
    :param resyncs: times the parser lost and regained framing: each maximal
        run of discarded bytes counts once (so a capture that starts
        mid-packet counts one).
    :param skipped_bytes: bytes that belonged to no accepted frame.
    :param health_frames: valid health frames seen (and skipped).
    :param info_frames: valid manufacture-information frames seen (and skipped).
    :param last_health_code: the error code of the latest health frame.
    """

    packets: int = 0
    crc_errors: int = 0
    resyncs: int = 0
    skipped_bytes: int = 0
    health_frames: int = 0
    info_frames: int = 0
    last_health_code: int | None = None

    def as_dict(self) -> dict[str, int | None]:
        return asdict(self)


class StreamParser:
    """Incremental frame parser; feed it chunks as they arrive.

    Bytes that might begin a frame are held until enough follow to decide;
    :meth:`flush` decides them at the end of a stream.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._in_gap = False
        self.stats = ParserStats()

    @property
    def pending(self) -> int:
        """Bytes held back, waiting for the rest of a possible frame."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget held bytes (after a reopen the stream restarts); keep counters."""
        if self._buf or self._in_gap:
            self.stats.skipped_bytes += len(self._buf)
            self.stats.resyncs += 1
        self._buf.clear()
        self._in_gap = False

    def feed(self, data: bytes | bytearray | memoryview) -> list[Packet]:
        """Consume *data*; return the data packets it completed, in order."""
        self._buf += data
        return self._run(final=False)

    def flush(self) -> list[Packet]:
        """Treat the stream as ended: decide every held byte, return late packets."""
        packets = self._run(final=True)
        if self._in_gap:
            self.stats.resyncs += 1
            self._in_gap = False
        return packets

    def _run(self, *, final: bool) -> list[Packet]:
        buf = self._buf
        stats = self.stats
        table = CRC_TABLE
        out: list[Packet] = []
        n = len(buf)
        pos = 0
        skipped = 0
        while pos < n:
            i = buf.find(HEADER, pos)
            if i < 0:
                skipped += n - pos
                pos = n
                break
            skipped += i - pos
            pos = i
            if pos + 1 >= n:
                if final:
                    skipped += 1
                    pos += 1
                break
            kind = buf[pos + 1]
            size = FRAME_SIZES.get(kind)
            if size is None:
                skipped += 1
                pos += 1
                continue
            end = pos + size
            if end > n:
                if not final:
                    break
                skipped += 1
                pos += 1
                continue
            crc = 0
            for byte in buf[pos : end - 1]:
                crc = table[crc ^ byte]
            if crc != buf[end - 1] or (kind == PACKET_TYPE and not _plausible(buf, pos)):
                if kind == PACKET_TYPE:
                    stats.crc_errors += 1
                skipped += 1
                pos += 1
                continue
            if skipped:
                stats.skipped_bytes += skipped
                skipped = 0
                self._in_gap = True
            if self._in_gap:
                stats.resyncs += 1
                self._in_gap = False
            if kind == PACKET_TYPE:
                out.append(_unpack(buf[pos:end]))
                stats.packets += 1
            elif kind == HEALTH_TYPE:
                stats.health_frames += 1
                stats.last_health_code = buf[pos + 2]
            else:
                stats.info_frames += 1
            pos = end
        if skipped:
            stats.skipped_bytes += skipped
            self._in_gap = True
        del buf[:pos]
        return out
