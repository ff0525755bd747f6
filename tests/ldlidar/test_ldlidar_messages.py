"""Scans as ``sensor_msgs/LaserScan`` messages."""

from __future__ import annotations

import dataclasses

import pytest

from ldlidar import PacketGenerator, ScanAssembler, StreamParser
from ldlidar.plugin import to_laser_scan


def test_laser_scan_conversion_keeps_every_field() -> None:
    generator = PacketGenerator("LD06")
    parser, assembler = StreamParser(), ScanAssembler(bins=0)
    scans = [s for p in parser.feed(generator.packets(120)) for s in assembler.push(p, host_time=1e9)]
    scan = scans[0]
    msg = to_laser_scan(scan, frame_id="laser")
    assert msg.header.frame_id == "laser"
    assert msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 == pytest.approx(scan.stamp, abs=1e-6)
    assert 0 <= msg.header.stamp.nanosec < 1_000_000_000
    assert list(msg.ranges) == pytest.approx(scan.ranges.tolist())
    assert list(msg.intensities) == pytest.approx(scan.intensities.tolist())
    assert msg.angle_increment * (len(msg.ranges) - 1) == pytest.approx(msg.angle_max - msg.angle_min)
    assert (msg.scan_time, msg.time_increment) == pytest.approx((scan.scan_time, scan.time_increment))


def test_stamp_just_below_a_whole_second_rounds_up_cleanly() -> None:
    generator = PacketGenerator("LD06")
    parser, assembler = StreamParser(), ScanAssembler()
    scan = next(s for p in parser.feed(generator.packets(120)) for s in assembler.push(p))
    stamp = to_laser_scan(dataclasses.replace(scan, stamp=41.9999999999), frame_id="x").header.stamp
    assert (stamp.sec, stamp.nanosec) == (42, 0)


def test_a_reused_message_holds_only_the_latest_scan() -> None:
    """The node fills one message per revolution (building a LaserScan costs more than filling one)."""
    generator = PacketGenerator("LD06")
    parser, assembler = StreamParser(), ScanAssembler(bins=0)
    scans = [s for p in parser.feed(generator.packets(200)) for s in assembler.push(p, host_time=1e9)]
    reused = to_laser_scan(scans[0], frame_id="laser")
    for scan in scans[1:]:
        again = to_laser_scan(scan, frame_id="laser", into=reused)
        assert again is reused
        assert again == to_laser_scan(scan, frame_id="laser")
