"""Memory freed by unloaded nodes, given back to the system.

Unloading a node frees what rclpy and Fast DDS allocated for it, but glibc
keeps freed heap pages for the process: 200 demo talkers took an empty
container from 92 to 432 MB RSS, and unloading them left 433 MB. Plain
rclpy alike (200 nodes with a publisher, a subscription and a timer each,
one process): 38 MB, 646 MB loaded, 645 MB destroyed; ``malloc_trim(0)``
then brought it to 86 MB in 80-90 ms. So once unloads settle,
:class:`MemoryReturn` asks glibc to give the free pages back, on a thread of
its own: the loop's thread never waits for it (a trim walks every arena).
Elsewhere than glibc (no ``malloc_trim``) it does nothing.
"""

from __future__ import annotations

import asyncio
import ctypes
import os
import time
from collections.abc import Callable
from dataclasses import dataclass

from .executor import in_thread

__all__ = ["MemoryReturn", "Trimmed", "resident_bytes"]

#: Seconds without an unload before the trim: a file's or a client's burst of
#: unloads is trimmed once, after its last.
SETTLE = 1.0

_PAGE = os.sysconf("SC_PAGE_SIZE")


def _find_trim() -> Callable[[], object] | None:
    """glibc's ``malloc_trim`` (``None`` elsewhere: musl, macOS).

    Looked up among the symbols the process has loaded (``CDLL(None)``: 0.06 ms),
    not through ``ctypes.util.find_library`` (2.4 ms here, a search of the
    linker cache), since this runs as the container starts."""
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return lambda: trim(0)


def resident_bytes() -> int:
    """This process's resident set (RSS), from ``/proc/self/statm`` (0 where there is none)."""
    try:
        with open("/proc/self/statm", "rb") as statm:
            return int(statm.read().split()[1]) * _PAGE
    except (OSError, IndexError, ValueError):
        return 0


@dataclass(frozen=True, slots=True)
class Trimmed:
    """One return of memory: RSS before and after (bytes), the trim's own time (s), and how
    many unloads it followed."""

    before: int
    after: int
    seconds: float
    unloads: int

    def describe(self) -> str:
        mib = 1 << 20
        return (
            f"Gave {max(self.before - self.after, 0) / mib:.0f} MiB back to the system after "
            f"{self.unloads} unload{'s' if self.unloads != 1 else ''} (RSS {self.before / mib:.0f} -> "
            f"{self.after / mib:.0f} MiB; malloc_trim took {self.seconds * 1000:.0f} ms)"
        )


class MemoryReturn:
    """Trims the heap :data:`SETTLE` seconds after the last of a burst of unloads.

    :param log: told of each return (the container's logger, at info).
    :param settle: seconds without an unload before trimming.
    :param trim: what gives memory back (glibc's ``malloc_trim(0)``; ``None``: nothing does).

    Used from the loop's thread only (:meth:`unloaded` from the unload).
    """

    def __init__(
        self,
        *,
        log: Callable[[Trimmed], object],
        settle: float = SETTLE,
        trim: Callable[[], object] | None = _find_trim(),  # noqa: B008 - found once, at import
    ) -> None:
        self._log = log
        self._settle = settle
        self._trim = trim
        self._unloads = 0
        self._timer: asyncio.TimerHandle | None = None
        self._running: asyncio.Task[None] | None = None

    @property
    def available(self) -> bool:
        """Whether this process's allocator can give memory back (glibc)."""
        return self._trim is not None

    def unloaded(self) -> None:
        """A node was unloaded: trim once no other follows for ``settle`` seconds."""
        if self._trim is None:
            return
        self._unloads += 1
        if self._timer is not None:
            self._timer.cancel()
        self._timer = asyncio.get_running_loop().call_later(self._settle, self._start)

    def _start(self) -> None:
        self._timer = None
        if self._running is not None and not self._running.done():
            self._timer = asyncio.get_running_loop().call_later(self._settle, self._start)
            return  # one trim at a time; this burst's comes after it
        unloads, self._unloads = self._unloads, 0
        self._running = asyncio.get_running_loop().create_task(self._return(unloads))

    async def _return(self, unloads: int) -> None:
        trim = self._trim
        assert trim is not None  # _start runs only with one

        def timed() -> tuple[int, float, int]:
            before = resident_bytes()
            started = time.perf_counter()
            trim()
            return before, time.perf_counter() - started, resident_bytes()

        before, seconds, after = await in_thread(timed, name="malloc-trim")
        self._log(Trimmed(before, after, seconds, unloads))

    def close(self) -> None:
        """Forget a pending trim (the container is going away)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._running is not None:
            self._running.cancel()
