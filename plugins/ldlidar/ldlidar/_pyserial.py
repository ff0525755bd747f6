"""pyserial on a descriptor the device policy opened and checked.

pyserial opens its port by name (``os.open(port, O_RDWR | O_NOCTTY |
O_NONBLOCK)``) and configures it at once (``termios``, modem lines); it has
no public way to take a descriptor someone else opened. Giving it the name
again would reopen whatever the name leads to by then, which is the race the
device policy closes. So it is given ``/proc/self/fd/N``: on Linux that is a
"magic link", which the kernel resolves to the very file descriptor N is open
on (its inode, even if the name was re-pointed or removed since), never by
walking a name; pyserial opens the device that was checked, and only public
pyserial API is used. The other route, a ``serial.Serial`` subclass adopting
the descriptor, would set ``fd`` and call the private ``_reconfigure_port``
and ``pipe_abort_*`` of ``serial.serialposix``, which change between
releases.
"""

from __future__ import annotations

import errno
import os
from typing import Any

__all__ = ["serial_on_descriptor"]


def serial_on_descriptor(fd: int, *, baudrate: int) -> Any:
    """Return a ``serial.Serial`` open on the device *fd* is open on, at *baudrate*, reads not blocking.

    *fd* stays the caller's to close (pyserial holds its own descriptor).

    :raises serial.SerialException: pyserial could not open or configure it.
    :raises OSError: what pyserial opened is not what *fd* is open on (it
        cannot be; checked all the same, and closed if so).
    """
    import serial

    checked = os.fstat(fd)
    port = serial.Serial(f"/proc/self/fd/{fd}", baudrate=baudrate, timeout=0)
    opened = os.fstat(port.fileno())
    if (opened.st_dev, opened.st_ino, opened.st_rdev) != (checked.st_dev, checked.st_ino, checked.st_rdev):
        port.close()
        raise OSError(errno.ESTALE, "/proc/self/fd led pyserial to another file than the one checked")
    return port
