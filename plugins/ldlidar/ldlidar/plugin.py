"""The ROS 2 face of the driver: the ``ldlidar::LdLidarNode`` lifecycle node.

This module is the distribution's ``container.plugins`` entry point and the
node's public surface; the core (protocol, parser, scans, devices) stays free
of ROS. The node fixes what hurts users of the community driver
(Myzhar/ldrobot-lidar-ros2) while keeping its parameter names, and takes the
vendor driver's (ldlidar_stl_ros2) as aliases with a deprecation warning:
``comm.baudrate`` is honoured (the STL-27L needs 921600), a port that cannot
open fails the configure transition instead of calling ``exit()``, a port that
vanishes is reopened, ``range_min``/``range_max`` are applied, every ray is
where and when the message says (see :mod:`ldlidar._scan`), and no override
is silently ignored.

Parameters (read by ``configure``; change them, then ``cleanup`` and
``configure`` again):

=================================  ==================  =============================================
name                               default             meaning
=================================  ==================  =============================================
comm.serial_port                   ``auto``            device path, pyserial URL
                                                       (``socket://host:port``), or
                                                       ``file://capture.bin[?rate=2&loop=1]``
                                                       (replayed at its device's pace);
                                                       ``auto``: the first of
                                                       :data:`AUTO_PORT_PATTERNS` that exists,
                                                       else the built-in emulator on a
                                                       pseudo-terminal (diagnostics WARN,
                                                       "simulated"); an explicit port never
                                                       falls back to it
comm.baudrate                      0                   line speed; 0 = the model's own
comm.timeout_msec                  1000                ms to wait for a valid packet: at
                                                       configure, and while streaming before the
                                                       port counts as lost and is reopened
comm.poll_msec                     20                  poll every so many ms (1-30) until a
                                                       revolution can be predicted, then read
                                                       once per revolution when it is due
lidar.model                        ``LD06``            ``LD06``, ``LD19``, ``STL27L`` (also
                                                       ``LDLiDAR_LD19``, ``STL-27L``, any case)
lidar.rot_verse                    ``CCW``             ``CCW`` for a sensor mounted upright,
                                                       ``CW`` for one mounted upside down
lidar.frame_id                     ``ldlidar_link``    ``header.frame_id`` of the scans
lidar.bins                         455                 rays per scan, fixed (what slam_toolbox
                                                       needs); 0 = the native resolution
lidar.range_min                    0.03                metres; closer readings are published -inf
lidar.range_max                    15.0                metres; farther readings are published +inf
lidar.enable_angle_crop            false               blank out a sector
lidar.angle_crop_min               90.0                sector start, degrees clockwise from the
                                                       sensor's front
lidar.angle_crop_max               270.0               sector end; cropped rays are NaN
lidar.noise_filter                 false               drop isolated dim returns under 5 m (the
                                                       vendor's LD06/LD19 near filter)
lidar.units                        ``M``               only metres; anything else is refused
general.publish_when_subscribed    false               publish only while ~/scan has a subscriber
general.debug_mode                 false               debug logging, a line per revolution
diagnostics.period_msec            1000                ms between two ``/diagnostics`` reports
                                                       (100-60000)
diagnostics.outage_msec            5000                ms without a valid packet after which an
                                                       outage is logged (WARN when it starts,
                                                       INFO when it ends)
qos_overrides./<node>/scan.        reliable, volatile, ~/scan's QoS, overridden the ROS way
publisher.<policy>                 keep_last, 10
=================================  ==================  =============================================

Topics:

* ``~/scan`` (``sensor_msgs/LaserScan``), one per revolution, while active,
  stamped with the system (wall-clock) time of ray 0, derived from the
  device's millisecond clock; ray ``i`` was measured at ``stamp + i *
  time_increment`` (negative upright: ray 0 is the last measured).
  QoS: reliable, volatile, keep last 10, unless overridden. rviz2's
  LaserScan display subscribes reliable by default and would never match a
  best-effort publisher; a best-effort (SensorData) subscriber such as
  slam_toolbox's still matches a reliable one.
* ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``), every
  ``diagnostics.period_msec`` while configured (inactive or active): packet,
  scan and byte rates, CRC errors, resyncs, skipped bytes, reopens, stalls,
  clock jumps; level ERROR when no valid packet arrives, saying whether no
  bytes arrive or bytes that form no valid packet (at what rate, and why).

The port is read from ``configure`` to ``cleanup``: a deactivated node stops
publishing but keeps reading, so the parser and the device clock stay in sync.
"""

from __future__ import annotations

from container import RegisterNodeType, hookimpl

from ._diagnostics import DIAGNOSTICS_PERIOD
from ._messages import to_laser_scan
from ._node import SCAN_QOS, SCAN_QOS_OVERRIDES, LdLidarNode
from ._ports import AUTO_PORT_PATTERNS, find_serial_ports

__all__ = [
    "AUTO_PORT_PATTERNS",
    "DIAGNOSTICS_PERIOD",
    "SCAN_QOS",
    "SCAN_QOS_OVERRIDES",
    "LdLidarNode",
    "find_serial_ports",
    "register_node_types",
    "to_laser_scan",
]


@hookimpl
def register_node_types(register: RegisterNodeType) -> None:
    """Register the LiDAR node as ``ldlidar::LdLidarNode``."""
    register(LdLidarNode)
