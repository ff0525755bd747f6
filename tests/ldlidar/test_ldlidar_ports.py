"""Finding an attached LiDAR for ``comm.serial_port: auto``."""

from __future__ import annotations

from pathlib import Path

from ldlidar.plugin import AUTO_PORT_PATTERNS, find_serial_ports


def test_ports_come_in_pattern_order_each_once(tmp_path: Path) -> None:
    for name in ("ttyUSB1", "ttyUSB0", "ttyACM0"):
        (tmp_path / name).touch()
    patterns = (f"{tmp_path}/ttyACM*", f"{tmp_path}/ttyUSB*", f"{tmp_path}/ttyUSB0", f"{tmp_path}/missing")
    assert find_serial_ports(patterns) == [str(tmp_path / n) for n in ("ttyACM0", "ttyUSB0", "ttyUSB1")]


def test_the_community_drivers_udev_link_is_tried_first() -> None:
    assert AUTO_PORT_PATTERNS[0] == "/dev/ldlidar"
