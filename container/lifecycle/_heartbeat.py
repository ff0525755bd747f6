"""Heartbeats between managed nodes and the lifecycle manager, as ``bond/Status``.

Nav2 bonds its manager with each node through bondcpp, a handshake both sides
must run. Only bond's wire format is kept here: every managed node publishes
``bond/Status`` on ``/bond`` (``id`` = its full name, ``instance_id`` = one
value per node object, so a respawned node is recognisable) and the manager
listens. No handshake means a node is monitored whoever hosts it, and the
manager can tell "silent" (crash, hang) from "said goodbye" (``active`` false,
sent when the node is destroyed).

A node beats only while something listens on the topic (a manager, or
``ros2 topic echo /bond``): it starts when a subscription matches, with one
beat at once, and stops when the last one goes. Unheard beats at Nav2's
10 Hz cost a LiDAR node a sixth of its CPU (measured: 0.37 % of a core of
2.2 %) for nothing; Nav2 itself beats only on a bond its manager formed.

The node side runs in the node's default callback group on purpose: a
callback of that group that hangs silences the heartbeat too, which is how a
hang is told from a slow but healthy node.
"""

from __future__ import annotations

import asyncio
import time
import uuid
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rclpy.qos import QoSProfile

if TYPE_CHECKING:
    from rclpy.callback_groups import CallbackGroup
    from rclpy.publisher import Publisher
    from rclpy.subscription import Subscription
    from rclpy.timer import Timer

__all__ = [
    "DEFAULT_HEARTBEAT_PERIOD",
    "DEFAULT_HEARTBEAT_TIMEOUT",
    "HEARTBEAT_TOPIC",
    "MIN_HEARTBEAT_PERIOD",
    "Heartbeat",
    "HeartbeatPublisher",
    "HeartbeatWatch",
    "status_type",
]

#: Absolute, so that nodes in any namespace reach one manager; ids are full names.
HEARTBEAT_TOPIC = "/bond"
#: Nav2 nodes beat every 0.1 s.
DEFAULT_HEARTBEAT_PERIOD = 0.1
#: Shortest period accepted, on both sides: 100 heartbeats a second.
MIN_HEARTBEAT_PERIOD = 0.01
#: bond's DEFAULT_HEARTBEAT_TIMEOUT; informational in the message.
DEFAULT_HEARTBEAT_TIMEOUT = 4.0

_QOS = QoSProfile(depth=10)

#: Instances remembered per node: the current one, a respawned one, a few strays.
_INSTANCES_KEPT = 8


def status_type() -> Any:
    """``bond.msg.Status``, or ``None`` when the generated package is missing.

    Imported late so that nodes still load (without heartbeats) in an
    environment where the interface packages have not been built.
    """
    try:
        from bond.msg import Status
    except ImportError:
        return None
    return Status


def _require_status_type() -> Any:
    status = status_type()
    if status is None:
        raise ImportError("the 'bond' interface package is not installed")
    return status


