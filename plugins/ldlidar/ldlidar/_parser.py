"""Streaming parser: bytes in arbitrary chunks, packets out.

The vendor parser drops a whole 47-byte window when its CRC fails, losing a
good packet whose header hides inside a truncated one. This parser advances
one byte after any failed window and searches again, so every valid frame
that is not inside an accepted frame is found. (A data packet is valid when
its CRC matches and its angles are possible; see :data:`MAX_SPAN`.)

Health (4 bytes) and information (23 bytes) frames carry far less to check
than a data packet: one health frame in 256 made of noise passes its CRC. So
they are recognised only when complete and valid *and no valid data packet
starts inside them*; otherwise the data packet wins (a truncated health frame
``54 E0 xx`` glued to the next packet's ``54`` would swallow its header). The
bulk decoder (:func:`ldlidar.decode_bytes`) implements the same rules with
NumPy and must agree with this parser byte for byte.
"""

from __future__ import annotations

import struct
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

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

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

__all__ = ["FRAME_SIZES", "MAX_SPAN", "ParserStats", "StreamParser"]

_PACKET_HEADER = bytes((HEADER, PACKET_TYPE))
#: Enough first and second bytes of back-to-back packets for any chunk a read returns.
_HEADS = bytes((HEADER,)) * 4096
_TYPES = bytes((PACKET_TYPE,)) * 4096
#: Start and end angle of a 47-byte data packet.
_ANGLES = struct.Struct("<4xH36xH3x")

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


def _packet_at(buf: bytearray, pos: int) -> bool:
    """Whether a valid data packet starts at *pos* (all 47 bytes are in *buf*)."""
    crc = 0
    table = CRC_TABLE
    for byte in buf[pos : pos + PACKET_SIZE - 1]:
        crc = table[crc ^ byte]
    return crc == buf[pos + PACKET_SIZE - 1] and _plausible(buf, pos)


def _packet_inside(buf: bytearray, pos: int, end: int, *, final: bool) -> bool | None:
    """Whether a valid data packet starts inside the frame ``buf[pos:end]``.

    ``None``: one might, but its bytes have not all arrived yet.
    """
    n = len(buf)
    if n == end and buf[end - 1] == HEADER:
        return False if final else None  # the byte saying what starts there is still to come
    q = buf.find(_PACKET_HEADER, pos + 1, end + 1)
    while 0 <= q < end:
        if q + PACKET_SIZE > n:
            if not final:
                return None
        elif _packet_at(buf, q):
            return True
        q = buf.find(_PACKET_HEADER, q + 1, end + 1)
    return False


@dataclass(slots=True)
class ParserStats:
    """What a parser has seen so far.

    :param packets: CRC-valid data packets delivered.
    :param crc_errors: 47-byte data-packet windows rejected because their
        CRC failed (line noise, a wrong baud rate); each costs one byte of
        resync, not the window.
    :param implausible: data-packet windows whose CRC passed but whose angles
        are impossible (see :data:`MAX_SPAN`), rejected alike: a device
        fault, or one false CRC match in 256 of noise; not line noise.
    :param resyncs: times the parser lost and regained framing: each maximal
        run of discarded bytes counts once (so a capture that starts
        mid-packet counts one).
    :param skipped_bytes: bytes that belonged to no accepted frame.
    :param health_frames: valid health frames seen (and skipped); a frame
        with a valid data packet starting inside it is not one.
    :param info_frames: valid manufacture-information frames seen (and skipped), likewise.
    :param last_health_code: the error code of the latest health frame.
    """

    packets: int = 0
    crc_errors: int = 0
    implausible: int = 0
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
        return [_unpack(raw) for raw in self._run(final=False)]

    def feed_rows(self, data: bytes | bytearray | memoryview) -> NDArray[np.uint8]:
        """Consume *data*; return the data packets it completed as ``(n, 47)`` rows.

        The same packets and counters as :meth:`feed`, for much less work on
        a clean stream: held bytes that start with back-to-back packets (what
        a healthy device sends) are checked with NumPy all at once, and only
        what follows the first break goes through the byte-by-byte search.
        """
        import numpy as np

        from ._crc import crc_ok

        self._buf += data
        buf = self._buf
        whole = len(buf) // PACKET_SIZE
        # A chain of whole packets from the first held byte, header by header
        # (compared as bytes: no array call for what is nearly always true).
        links = whole
        size = whole * PACKET_SIZE
        if buf[0:size:PACKET_SIZE] != _HEADS[:whole] or buf[1:size:PACKET_SIZE] != _TYPES[:whole]:
            links = next(
                i for i in range(whole) if buf[i * PACKET_SIZE : i * PACKET_SIZE + 2] != _PACKET_HEADER
            )
        chain = bytes(buf[: links * PACKET_SIZE])
        rows = np.frombuffer(chain, dtype=np.uint8).reshape(links, PACKET_SIZE)
        if links:
            ok = crc_ok(rows)
            for i, (start, end) in enumerate(_ANGLES.iter_unpack(chain)):
                if not ok[i] or not (
                    start < ANGLE_UNITS and end < ANGLE_UNITS and (end - start) % ANGLE_UNITS <= MAX_SPAN
                ):
                    links = i
                    rows = rows[:links]
                    break
        if links:
            del buf[: links * PACKET_SIZE]
            self.stats.packets += links
            if self._in_gap:
                self.stats.resyncs += 1
                self._in_gap = False
        rest = self._run(final=False)
        if not rest:
            return rows
        tail = np.frombuffer(b"".join(rest), dtype=np.uint8).reshape(len(rest), PACKET_SIZE)
        return np.concatenate((rows, tail))

    def flush(self) -> list[Packet]:
        """Treat the stream as ended: decide every held byte, return late packets."""
        packets = [_unpack(raw) for raw in self._run(final=True)]
        if self._in_gap:
            self.stats.resyncs += 1
            self._in_gap = False
        return packets

    def _run(self, *, final: bool) -> list[bytes]:
        buf = self._buf
        stats = self.stats
        table = CRC_TABLE
        out: list[bytes] = []
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
                    if crc != buf[end - 1]:
                        stats.crc_errors += 1
                    else:
                        stats.implausible += 1
                skipped += 1
                pos += 1
                continue
            if kind != PACKET_TYPE:
                inside = _packet_inside(buf, pos, end, final=final)
                if inside is None:
                    break  # decide when the packet that may start inside has arrived
                if inside:
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
                out.append(bytes(buf[pos:end]))
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
