"""Wire format of the LDRobot LD-series serial LiDARs.

A data packet is 47 bytes, little-endian::

    0      header 0x54
    1      ver_len 0x2C (low 5 bits: 12 points)
    2..3   rotation speed, degrees per second
    4..5   start angle, 0.01 degree
    6..41  12 points: u16 distance (mm), u8 intensity
    42..43 end angle, 0.01 degree
    44..45 device timestamp, ms, wrapping at 30000
    46     CRC-8 of bytes 0..45

Health (``54 E0 code crc``, 4 bytes) and manufacture information (``54 0F``,
23 bytes) frames share the header. The vendor documents their length but not
their checksum; we assume the same CRC-8 over all bytes but the last, so a
frame that fails it is treated as noise (its bytes counted as skipped), never
as a reason to lose a data packet.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final

from container import clip

from ._errors import ProtocolError

__all__ = [
    "BOUNDARY",
    "CRC_TABLE",
    "HEADER",
    "HEALTH_SIZE",
    "HEALTH_TYPE",
    "INFO_SIZE",
    "INFO_TYPE",
    "MODELS",
    "PACKET_SIZE",
    "PACKET_TYPE",
    "POINTS_PER_PACKET",
    "TIMESTAMP_WRAP_MS",
    "Model",
    "Packet",
    "crc8",
    "decode_packet",
    "encode_health",
    "encode_info",
    "encode_packet",
    "get_model",
]

HEADER: Final = 0x54
PACKET_TYPE: Final = 0x2C
HEALTH_TYPE: Final = 0xE0
INFO_TYPE: Final = 0x0F
PACKET_SIZE: Final = 47
HEALTH_SIZE: Final = 4
INFO_SIZE: Final = 23
POINTS_PER_PACKET: Final = 12
TIMESTAMP_WRAP_MS: Final = 30000
ANGLE_UNITS: Final = 36000
"""Angles travel in hundredths of a degree; a full turn is this many units."""
SUBUNITS: Final = 11
"""Interpolated point angles are exact in 1/11 of the wire's unit."""
TURN_SUBUNITS: Final = ANGLE_UNITS * SUBUNITS
BOUNDARY: Final = ANGLE_UNITS // 2
"""Device angle (0.01 degree) where one revolution ends and the next begins:
the back of the sensor, so that a scan's array runs in time order (see
:mod:`ldlidar._scan`)."""

_CRC_POLY: Final = 0x4D


