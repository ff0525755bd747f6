"""The ROS 2 face of the driver: the ``ldlidar::LdLidarNode`` lifecycle node.

This module is the distribution's ``container.plugins`` entry point and the
node's public surface; the core (protocol, parser, scans, devices) stays free
of ROS. The node fixes what hurts users of the community driver
(Myzhar/ldrobot-lidar-ros2) while keeping its parameter names:
``comm.baudrate`` is honoured (the STL-27L needs 921600), a port that cannot
open fails the configure transition instead of calling ``exit()``, a port that
vanishes is reopened, ``range_min``/``range_max`` are applied, and scans are
stamped with the time of their first ray.

Parameters (read by ``configure``; change them, then ``cleanup`` and
``configure`` again):

========================  ==================  =============================================
name                      default             meaning
========================  ==================  =============================================
comm.serial_port          ``auto``            device path, pyserial URL
                                              (``socket://host:port``), or
                                              ``file://capture.bin`` (replayed at line
                                              rate, once); ``auto``: the first of
                                              :data:`AUTO_PORT_PATTERNS` that exists,
                                              else the built-in emulator on a
                                              pseudo-terminal
comm.baudrate             0                   line speed; 0 = the model's own
comm.timeout_msec         1000                ms to wait for a valid packet: at
                                              configure, and while streaming before the
                                              port counts as lost and is reopened
comm.poll_msec            20                  read the port every so many ms, and when
                                              each revolution is predicted to complete
                                              (few large reads: less CPU, same
                                              latency); 0 = read whenever bytes arrive
                                              (not in the community driver)
lidar.model               ``LD06``            ``LD06``, ``LD19``, ``STL27L`` (also
                                              ``LDLiDAR_LD19``, ``STL-27L``, any case)
lidar.rot_verse           ``CCW``             ``CCW`` for a sensor mounted upright,
                                              ``CW`` for one mounted upside down
lidar.frame_id            ``ldlidar_link``    ``header.frame_id`` of the scans
lidar.bins                455                 rays per scan, fixed (what slam_toolbox
                                              needs); 0 = one ray per measured point
                                              (the length varies between turns)
lidar.range_min           0.03                metres; closer readings are published -inf
lidar.range_max           15.0                metres; farther readings are published +inf
lidar.enable_angle_crop   false               blank out a sector
lidar.angle_crop_min      90.0                sector start, degrees clockwise from the
                                              sensor's front
lidar.angle_crop_max      270.0               sector end; cropped rays are NaN
========================  ==================  =============================================

Topics:

* ``~/scan`` (``sensor_msgs/LaserScan``), one per revolution, while active,
  stamped with the system (wall-clock) time of the revolution's first ray,
  derived from the device's millisecond clock.
  QoS: reliable, volatile, keep last 10. rviz2's LaserScan display
  subscribes reliable by default and would never match a best-effort
  publisher; a best-effort (SensorData) subscriber such as slam_toolbox's
  still matches a reliable one.
* ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``), about once a second
  while configured (inactive or active): packet and scan rates, CRC errors,
  resyncs, skipped bytes, reopens; level ERROR when no data arrives.

The port is read from ``configure`` to ``cleanup``: a deactivated node stops
publishing but keeps reading, so the parser and the device clock stay in sync.
"""

from __future__ import annotations

from container import RegisterNodeType, hookimpl

from ._diagnostics import DIAGNOSTICS_PERIOD
from ._messages import to_laser_scan
from ._node import SCAN_QOS, LdLidarNode
from ._ports import AUTO_PORT_PATTERNS, find_serial_ports

__all__ = [
    "AUTO_PORT_PATTERNS",
    "DIAGNOSTICS_PERIOD",
    "SCAN_QOS",
    "LdLidarNode",
    "find_serial_ports",
    "register_node_types",
    "to_laser_scan",
]


@hookimpl
def register_node_types(register: RegisterNodeType) -> None:
    """Register the LiDAR node as ``ldlidar::LdLidarNode``."""
    register(LdLidarNode)