class HeartbeatPublisher:
    """Publish a node's heartbeat every ``period`` seconds until :meth:`close`.

    :param timeout: what the node advertises as its heartbeat timeout; the
        manager applies its own ``bond_timeout``.
    """

    def __init__(
        self,
        node: Node,
        *,
        period: float = DEFAULT_HEARTBEAT_PERIOD,
        timeout: float = DEFAULT_HEARTBEAT_TIMEOUT,
        topic: str = HEARTBEAT_TOPIC,
    ) -> None:
        status = _require_status_type()
        self._node = node
        self._status = status
        self._id = node.get_fully_qualified_name()
        self.instance_id = uuid.uuid4().hex
        self.period = period
        self.timeout = timeout
        # Node.create_* directly: a lifecycle base would otherwise make these
        # follow the node's state, and heartbeats must flow in every state.
        # The matched event runs in the timer's group (the node's default).
        self._publisher: Publisher[Any] | None = Node.create_publisher(
            node, status, topic, _QOS, event_callbacks=PublisherEventCallbacks(matched=self._matched)
        )
        self._timer: Timer | None = Node.create_timer(node, period, self._beat, autostart=False)
        self._matched(None)

    @property
    def beating(self) -> bool:
        """Whether heartbeats go out now (something listens on the topic)."""
        return self._timer is not None and not self._timer.is_canceled()

    def _matched(self, _info: object) -> None:
        timer, publisher = self._timer, self._publisher
        if timer is None or publisher is None:
            return
        if publisher.get_subscription_count() == 0:
            timer.cancel()
        elif timer.is_canceled():
            timer.reset()  # wakes the wait set through the timer's own guard condition
            self._publish(active=True)  # a new listener hears the node at once

    def _beat(self) -> None:
        # Plain, not async: it must not wait for the event loop, which
        # another node's callback may hold; a hang of this node's own
        # default group still silences it, which is what tells a hang.
        self._publish(active=True)

    def _publish(self, *, active: bool) -> None:
        if self._publisher is None:
            return
        message = self._status(
            id=self._id,
            instance_id=self.instance_id,
            active=active,
            heartbeat_timeout=float(self.timeout),
            heartbeat_period=float(self.period),
        )
        message.header.stamp = self._node.get_clock().now().to_msg()
        self._publisher.publish(message)

    def close(self) -> None:
        """Say goodbye (``active`` false) and stop beating."""
        if self._timer is not None:
            self._node.destroy_timer(self._timer)
            self._timer = None
        if self._publisher is not None:
            self._publish(active=False)
            Node.destroy_publisher(self._node, self._publisher)
            self._publisher = None


@dataclass(frozen=True, slots=True)
class Heartbeat:
    """The last heartbeat seen from one node."""

    #: ``time.monotonic()`` when it arrived.
    received: float
    instance_id: str
    active: bool


class HeartbeatWatch:
    """Remember the last heartbeat of every node on the heartbeat topic.

    Must be used from the executor's event loop: the subscription callback
    is ``async`` so that it runs there and may wake waiting coroutines.
    """

    def __init__(
        self,
        node: Node,
        *,
        callback_group: CallbackGroup | None = None,
        topic: str = HEARTBEAT_TOPIC,
    ) -> None:
        status = _require_status_type()
        self._node = node
        #: Per node, the last heartbeat of each instance of it.
        self._seen: dict[str, dict[str, Heartbeat]] = {}
        self._changed: asyncio.Event | None = None
        # rclpy's annotation knows no async callbacks; AsyncioExecutor runs them.
        self._subscription: Subscription[Any] | None = node.create_subscription(
            status,
            topic,
            self._receive,  # type: ignore[arg-type]
            _QOS,
            callback_group=callback_group,
        )

    async def _receive(self, message: Any) -> None:
        instances = self._seen.setdefault(message.id, {})
        instances[message.instance_id] = Heartbeat(time.monotonic(), message.instance_id, message.active)
        if len(instances) > _INSTANCES_KEPT:  # a peer inventing instance ids costs nothing
            del instances[min(instances, key=lambda key: instances[key].received)]
        if self._changed is not None:
            self._changed.set()
            self._changed = None

    def last(self, node_name: str, *, instance: str | None = None) -> Heartbeat | None:
        """The last heartbeat of ``node_name``: of ``instance`` if given, else of any instance."""
        instances = self._seen.get(node_name, {})
        if instance is not None:
            return instances.get(instance)
        return max(instances.values(), key=lambda seen: seen.received, default=None)

    async def wait(self, node_name: str, *, after: float, timeout: float) -> Heartbeat | None:
        """Wait for a live heartbeat of ``node_name`` received after ``after``.

        :return: the heartbeat, or ``None`` if none came within ``timeout``.
        """
        deadline = time.monotonic() + timeout
        while True:
            seen = self.last(node_name)
            if seen is not None and seen.active and seen.received > after:
                return seen
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            if self._changed is None:
                self._changed = asyncio.Event()
            try:
                await asyncio.wait_for(self._changed.wait(), remaining)
            except TimeoutError:
                return None

    def close(self) -> None:
        if self._subscription is not None:
            self._node.destroy_subscription(self._subscription)
            self._subscription = None
