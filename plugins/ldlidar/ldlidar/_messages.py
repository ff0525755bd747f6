"""Scans as ROS messages: the one place the core's :class:`Scan` meets ``sensor_msgs``."""

from __future__ import annotations

import array
import math

from sensor_msgs.msg import LaserScan

from ._scan import Scan

__all__ = ["to_laser_scan"]


def to_laser_scan(scan: Scan, *, frame_id: str, into: LaserScan | None = None) -> LaserScan:
    """Return *scan* as a ``sensor_msgs/LaserScan`` stamped with ray 0's time.

    :param into: a message to fill instead of a new one: building a
        ``LaserScan`` costs more than filling it, and a publisher serialises
        the message before ``publish`` returns, so one can be reused.
    """
    msg = LaserScan() if into is None else into
    msg.header.frame_id = frame_id
    sec, nanosec = _to_time(scan.stamp)
    msg.header.stamp.sec = sec
    msg.header.stamp.nanosec = nanosec
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


def _to_time(seconds: float) -> tuple[int, int]:
    # Rounding the fraction can reach a whole second, which a Time cannot hold
    # in its nanoseconds: carry it into the seconds.
    sec = math.floor(seconds)
    nanosec = round((seconds - sec) * 1e9)
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return sec, nanosec
