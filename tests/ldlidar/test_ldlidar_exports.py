from __future__ import annotations

from pathlib import Path

import container
import ldlidar
import ldlidar.plugin
from tests.ldlidar.ldlidar_support import CAPTURE, decode_command_modules

EXPECTED = {
    "HEADER", "HEALTH_SIZE", "HEALTH_TYPE", "INFO_SIZE", "INFO_TYPE", "MODELS",
    "PACKET_SIZE", "PACKET_TYPE", "POINTS_PER_PACKET", "TIMESTAMP_WRAP_MS",
    "DecodedStream", "DeviceClock", "DeviceError", "DeviceRefused", "Direction", "Emulator", "Lidar",
    "LidarError", "Model", "Packet", "PacketGenerator", "ParserStats", "ProtocolError",
    "ReplaySource", "Replayer", "Room", "Scan", "ScanAssembler", "SerialSource", "Source",
    "StreamParser", "crc8", "decode_bytes", "decode_file", "decode_packet",
    "encode_health", "encode_info", "encode_packet", "encode_png", "get_model",
    "open_source", "render_scan",
}


def test_public_names_are_exactly_the_curated_set() -> None:
    assert set(ldlidar.__all__) == EXPECTED


def test_every_public_name_resolves() -> None:
    for name in ldlidar.__all__:
        assert getattr(ldlidar, name) is not None, name


def test_unknown_attribute_raises() -> None:
    try:
        ldlidar.nope  # noqa: B018
    except AttributeError as exc:
        assert "nope" in str(exc)
    else:
        raise AssertionError("no AttributeError")


def test_errors_form_one_hierarchy() -> None:
    assert issubclass(ldlidar.ProtocolError, ldlidar.LidarError)
    assert issubclass(ldlidar.DeviceError, ldlidar.LidarError)
    assert issubclass(ldlidar.DeviceRefused, ldlidar.DeviceError)
    err = ldlidar.DeviceError("gone", device="/dev/ttyUSB0")
    assert err.device == "/dev/ttyUSB0" and "gone" in str(err)


def test_errors_sit_under_the_containers_hierarchy() -> None:
    assert issubclass(ldlidar.LidarError, container.ContainerError)
    assert issubclass(ldlidar.DeviceError, container.DeviceError)
    err = ldlidar.DeviceError("gone", device="/dev/ttyUSB0")
    assert (str(err), err.reason) == ("/dev/ttyUSB0: gone", "gone")
    assert ldlidar.ProtocolError("bad CRC").reason == "bad CRC"


def test_decode_command_imports_neither_asyncio_serial_nor_rclpy(tmp_path: Path) -> None:
    capture = CAPTURE if CAPTURE.is_file() else tmp_path / "empty.bin"
    capture.touch(exist_ok=True)
    loaded = decode_command_modules(capture)
    bad = sorted(m for m in loaded if m.split(".")[0] in ("asyncio", "serial", "serial_asyncio", "rclpy"))
    assert bad == []


def test_plugin_module_exports_the_node_and_its_hook() -> None:
    assert set(ldlidar.plugin.__all__) == {
        "AUTO_PORT_PATTERNS", "DIAGNOSTICS_PERIOD", "SCAN_QOS", "SCAN_QOS_OVERRIDES", "LdLidarNode",
        "find_serial_ports", "register_node_types", "to_laser_scan",
    }
    for name in ldlidar.plugin.__all__:
        assert getattr(ldlidar.plugin, name) is not None, name
