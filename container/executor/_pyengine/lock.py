"""A mutex used as ``threading.Lock`` by both the lanes and the async chain (``fastpath/lock.c``).

The compiled ``Lock`` exists so that its C callers check and take it
without a Python call; here every caller is Python, and a lock is what
``threading.Lock`` gives: ``acquire(blocking=True, timeout=-1)``,
``release()``, ``locked()``, ``with``. The chain's non-blocking take
(``lock_try``) is ``acquire(blocking=False)``.

Both refuse what ``threading.Lock`` refuses (a timeout with a non-blocking
call, a negative one, one too large to wait), and a NaN timeout too, which
``threading.Lock`` would wait on for ever; in both, a signal handler's
exception in the main thread interrupts a blocked ``acquire``.
"""

from __future__ import annotations

import threading

__all__ = ["Lock"]


class Lock:
    """A mutex used as ``threading.Lock``."""

    __slots__ = ("_lock",)

    def __init__(self) -> None:
        self._lock = threading.Lock()

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        """Take it (``threading.Lock.acquire``'s arguments and answers)."""
        if timeout != timeout:  # NaN
            raise ValueError("timeout value must be a non-negative number")
        return self._lock.acquire(blocking, timeout)

    def release(self) -> None:
        """Let it go; ``RuntimeError`` when it is not held."""
        self._lock.release()

    def locked(self) -> bool:
        return self._lock.locked()

    def __enter__(self) -> bool:
        return self._lock.acquire()

    def __exit__(self, *exc_info: object) -> None:
        self._lock.release()
