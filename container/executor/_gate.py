"""The spin_once gate: how many callbacks may start now.

Under ``spin`` everything starts. Under ``spin_once`` one callback starts per
call, as in rclpy: what is taken meanwhile waits here, its starts kept in
arrival order and bounded per entity by its depth (the keep-last rule the
lanes use, the same compiled :class:`KeepLast`), like the rcl queue it came
from.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from ._engine import KeepLast

__all__: list[str] = []


class Gate:
    """How many more callbacks may start (``permits``; ``None``: any number)."""

    def __init__(self) -> None:
        #: Read without the lock on the hot path: ``None`` means the gate is open.
        self.permits: int | None = 0
        #: Work taken while no permit was left: its starts, keep-last per entity.
        self._held = KeepLast()
        #: Whether a spin holds the gate open (``limit`` other than 0): a
        #: permit given back after the spin returned must not start anything.
        self._open = False
        self._lock = threading.Lock()

    def admit(self, entity: object, depth: int, start: Callable[[], None]) -> bool:
        """Whether a callback may start now; if not, ``start`` is kept until it may.

        Without a limit (``spin``) everything starts. Under ``spin_once`` one
        callback starts per call, as in rclpy: what was taken meanwhile waits
        here, bounded per entity by its depth like the rcl queue it came from.
        """
        with self._lock:
            permits = self.permits
            if permits is None:
                return True
            if permits > 0:
                self.permits = permits - 1
                return True
            self._held.push(start, entity, depth)
            return False

    def limit(self, permits: int | None) -> None:
        """Let ``permits`` more callbacks start (``None``: any number), those held first.

        Held work starts in the order it was taken; until the last of it has
        started, work taken meanwhile (other threads deliver too) is held
        behind it, so a subscription's messages never overtake each other.
        """
        left = permits
        with self._lock:
            self._open = permits != 0
        while True:
            with self._lock:
                if not self._held or left == 0:
                    self.permits = left
                    return
                self.permits = 0
                start = self._pop_held()
                if left is not None:
                    left -= 1
            start()

    def refund(self) -> None:
        """Give back the permit of a callback that turned out to have nothing
        to run (a task cancelled before its turn, work of a removed node):
        under ``spin_once`` the next one starts instead, as rclpy passes
        over what it will not run. Nothing once the spin has returned."""
        with self._lock:
            if self.permits is None or not self._open:
                return
            if not self._held:
                self.permits += 1
                return
            start = self._pop_held()
        start()

    def _pop_held(self) -> Callable[[], None]:
        """The oldest held work's start (under the gate lock)."""
        start: Callable[[], None] = self._held.pop()
        return start

