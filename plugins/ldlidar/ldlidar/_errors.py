"""The plugin's exceptions, all in one place.

::

    LidarError                 anything this package raises on purpose
    ├── ProtocolError          bytes that are not a valid frame
    └── DeviceError            a device (serial port, capture file, emulator) failed

They stand alone until the container's hierarchy can be imported; then
``LidarError`` is meant to be rebased onto ``container.ContainerError`` and
``DeviceError`` onto ``container.DeviceError`` (same ``device`` keyword).
Foreign errors (pyserial, OS) are translated where they enter this package and
chained with ``raise ... from exc``.
"""

from __future__ import annotations

__all__ = ["DeviceError", "LidarError", "ProtocolError"]


class LidarError(Exception):
    """Base of every error this package raises on purpose."""


class ProtocolError(LidarError):
    """Bytes handed to a decoder are not a valid frame."""


class DeviceError(LidarError):
    """A device failed: it could not open, vanished, or sent nothing valid.

    :param device: the port, URL or file of the device.
    """

    def __init__(self, message: str, *, device: str) -> None:
        super().__init__(f"{device}: {message}")
        self.device = device
