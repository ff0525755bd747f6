"""The node class that puts a node's publishers and subscriptions in its context's domain.

:class:`IntraProcessNode` extends rclpy's ``create_publisher`` and
``create_subscription`` (and their ``destroy_*``). Once the node is
enabled, a new publisher is an :class:`IntraProcessPublisher` (the class
asked for, extended), whose ``publish`` goes through its record in the
domain; a new subscription is created with its record's ``from_dds`` as
callback, which drops the DDS copies of messages it already got in process
and calls the node's callback with the rest. The container's
:class:`~container.LifecycleNode` is such a node; any other node class
gets the same methods from :func:`intra_process_class`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar, cast

from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile
from rclpy.subscription import Subscription
from rclpy.utilities import get_default_context

from ._domain import Domain, PublisherRecord, SubscriptionRecord, domain_of

__all__ = [
    "IntraProcessNode",
    "IntraProcessPublisher",
    "enable_intra_process",
    "hand_over",
    "intra_process_class",
    "intra_process_enabled",
]

N = TypeVar("N", bound=Node)


if TYPE_CHECKING:
    _AnyPublisher = Publisher[Any]
else:  # rclpy 7 (Jazzy): Publisher is not subscriptable
    _AnyPublisher = Publisher


class IntraProcessPublisher(_AnyPublisher):
    """A publisher of an intra-process node: delivers in process, and over DDS when someone there needs it."""

    #: Its record in the domain; ``None`` once it left (destroyed).
    _record: PublisherRecord | None = None

    def publish(self, msg: Any) -> None:
        record = self._record
        if record is None:
            super().publish(msg)
        else:
            record.publish(msg)

    def _publish_over_dds(self, msg: Any) -> None:
        super().publish(msg)

    def _join(self, domain: Domain, node: Node) -> None:
        self._record = domain.add_publisher(node, self, self._publish_over_dds)

    def _leave(self) -> None:
        record, self._record = self._record, None
        if record is not None:
            record.domain.remove_publisher(record)


_classes_lock = threading.Lock()
_publisher_classes: dict[type[Publisher[Any]], type[IntraProcessPublisher]] = {}
_node_classes: dict[type[Node], type[Node]] = {}


def _publisher_class(publisher_class: type[Publisher[Any]]) -> type[IntraProcessPublisher]:
    """``publisher_class`` extended to deliver in process (``Publisher``, ``LifecyclePublisher``, ...)."""
    if issubclass(publisher_class, IntraProcessPublisher):
        return publisher_class
    if publisher_class is Publisher:
        return IntraProcessPublisher
    with _classes_lock:
        extended = _publisher_classes.get(publisher_class)
        if extended is None:
            name = f"IntraProcess{publisher_class.__name__}"
            attributes = {"__module__": __name__, "__qualname__": name}
            created = type(name, (IntraProcessPublisher, publisher_class), attributes)
            extended = _publisher_classes[publisher_class] = cast("type[IntraProcessPublisher]", created)
        return extended


class IntraProcessNode(Node):
    """An rclpy node that exchanges messages in process with the other such nodes of its context.

    Once enabled (the keyword, or :func:`enable_intra_process`), every
    publisher and subscription it creates joins its context's domain, and
    destroying one (or the node) leaves; see :mod:`container.intra`.
    Subscriptions created with ``raw=True`` get bytes over DDS only.

    :param use_intra_process_comms: enabled from the start, so that the
        entities rclpy's constructor creates join too.
    """

    #: The domain the node's new publishers and subscriptions join; ``None``: DDS only.
    _intra_domain: Domain | None = None

    def __init__(self, node_name: str, *, use_intra_process_comms: bool = False, **kwargs: Any) -> None:
        if use_intra_process_comms:
            # The context rclpy's constructor takes, before it creates anything.
            self._intra_domain = domain_of(kwargs.get("context") or get_default_context())
        super().__init__(node_name, **kwargs)

    def create_publisher(
        self, msg_type: Any, topic: str, qos_profile: QoSProfile | int, **kwargs: Any
    ) -> Publisher[Any]:
        domain = self._intra_domain
        if domain is None:
            return super().create_publisher(msg_type, topic, qos_profile, **kwargs)
        kwargs["publisher_class"] = _publisher_class(kwargs.get("publisher_class", Publisher))
        publisher = cast("IntraProcessPublisher", super().create_publisher(msg_type, topic, qos_profile, **kwargs))
        publisher._join(domain, self)
        return publisher

    def destroy_publisher(self, publisher: Publisher[Any]) -> bool:
        # Leaves first: no message goes in process through a destroyed publisher.
        if isinstance(publisher, IntraProcessPublisher) and publisher in self.publishers:
            publisher._leave()
        return super().destroy_publisher(publisher)

    def create_subscription(
        self,
        msg_type: Any,
        topic: str,
        callback: Callable[..., Any],
        qos_profile: QoSProfile | int,
        **kwargs: Any,
    ) -> Subscription[Any]:
        domain = self._intra_domain
        if domain is None or kwargs.get("raw", False):
            return super().create_subscription(msg_type, topic, callback, qos_profile, **kwargs)
        record = SubscriptionRecord(self, callback)
        # Joins before its DDS reader exists (see SubscriptionRecord).
        qos = qos_profile if isinstance(qos_profile, QoSProfile) else QoSProfile(depth=qos_profile)
        record.expect(self.resolve_topic_name(topic), msg_type, qos)
        domain.add_subscription(record)
        from_dds: Any = record.from_dds  # rclpy's annotation knows neither message info nor coroutines
        try:
            subscription = super().create_subscription(msg_type, topic, from_dds, qos_profile, **kwargs)
        except BaseException:
            domain.discard(record)
            raise
        domain.attach(record, subscription)
        return subscription

    def destroy_subscription(self, subscription: Subscription[Any]) -> bool:
        domain = self._intra_domain
        if domain is not None and subscription in self.subscriptions:
            domain.remove_subscription(subscription)
        return super().destroy_subscription(subscription)


def intra_process_class(node_class: type[N]) -> type[N]:
    """``node_class`` if it is an :class:`IntraProcessNode`, else its subclass that is one.

    The subclass takes the ``use_intra_process_comms`` keyword, and keeps
    ``node_class``'s name, module and docstring: it looks the same in logs.
    """
    if issubclass(node_class, IntraProcessNode):
        return node_class
    with _classes_lock:
        extended = _node_classes.get(node_class)
        if extended is None:
            attributes = {
                "__module__": node_class.__module__,
                "__qualname__": node_class.__qualname__,
                "__doc__": node_class.__doc__,
            }
            extended = _node_classes[node_class] = type(node_class.__name__, (IntraProcessNode, node_class), attributes)
        return cast("type[N]", extended)


def intra_process_enabled(node: Node) -> bool:
    """Whether :func:`enable_intra_process` was called for ``node`` (or it was made with the keyword)."""
    return isinstance(node, IntraProcessNode) and node._intra_domain is not None


def enable_intra_process(node: Node) -> None:
    """Let ``node`` exchange messages in process with the other such nodes of its context.

    Every publisher and subscription it creates from now on joins; those it
    has already stay on DDS alone (construct it with
    ``use_intra_process_comms=True`` for every one to join). A node that is
    not an :class:`IntraProcessNode` becomes one: its class becomes
    :func:`intra_process_class` of it. Delivery in process needs the
    subscribing node to run on an :class:`~container.AsyncioExecutor`;
    everything else goes over DDS as before. Idempotent.
    """
    if not isinstance(node, IntraProcessNode):
        node.__class__ = intra_process_class(type(node))
    joining = cast("IntraProcessNode", node)
    if joining._intra_domain is None:
        joining._intra_domain = domain_of(node.context)


def hand_over(publisher: Publisher[Any], message: Any) -> None:
    """Publish ``message`` and give it up: subscribers in process get the object itself.

    The zero-copy publish, like rclcpp's ``publish(std::unique_ptr<T>)``:
    the caller must not touch ``message`` afterwards, and subscribers must
    treat it as read-only (they may share it). On a publisher without
    intra-process this is ``publisher.publish(message)``.
    """
    record = publisher._record if isinstance(publisher, IntraProcessPublisher) else None
    if record is None:
        publisher.publish(message)
    else:
        record.publish(message, handed_over=True)
