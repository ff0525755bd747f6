"""One subscription's messages, taken through rclpy's own ``take_message`` (``fastpath/taker.c``).

The compiled ``Taker`` takes with ``rcl_take`` into a C message kept across
takes and converts it with the type's rosidl functions, without the
message-info dictionary nobody asked for. Here the take is rclpy's
(``handle.take_message(message_type, False)``), which does the same
conversions; what a caller gets is the same: the message, or with
:meth:`Taker.take_with_info` the pair with the keys rclpy gives
(``publisher_gid`` when made with it: rclpy 9 gives one; rclpy 7 has none
to give, and this engine has no other way to it).

Difference: rclpy's take makes a new C message for every take, where the
compiled one takes into one kept across takes: a large message (a 1080p
image) allocates its buffer, and faults its pages in, every time.
"""

from __future__ import annotations

from typing import Any

from .held import Held, check_message_type

__all__ = ["Taker", "publisher_gid"]


class Taker:
    """One subscription's messages (its handle held)."""

    __slots__ = ("_message_type", "_subscription", "_with_gid")

    def __init__(self, *, subscription: Any, message_type: type, publisher_gid: bool = False) -> None:
        if getattr(self, "_subscription", None) is not None:
            raise RuntimeError("Taker is initialised once")
        self._with_gid = bool(publisher_gid)
        check_message_type(message_type)
        self._message_type = message_type
        self._subscription: Held | None = Held(subscription)

    def close(self) -> None:
        """Let the handle go; a take after this raises ``RuntimeError``."""
        held, self._subscription = self._subscription, None
        if held is not None:
            held.exit()

    def _take(self) -> tuple[Any, dict[str, Any]] | None:
        held = self._subscription
        if held is None:
            raise RuntimeError("Taker not initialised, or closed")
        taken: tuple[Any, dict[str, Any]] | None = held.handle.take_message(self._message_type, False)
        return taken

    def take(self) -> object | None:
        """One message, or ``None`` when there is none."""
        taken = self._take()
        return None if taken is None else taken[0]

    def take_with_info(self) -> tuple[object, dict[str, Any]] | None:
        """``(message, info)``, with the keys rclpy's ``take_message`` gives
        (``publisher_gid`` only when made with it), or ``None``."""
        taken = self._take()
        if taken is None:
            return None
        message, info = taken
        if not self._with_gid:
            info.pop("publisher_gid", None)
        return message, info


def publisher_gid(publisher: Any, /) -> dict[str, str | bytes]:
    """The gid of ``publisher``'s rcl publisher (its handle), as rclpy 9's message info gives it.

    ``NotImplementedError`` here: rclpy (7 and 9) offers no publisher's gid to
    Python (its ``Publisher`` handle has no accessor; the graph names the
    gids of a topic's publishers, not which handle has which).
    """
    Held(publisher).exit()  # what is no handle is refused as the compiled one refuses it
    raise NotImplementedError("rclpy offers no publisher's gid to Python")
