"""Warnings that repeat, logged at a rate a person can read.

A device that loses its clock every tenth of a second, or a peer that keeps
sending the same bad request, would otherwise bury every other line of the
log. :class:`Throttle` logs the first warning of a kind at once, then at most
one line of that kind per period, saying how many were held back in between;
nothing is lost from the count, only from the log.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass

__all__ = ["Throttle"]


@dataclass(slots=True)
class _Kind:
    last: float
    held: int = 0


class Throttle:
    """Log through ``log`` at most once per ``period`` seconds for each kind.

    :param log: where lines go (``node.get_logger().warning``).
    :param period: the shortest time between two lines of one kind.
    :param clock: seconds, monotonic (for tests).

    Thread-safe: plain callbacks of one node may run on several threads.
    """

    def __init__(
        self,
        log: Callable[[str], object],
        *,
        period: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._log = log
        self.period = period
        self._clock = clock
        self._kinds: dict[Hashable, _Kind] = {}
        self._lock = threading.Lock()

    def __call__(self, kind: Hashable, message: str) -> bool:
        """Log ``message`` unless a line of ``kind`` went out less than a period ago.

        :return: whether it was logged (else it was counted).
        """
        now = self._clock()
        with self._lock:
            seen = self._kinds.get(kind)
            if seen is not None and now - seen.last < self.period:
                seen.held += 1
                return False
            self._kinds[kind] = _Kind(now)
        if seen is not None and seen.held:
            message = f"{message} ({seen.held} more like this in the last {now - seen.last:.0f} s)"
        self._log(message)
        return True

    def flush(self) -> None:
        """Log, for each kind, how many lines were held back since its last one."""
        with self._lock:
            held = [(kind, entry.held) for kind, entry in self._kinds.items() if entry.held]
            for kind, _ in held:
                self._kinds[kind].held = 0
        for kind, count in held:
            self._log(f"{count} more '{kind}' warning(s) were not logged")

    def held(self, kind: Hashable) -> int:
        """How many lines of ``kind`` are held back now."""
        with self._lock:
            seen = self._kinds.get(kind)
            return seen.held if seen is not None else 0
