"""The plugin's exceptions, all in one place, under the container's hierarchy.

::

    container.ContainerError
    └── LidarError                 anything this package raises on purpose
        ├── ProtocolError          bytes that are not a valid frame
        └── DeviceError            a device (serial port, capture file, emulator) failed
            │                      (also a container.DeviceError)
            └── DeviceRefused      the device policy refused what the port names now

A container that loads the node, or a program that drives a :class:`Lidar`,
can therefore catch ``container.ContainerError`` or ``container.DeviceError``
without knowing this plugin; ``device`` and ``reason`` are the container's
attributes, so nobody takes a message apart. ``container`` loads its
ROS-dependent parts on first use, which keeps the decode path free of rclpy.
Foreign errors (pyserial, OS) are translated where they enter this package and
chained with ``raise ... from exc``.
"""

from __future__ import annotations

import container

__all__ = ["DeviceError", "DeviceRefused", "LidarError", "ProtocolError"]


class LidarError(container.ContainerError):
    """Base of every error this package raises on purpose."""


class ProtocolError(LidarError):
    """Bytes handed to a decoder are not a valid frame."""


class DeviceError(LidarError, container.DeviceError):
    """A device failed: it could not open, vanished, or sent nothing valid.

    :param device: the port, URL or file of the device.
    """


class DeviceRefused(DeviceError):
    """The container's device policy refused what the port names, at this open.

    Chained to the policy's :class:`container.devices.PortRefused`. A
    device error all the same: a port that named a serial adapter at
    configure may name something else when it is reopened (a re-pointed
    symlink), and the reopen loop keeps waiting for the device, opening
    nothing meanwhile.
    """
