"""What an engine object owns of rclpy's: handles, held and entered (``fastpath/held.c``).

Why: an rcl pointer is valid only while the rclpy handle that owns it has
not destroyed it, and rclpy destroys it when asked (``node.destroy_*()``,
shutdown) unless the handle is entered: then destruction waits for the
last exit (rclpy's ``Destroyable``). So every object of the engine that
uses an entity holds and enters its handle for as long as it may use it,
and knows it by its address (``handle.pointer``), a key only.

The compiled ``held.c`` also reads each message type's rosidl capsules
(its conversion functions); this engine converts through rclpy's own
calls, and only checks that a type has them (:func:`check_message_type`),
so that both engines accept and refuse the same types.

Differences: an ``__exit__`` that raises in :meth:`Held.exit` is raised
(the compiled one reports it as unraisable and goes on); at collection
both report it as unraisable.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

__all__ = ["Held", "check_message_type", "enter_all", "exit_all"]

#: The capsules of a message type the compiled engine reads (``message_functions``).
_TO_PY = ("_CREATE_ROS_MESSAGE", "_DESTROY_ROS_MESSAGE", "_CONVERT_TO_PY")
_FROM_PY = "_CONVERT_FROM_PY"


class Held:
    """An rclpy handle held: a strong reference, entered until :meth:`exit` or collection.

    Raises ``TypeError`` for what is no handle (``None``, an address),
    rclpy's ``InvalidHandle`` for one destroyed already (entered first),
    ``ValueError`` for one without an rcl object; nothing is held then.
    """

    __slots__ = ("handle", "pointer")

    def __init__(self, handle: Any) -> None:
        self.handle: Any = None
        #: The rcl object's address (0 once let go): a key, never dereferenced.
        self.pointer = 0
        if handle is None or isinstance(handle, int):
            raise TypeError(f"an rclpy handle is needed (the entity's .handle), not {type(handle).__name__}")
        # Entered first: a handle destroyed already raises rclpy's InvalidHandle here.
        handle.__enter__()
        self.handle = handle
        try:
            pointer = int(handle.pointer)
        except BaseException:
            self.exit()
            raise
        if pointer == 0:
            self.exit()
            raise ValueError(f"{type(handle).__name__} has no rcl object (pointer 0)")
        self.pointer = pointer

    def exit(self) -> None:
        """Exit and let go (nothing when nothing is held)."""
        handle, self.handle, self.pointer = self.handle, None, 0
        if handle is not None:
            handle.__exit__(None, None, None)

    def __del__(self) -> None:
        self.exit()


def enter_all(handles: Iterable[Any]) -> list[Held]:
    """Every handle of ``handles`` held and entered; on a failure, none (those held are let go)."""
    if isinstance(handles, str | bytes) or not hasattr(handles, "__iter__"):
        raise TypeError("entities must be a sequence of rclpy handles")
    held: list[Held] = []
    try:
        for handle in handles:
            held.append(Held(handle))
    except BaseException:
        exit_all(held)
        raise
    return held


def exit_all(held: list[Held]) -> None:
    """Let every handle of ``held`` go, the last first; the list is emptied."""
    while held:
        held.pop().exit()


def check_message_type(message_type: Any, *, from_py: bool = False) -> None:
    """Refuse what the compiled engine refuses: a type without rosidl's conversion capsules.

    ``AttributeError`` when one is missing, ``ValueError`` when one is no capsule.
    """
    for name in (*_TO_PY, _FROM_PY) if from_py else _TO_PY:
        capsule = getattr(message_type, name)
        if type(capsule).__name__ != "PyCapsule":
            raise ValueError(f"{name} of {message_type!r} is not a capsule")
