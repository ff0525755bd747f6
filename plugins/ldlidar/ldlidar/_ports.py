"""Where ``comm.serial_port: auto`` looks for an attached LiDAR."""

from __future__ import annotations

import glob
from collections.abc import Sequence
from typing import Final

__all__ = ["AUTO_PORT_PATTERNS", "find_serial_ports"]

#: Where ``comm.serial_port: auto`` looks, in order: the community driver's
#: udev link, stable by-id names, then raw USB-serial and CDC-ACM devices.
AUTO_PORT_PATTERNS: Final = ("/dev/ldlidar", "/dev/serial/by-id/*", "/dev/ttyUSB*", "/dev/ttyACM*")


def find_serial_ports(patterns: Sequence[str] = AUTO_PORT_PATTERNS) -> list[str]:
    """Return the existing devices matching *patterns*, in pattern order, each once."""
    found: list[str] = []
    for pattern in patterns:
        for path in sorted(glob.glob(pattern)):
            if path not in found:
                found.append(path)
    return found
