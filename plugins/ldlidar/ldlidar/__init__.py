"""LDRobot LD06 / LD19 / STL-27L serial LiDAR driver core (no ROS).

The pieces, bottom up: the wire format (:func:`decode_packet`,
:func:`encode_packet`, :data:`MODELS`), a streaming parser
(:class:`StreamParser`) and a bulk decoder that agrees with it
(:func:`decode_bytes`), revolution assembly (:class:`ScanAssembler`), byte
sources (:class:`SerialSource`, :class:`ReplaySource`), a device facade that
reopens after unplugs (:class:`Lidar`), an emulator (:class:`Emulator`) and a
capture player (:class:`Replayer`).

The asyncio-based and NumPy-based names are imported on first use, so that
``python -m ldlidar decode`` starts without asyncio or pyserial and loads
only the modules it needs (and can tune NumPy before loading it).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ._errors import DeviceError, DeviceRefused, LidarError, ProtocolError
from ._parser import ParserStats, StreamParser
from ._protocol import (
    HEADER,
    HEALTH_SIZE,
    HEALTH_TYPE,
    INFO_SIZE,
    INFO_TYPE,
    MODELS,
    PACKET_SIZE,
    PACKET_TYPE,
    POINTS_PER_PACKET,
    TIMESTAMP_WRAP_MS,
    Model,
    Packet,
    crc8,
    decode_packet,
    encode_health,
    encode_info,
    encode_packet,
    get_model,
)

if TYPE_CHECKING:
    from ._bulk import DecodedStream, decode_bytes, decode_file
    from ._emulator import Emulator, PacketGenerator, Replayer, Room
    from ._lidar import Lidar
    from ._render import encode_png, render_scan
    from ._scan import DeviceClock, Direction, Scan, ScanAssembler
    from ._sources import ReplaySource, SerialSource, Source, open_source

__all__ = [
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
    "DecodedStream",
    "DeviceClock",
    "DeviceError",
    "DeviceRefused",
    "Direction",
    "Emulator",
    "Lidar",
    "LidarError",
    "Model",
    "Packet",
    "PacketGenerator",
    "ParserStats",
    "ProtocolError",
    "ReplaySource",
    "Replayer",
    "Room",
    "Scan",
    "ScanAssembler",
    "SerialSource",
    "Source",
    "StreamParser",
    "crc8",
    "decode_bytes",
    "decode_file",
    "decode_packet",
    "encode_health",
    "encode_info",
    "encode_packet",
    "encode_png",
    "get_model",
    "open_source",
    "render_scan",
]

_LAZY = {
    "DecodedStream": "_bulk",
    "decode_bytes": "_bulk",
    "decode_file": "_bulk",
    "encode_png": "_render",
    "render_scan": "_render",
    "DeviceClock": "_scan",
    "Direction": "_scan",
    "Scan": "_scan",
    "ScanAssembler": "_scan",
    "Emulator": "_emulator",
    "PacketGenerator": "_emulator",
    "Replayer": "_emulator",
    "Room": "_emulator",
    "Lidar": "_lidar",
    "ReplaySource": "_sources",
    "SerialSource": "_sources",
    "Source": "_sources",
    "open_source": "_sources",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
