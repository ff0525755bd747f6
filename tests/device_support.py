"""What this process opens while a device is decided on: nothing it should not.

:class:`OpenWatch` records every path any thread of this process asks to
open (``os.open``, ``open()``, pyserial's opens: Python's ``open`` audit
event, raised before the system call, so a failed or refused open is seen
too), with what it resolved to then, and the descriptors ``/proc/self/fd``
lists before and after. A refusal that opened and closed the device at once
would leave no descriptor behind; the audit event still shows it.
"""

from __future__ import annotations

import os
import sys
import threading
from types import TracebackType
from typing import Any, Self

__all__ = ["OpenWatch", "descriptors"]

_lock = threading.Lock()
_watches: list[OpenWatch] = []
_installed = False


def _audit(event: str, args: tuple[Any, ...]) -> None:
    if event != "open" or not _watches:
        return
    path = args[0]
    if isinstance(path, (str, bytes)):
        name = os.fsdecode(path)
        # Resolved now: /proc/self/fd/N means something else once N is closed.
        resolved = os.path.realpath(name)
        with _lock:
            for watch in _watches:
                watch.opened.append((name, resolved))


def descriptors() -> dict[int, str]:
    """This process's open descriptors and what each is open on."""
    found: dict[int, str] = {}
    for entry in os.listdir("/proc/self/fd"):
        try:
            found[int(entry)] = os.readlink(f"/proc/self/fd/{entry}")
        except OSError:
            continue  # the one listdir itself held
    return found


class OpenWatch:
    """Use as ``with OpenWatch() as watch:``; then :meth:`opens_of` and :meth:`left_open_on`."""

    def __init__(self) -> None:
        #: (the path as asked, what it resolved to then), in order.
        self.opened: list[tuple[str, str]] = []
        self.before: dict[int, str] = {}
        self.after: dict[int, str] = {}

    def __enter__(self) -> Self:
        global _installed
        with _lock:
            if not _installed:
                # An audit hook cannot be removed: it is installed once and
                # does nothing while no watch is active.
                sys.addaudithook(_audit)
                _installed = True
        self.before = descriptors()
        with _lock:
            _watches.append(self)
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        with _lock:
            _watches.remove(self)
        self.after = descriptors()

    def opens_of(self, *targets: str) -> list[str]:
        """The opens asked for any of *targets*, by name or by what they resolved to."""
        wanted = set(targets) | {os.path.realpath(target) for target in targets}
        return [name for name, resolved in self.opened if name in wanted or resolved in wanted]

    def left_open_on(self, *targets: str) -> list[str]:
        """Descriptors open after the watch, not before, on any of *targets* (resolved)."""
        wanted = set(targets) | {os.path.realpath(target) for target in targets}
        return [
            f"fd {fd} -> {where}"
            for fd, where in self.after.items()
            if where in wanted and self.before.get(fd) != where
        ]
