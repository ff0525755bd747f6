"""A notifier that never reports: rmw's new-data callbacks are out of Python's reach (``fastpath/notifier.c``).

The compiled ``Notifier`` registers rmw's per-entity new-data callback
(``rcl_subscription_set_on_new_message_callback`` and its kin): Fast DDS
calls it in the publishing thread, or in its receive thread, without the
GIL, and the notifier records which entity became ready and triggers the
loop's guard condition while the loop sleeps in ``rcl_wait`` (armed). A
ping-pong between two nodes of one process then never enters ``rcl_wait``.

rclpy 7 (Jazzy) and 9 (Kilted) offer no such setter to Python (their
events executor registers it in C++), and a Python callback would run in
rmw's threads with the GIL. So :meth:`Notifier.watch` raises
``NotImplementedError``, and the executor waits on the entity in the rcl
wait set instead (``_waitset.EntityWaitSet._watch``, the fallback for an
rmw without the callback). The notifier still holds its guard's handle
until :meth:`Notifier.close`; everything else behaves as a notifier that
nothing ever reported to: nothing pending, nothing ready, nothing carried.

Differences, all following from that: no entity is reported between
waits (every message costs a wait), no carried message skips a wake-up
(``mark_carrier`` has nothing to defer), and QoS events are waited on too.
"""

from __future__ import annotations

from typing import Any

from .held import Held

__all__ = ["CLIENT", "DRAIN", "EVENT", "SERVICE", "SUBSCRIPTION", "Notifier", "mark_carrier"]

SUBSCRIPTION = 0
CLIENT = 1
SERVICE = 2
EVENT = 3
#: The count :meth:`Notifier.ready` gives for "take until nothing is left" (a fresh watch).
DRAIN = 1 << 30


class Notifier:
    """rmw's new-data callbacks of the watched entities (none here: see the module), turned
    into a ready list and one trigger of ``guard`` while the waiter sleeps (armed)."""

    __slots__ = ("_guard",)

    def __init__(self, *, guard: Any) -> None:
        if getattr(self, "_guard", None) is not None:
            raise RuntimeError("Notifier is initialised once")
        self._guard: Held | None = Held(guard)

    def watch(self, handle: Any, kind: int, plain: bool = False, /) -> bool:
        """Report new data of ``handle``'s entity: ``NotImplementedError`` here (no rmw
        callback from Python), after the checks the compiled one makes."""
        if not SUBSCRIPTION <= kind <= EVENT:
            raise ValueError("watch() needs a known kind")
        if self._guard is None:
            raise RuntimeError("Notifier not initialised, or closed")
        Held(handle).exit()  # what is no handle is refused as the compiled one refuses it
        raise NotImplementedError("rclpy offers no rmw new-data callback to Python: the entity is waited on")

    def unwatch(self, handle: Any, /) -> bool:
        """Stop reporting ``handle``'s entity: ``False``, it was never watched."""
        return False

    def arm(self) -> bool:
        """About to wait: ``True`` if something is ready already (never here)."""
        return False

    def disarm(self) -> None:
        """Back from the wait."""

    def pending(self) -> bool:
        """Whether something is ready (never here)."""
        return False

    def ready(self) -> list[tuple[int, int]]:
        """``(address, events)`` of the entities that became ready since the last call."""
        return []

    def carry(self) -> list[tuple[int, int]]:
        """What :meth:`ready` would give, of the plain entities only."""
        return []

    def close(self) -> None:
        """Never trigger the guard again; unwatch everything and let every handle go."""
        held, self._guard = self._guard, None
        if held is not None:
            held.exit()

    @property
    def triggers(self) -> int:
        """How often a report woke the waiter."""
        return 0

    @property
    def watched(self) -> int:
        """How many entities are watched."""
        return 0



def mark_carrier() -> None:
    """This thread takes, after each plain callback, what it published to other plain
    callbacks (``Notifier.carry``): nothing to mark here, where no notifier reports
    a publish, so none defers the waiter's wake-up for it."""
