"""What a character device is, told by its driver, not by its name.

A device node's name says nothing reliable about what opening it reaches:
``/dev/ttyV`` may be any device, and ``/dev/tty`` is whichever terminal the
process happens to have. Its major and minor numbers say which driver
serves it, and the kernel lists its terminal drivers with their numbers and
kind in ``/proc/tty/drivers``::

    /dev/tty             /dev/tty        5       0 system:/dev/tty
    /dev/console         /dev/console    5       1 system:console
    /dev/vc/0            /dev/vc/0       4       0 system:vtmaster
    unknown              /dev/tty        4    1-63 console
    serial               /dev/ttyS       4  64-111 serial
    usbserial            /dev/ttyUSB   188   0-511 serial
    acm                  /dev/ttyACM   166   0-255 serial
    pty_slave            /dev/pts      136 0-1048575 pty:slave

The file is read at each classification: a driver module loaded when an
adapter is plugged in adds its line. Where it cannot be read, the numbers
the kernel fixes for these drivers (``Documentation/admin-guide/devices.txt``)
stand in.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Final, Literal

__all__ = ["DRIVERS_FILE", "TtyClass", "TtyKind", "classify"]

DRIVERS_FILE: Final = "/proc/tty/drivers"

TtyKind = Literal["serial", "ttyS", "pty", "terminal", "other"]
"""What a device is, for the device policy.

``serial``: a serial port's driver (a USB serial or CDC-ACM adapter, a
board's UART). ``ttyS``: the 8250/16550 ports, often the machine's serial
console. ``pty``: a pseudo-terminal's slave side, any process's terminal.
``terminal``: the controlling terminal (``/dev/tty``), the console, the
virtual consoles, ``/dev/ptmx`` and pseudo-terminal masters. ``other``: not
a terminal driver's device at all (``/dev/null``, ``/dev/zero``, a disk).
"""


@dataclass(frozen=True, slots=True)
class TtyClass:
    """A character device's kind and the driver line that says so.

    :param kind: see :data:`TtyKind`.
    :param what: the same in words, for messages (``the controlling terminal``).
    :param driver: the driver's name and device prefix, for messages
        (``usbserial /dev/ttyUSB``); empty when no terminal driver serves it.
    :param major, minor: the device's numbers.
    """

    kind: TtyKind
    what: str
    driver: str
    major: int
    minor: int

    def describe(self) -> str:
        """A few words for a refusal: ``character device 188:0 (usbserial /dev/ttyUSB serial)``."""
        served = f" ({self.driver})" if self.driver else ", not a terminal driver's"
        return f"character device {self.major}:{self.minor}{served}"


# (name, prefix, major, first minor, last minor, type): what the kernel
# assigns these drivers, for when /proc/tty/drivers cannot be read.
_FIXED: Final = (
    ("/dev/tty", "/dev/tty", 5, 0, 0, "system:/dev/tty"),
    ("/dev/console", "/dev/console", 5, 1, 1, "system:console"),
    ("/dev/ptmx", "/dev/ptmx", 5, 2, 2, "system"),
    ("/dev/vc/0", "/dev/vc/0", 4, 0, 0, "system:vtmaster"),
    ("unknown", "/dev/tty", 4, 1, 63, "console"),
    ("serial", "/dev/ttyS", 4, 64, 255, "serial"),
    ("usbserial", "/dev/ttyUSB", 188, 0, 1 << 20, "serial"),
    ("acm", "/dev/ttyACM", 166, 0, 1 << 20, "serial"),
    *(("pty_slave", "/dev/pts", major, 0, 1 << 20, "pty:slave") for major in range(136, 144)),
    *(("pty_master", "/dev/ptm", major, 0, 1 << 20, "pty:master") for major in range(128, 136)),
)

_Driver = tuple[str, str, int, int, int, str]


def classify(device: int, *, drivers: str = DRIVERS_FILE) -> TtyClass:
    """Say what the character device numbered *device* (an ``st_rdev``) is.

    :param drivers: the driver list to read (tests name another).
    """
    major, minor = os.major(device), os.minor(device)
    for name, prefix, first_major, low, high, kind in _drivers(drivers):
        if major == first_major and low <= minor <= high:
            driver = f"{prefix} {kind}" if name == prefix else f"{name} {prefix} {kind}"
            return TtyClass(*_kind(prefix, kind), driver, major, minor)
    return TtyClass("other", "not a terminal", "", major, minor)


#: Terminal driver types that are never a sensor's port, in words.
_TERMINALS: Final = {
    "system:/dev/tty": "the controlling terminal",
    "system:console": "the system console",
    "system:vtmaster": "a virtual console",
    "console": "a virtual console",
    "system": "the pseudo-terminal multiplexer",
    "pty:master": "a pseudo-terminal master",
}


def _kind(prefix: str, kind: str) -> tuple[TtyKind, str]:
    if kind == "serial":
        # The 8250 driver's ports are where a machine's serial console lives.
        if prefix == "/dev/ttyS":
            return "ttyS", "an 8250/16550 serial port (often the machine's serial console)"
        return "serial", "a serial port"
    if kind == "pty:slave":
        return "pty", "a pseudo-terminal"
    # Any type this code does not know is a terminal too: never admitted.
    return "terminal", _TERMINALS.get(kind, f"a terminal ({kind})")


def _drivers(path: str) -> tuple[_Driver, ...]:
    try:
        with open(path, encoding="ascii", errors="replace") as file:
            text = file.read()
    except OSError:
        return _FIXED
    found: list[_Driver] = []
    for line in text.splitlines():
        fields = line.split()
        if len(fields) != 5:
            continue
        name, prefix, major, minors, kind = fields
        low, _, high = minors.partition("-")
        try:
            found.append((name, prefix, int(major), int(low), int(high or low), kind))
        except ValueError:
            continue
    return tuple(found) or _FIXED
