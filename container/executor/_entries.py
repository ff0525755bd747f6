"""What the executor knows of each entity it serves, and how it names one in a log.

An :class:`Entry` is computed once per change of a node's entities (not per
message): its lane, whether its callback is ``async def``, how much of its
work may wait, its token. The wait set and the takes read it per message.
"""

from __future__ import annotations

import contextlib
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rclpy.node import Node

from ._engine import (
    Caller,
    Meter,
    Server,
    Taker,
    Token,
    Work,
)
from ._lanes import Lane
from ._owners import Owner

__all__: list[str] = []

#: What :meth:`Dispatcher.wait_and_dispatch` returns when one of the
#: executor's own guard conditions fired.
WOKEN = 1

#: Entity kinds, all in the loop's wait set (services and clients are
#: event-driven too, so requests are taken and answered on the loop's thread
#: without a hop); the other thread's wait set serves generic waitables only.
KINDS = ("subscription", "timer", "client", "guard_condition", "service")


@dataclass(slots=True)
class Entry:
    """An entity with what dispatching it needs, computed once per change."""

    entity: Any
    node: Node
    lane: Lane
    is_async: bool
    depth: int
    done: Callable[[Work, BaseException | None], None]
    token: Token
    #: Takes the subscription's messages in C (``None``: rclpy's take, e.g. raw).
    taker: Taker | None = None
    #: Takes the service's requests and sends its answers in C (``None``: rclpy's).
    server: Server | None = None
    #: Takes the client's responses in C (``None``: rclpy's take).
    caller: Caller | None = None
    #: A subscription whose callback takes ``(message, message_info)``.
    wants_info: bool = False
    #: What its callbacks cost is told (``None``: accounting is off).
    meter: Meter | None = None
    #: Its node's other work (``None``: accounting is off): a client's response's
    #: done-callbacks run as its node's (see ``_takes.take_response``).
    owner: Owner | None = None

    def close(self) -> None:
        """Let go of the handles its compiled takes hold (the executor is closing).

        Not the server's: an answer still to come (a plain callback that ran
        past the shutdown) holds it and sends through it; it lets its handle
        go when the last answer has.
        """
        for taking in (self.taker, self.caller):
            if taking is not None:
                taking.close()



def describe(entity: object) -> str:
    """Name an entity the way a ROS user would recognise it in a log.

    Topics and services by their full names, as ``ros2 topic list`` and
    ``ros2 service list`` write them: rclpy keeps a service's name as it was
    given (``~/change_state`` expanded, ``describe_parameters`` relative),
    rcl knows it resolved.
    """
    # Work the executor runs for a node itself (a transition) is the callable.
    callback = getattr(entity, "callback", entity)
    name = getattr(callback, "__qualname__", None) or repr(callback)
    topic = getattr(entity, "topic_name", None)
    if isinstance(topic, str):
        return f"subscription {topic!r} callback {name}"
    service = getattr(entity, "srv_name", None)
    if isinstance(service, str):
        with contextlib.suppress(Exception):  # destroyed: rcl no longer knows it
            service = entity.service_name  # type: ignore[attr-defined]
        return f"service {service!r} callback {name}"
    return f"{type(entity).__name__.lower()} callback {name}"


def format_error(entity: object, error: BaseException) -> str:
    details = "".join(traceback.format_exception(error)).rstrip()
    return f"{describe(entity)} raised {type(error).__name__}: {error}\n{details}"



def express_work(entry: Entry, args: tuple[Any, ...], *, started: int = 0) -> Work:
    """Async work of ``entry``'s callback called with ``args``, as the C path runs it
    (``started``: when the C path began its first step, in monotonic ns)."""
    entity = entry.entity
    return Work(
        entity, entity.callback, True, entry.depth, entry.done, entry.token, args, meter=entry.meter, started=started
    )



def entities_of(node: Node, kind: str) -> list[Any]:
    if kind == "subscription":
        return list(node.subscriptions)
    if kind == "timer":
        return list(node.timers)
    if kind == "client":
        return list(node.clients)
    if kind == "service":
        return list(node.services)
    return list(node.guards)


