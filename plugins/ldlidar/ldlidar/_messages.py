"""Scans as ROS messages: the one place the core's :class:`Scan` meets ``sensor_msgs``."""

from __future__ import annotations

import array
import math

from builtin_interfaces.msg import Time
from sensor_msgs.msg import LaserScan

from ._scan import Scan

__all__ = ["to_laser_scan"]


def to_laser_scan(scan: Scan, *, frame_id: str) -> LaserScan:
    """Return *scan* as a ``sensor_msgs/LaserScan`` stamped with its first ray's time."""
    msg = LaserScan()
    msg.header.frame_id = frame_id
    msg.header.stamp = _to_time(scan.stamp)
    msg.angle_min = scan.angle_min
    msg.angle_max = scan.angle_max
    msg.angle_increment = scan.angle_increment
    msg.time_increment = scan.time_increment
    msg.scan_time = scan.scan_time
    msg.range_min = scan.range_min
    msg.range_max = scan.range_max
    # The arrays are float32 already: a byte copy, not a per-element check.
    msg.ranges = array.array("f", scan.ranges.tobytes())
    msg.intensities = array.array("f", scan.intensities.tobytes())
    return msg


def _to_time(seconds: float) -> Time:
    # Rounding the fraction can reach a whole second, which a Time cannot hold
    # in its nanoseconds: carry it into the seconds.
    sec = math.floor(seconds)
    nanosec = round((seconds - sec) * 1e9)
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return Time(sec=sec, nanosec=nanosec)