def _crc_table() -> tuple[int, ...]:
    table = []
    for value in range(256):
        crc = value
        for _ in range(8):
            crc = ((crc << 1) ^ _CRC_POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


CRC_TABLE: Final = _crc_table()


def crc8(data: bytes | bytearray | memoryview, /, *, crc: int = 0) -> int:
    """Return the LD-series CRC-8 of *data* (poly 0x4D, init 0, no reflection).

    :param crc: a running value, to checksum data given in pieces.
    """
    table = CRC_TABLE
    for byte in data:
        crc = table[crc ^ byte]
    return crc


@dataclass(frozen=True, slots=True)
class Model:
    """Line-rate figures of one LiDAR model.

    :param name: the canonical name, a key of :data:`MODELS`.
    :param baudrate: the serial speed the device transmits at (8N1).
    :param packets_per_second: data packets per second (points / 12).
    :param points_per_second: measurements per second.
    :param scan_hz: the usual rotation rate.
    """

    name: str
    baudrate: int
    packets_per_second: int
    points_per_second: int
    scan_hz: float = 10.0

    @property
    def bytes_per_second(self) -> int:
        """Bytes the line carries at full speed (10 bits per byte on 8N1)."""
        return self.baudrate // 10

    @property
    def packets_per_revolution(self) -> float:
        return self.packets_per_second / self.scan_hz


MODELS: Final[Mapping[str, Model]] = MappingProxyType(
    {
        "LD06": Model("LD06", 230400, 375, 4500),
        "LD19": Model("LD19", 230400, 375, 4500),
        "STL27L": Model("STL27L", 921600, 1800, 21600),
    }
)


def get_model(name: str) -> Model:
    """Return the model called *name*.

    Accepts the spellings users meet in other drivers: ``LD06``, ``ld19``,
    ``LDLiDAR_LD19``, ``STL-27L``, ``stl27l``.
    """
    key = name.upper().replace("-", "").replace("_", "")
    key = key.removeprefix("LDLIDAR")
    try:
        return MODELS[key]
    except KeyError:
        raise ValueError(
            f"unknown LiDAR model {clip(name, quote=True)}; known: {', '.join(MODELS)}"
        ) from None


_STRUCT = struct.Struct("<BBHH" + "HB" * POINTS_PER_PACKET + "HHB")


@dataclass(frozen=True, slots=True)
class Packet:
    """One decoded data packet, fields in device units.

    Angles are hundredths of a degree, clockwise from the sensor's front;
    distances millimetres (0: no valid return); timestamp milliseconds on the
    device's clock, wrapping at :data:`TIMESTAMP_WRAP_MS`.
    """

    speed: int
    start_angle: int
    end_angle: int
    timestamp: int
    distances: tuple[int, ...]
    intensities: tuple[int, ...]
    crc: int

    @property
    def start_deg(self) -> float:
        return self.start_angle / 100

    @property
    def end_deg(self) -> float:
        return self.end_angle / 100

    @property
    def span(self) -> int:
        """Angle covered from the first to the last point, 0.01 degree, wrap-aware."""
        return (self.end_angle - self.start_angle) % ANGLE_UNITS

    def positions(self) -> list[int]:
        """Return each point's angle in 1/11 of 0.01 degree, in [0, 11 * 36000).

        Linear interpolation of 12 points divides the span by 11, so these
        integer units make it exact: the streaming and bulk decoders then
        agree on which point starts a revolution.
        """
        base = (self.start_angle % ANGLE_UNITS) * SUBUNITS
        span = self.span
        return [(base + span * k) % TURN_SUBUNITS for k in range(POINTS_PER_PACKET)]

    def angles(self) -> list[float]:
        """Return each point's angle in degrees in [0, 360), clockwise from the front."""
        return [p / (100 * SUBUNITS) for p in self.positions()]


def encode_packet(
    *,
    speed: int,
    start_angle: int,
    end_angle: int,
    timestamp: int,
    distances: Sequence[int] | Iterable[int],
    intensities: Sequence[int] | Iterable[int],
) -> bytes:
    """Return a 47-byte data packet with a valid CRC.

    Angles are hundredths of a degree and are reduced modulo a full turn;
    the timestamp is reduced modulo :data:`TIMESTAMP_WRAP_MS`.
    """
    dist = list(distances)
    inten = list(intensities)
    if len(dist) != POINTS_PER_PACKET or len(inten) != POINTS_PER_PACKET:
        raise ValueError(
            f"a packet carries {POINTS_PER_PACKET} distances and intensities, "
            f"got {len(dist)} and {len(inten)}"
        )
    points: list[int] = []
    for d, i in zip(dist, inten, strict=True):
        points += (d, i)
    body = _STRUCT.pack(
        HEADER,
        PACKET_TYPE,
        speed,
        start_angle % ANGLE_UNITS,
        *points,
        end_angle % ANGLE_UNITS,
        timestamp % TIMESTAMP_WRAP_MS,
        0,
    )[:-1]
    return body + bytes((crc8(body),))


def decode_packet(data: bytes | bytearray | memoryview) -> Packet:
    """Decode one 47-byte data packet.

    :raises ProtocolError: wrong length, header or CRC.
    """
    if len(data) != PACKET_SIZE:
        raise ProtocolError(f"a data packet is {PACKET_SIZE} bytes, got {len(data)}")
    if data[0] != HEADER or data[1] != PACKET_TYPE:
        raise ProtocolError(f"not a data packet header: {bytes(data[:2]).hex(' ')}")
    expected = crc8(memoryview(data)[:-1])
    if expected != data[-1]:
        raise ProtocolError(f"bad CRC: {data[-1]:#04x}, expected {expected:#04x}")
    return _unpack(data)


def _unpack(data: bytes | bytearray | memoryview) -> Packet:
    """Build a :class:`Packet` from a window already known to be valid."""
    fields = _STRUCT.unpack(data)
    return Packet(
        speed=fields[2],
        start_angle=fields[3],
        end_angle=fields[-3],
        timestamp=fields[-2],
        distances=fields[4:-3:2],
        intensities=fields[5:-3:2],
        crc=fields[-1],
    )


def encode_health(code: int) -> bytes:
    """Return a 4-byte health frame carrying error *code*."""
    body = bytes((HEADER, HEALTH_TYPE, code & 0xFF))
    return body + bytes((crc8(body),))


def encode_info(payload: bytes = bytes(INFO_SIZE - 3)) -> bytes:
    """Return a 23-byte manufacture-information frame around *payload* (20 bytes)."""
    if len(payload) != INFO_SIZE - 3:
        raise ValueError(f"an info frame carries {INFO_SIZE - 3} bytes, got {len(payload)}")
    body = bytes((HEADER, INFO_TYPE)) + payload
    return body + bytes((crc8(body),))
