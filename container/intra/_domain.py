"""Intra-process delivery between the nodes of one process that enable it.

Every rclpy context has one *domain*: the publishers and subscriptions of
its intra-process nodes, by resolved topic name. A publish from such a node
goes, in the publishing thread:

1. to each registered subscription on the same topic, of the same type, whose
   QoS DDS would match (``rclpy.qos.qos_check_compatible``), and whose node
   is in an :class:`~container.AsyncioExecutor`: a copy of the message made
   once and shared read-only (or the message itself after :func:`hand_over`)
   is handed to the subscription's callback-group lane through
   :meth:`AsyncioExecutor.deliver`, bounded by its QoS depth like a message
   taken from rcl;
2. to DDS, only when someone else needs it: the graph counts more
   subscriptions on the topic than step 1 served (other processes, nodes
   without intra-process, ``ros2 topic echo``), or the publisher is
   ``transient_local`` (which always publishes through DDS only, so that
   late joiners get its history from DDS).

A subscription served in step 1 still receives the DDS copy of a message it
already got. rclpy's message info carries no publisher gid on Jazzy, so the
copy is recognised otherwise (on every distribution alike): before writing, the publisher leaves the
subscription a note (the DDS sequence number the write will get, and the
time just before it); the DDS copy carries its sequence number and a source
timestamp taken inside the write, and the note that matches both claims it.
Notes are only left while every publisher on the topic is one of the
domain's, so a copy from another writer can never be taken for one of ours.
A publisher that needs DDS while another writer shares its topic publishes
over DDS only from then on: switching back could let a message in process
overtake DDS copies still in flight, and per-publisher order must hold.
"""

from __future__ import annotations

import collections
import inspect
import threading
import time
import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

from rclpy.lifecycle import LifecyclePublisher
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, QoSCompatibility, qos_check_compatible
from rclpy.subscription import Subscription

from .._compat import subscription_wants_info
from ..executor import AsyncioExecutor, publisher_gid
from ._copy import copy_message

if TYPE_CHECKING:
    from rclpy.context import Context

__all__ = ["domain_of", "enable_intra_process", "hand_over", "intra_process_enabled"]

#: Notes kept per publisher for one subscription (KEEP_ALL and deep histories).
_MAX_NOTES = 1024

#: How long the graph's count of a topic's subscribers is taken as is (ns).
_GRAPH_RECHECK_NS = 50_000_000


class _Note:
    """A message delivered in process whose DDS copy is still to come."""

    __slots__ = ("after", "before", "sequence")

    def __init__(self, sequence: int, after: int) -> None:
        #: The DDS publication sequence number the write gets.
        self.sequence = sequence
        #: Nanoseconds (system clock) just before the write.
        self.after = after
        #: Just after it; until then any later source timestamp fits.
        self.before: int | None = None

    def fits(self, stamp: int) -> bool:
        return self.after <= stamp and (self.before is None or stamp <= self.before)


class _Sub:
    """A subscription of an intra-process node."""

    def __init__(self, node: Node, subscription: Subscription[Any]) -> None:
        self.node = node
        self.subscription = subscription
        self.topic: str = subscription.topic_name
        self.msg_type = subscription.msg_type
        self.qos = subscription.qos_profile
        self.callback: Callable[..., Any] = subscription.callback
        self.wants_info = subscription_wants_info(subscription)
        self.is_async = inspect.iscoroutinefunction(self.callback)
        self.alive = True
        depth = self.qos.depth
        self.max_notes = 4 * depth + 16 if depth > 0 else _MAX_NOTES
        self._lock = threading.Lock()
        self._notes: dict[_Pub, collections.deque[_Note]] = {}
        # The DDS path: every message taken from rcl passes the check first.
        from_dds = self._from_dds_async if self.is_async else self._from_dds
        # rclpy 9 annotates subscription callbacks as plain; its executors and ours await an async one.
        subscription.callback = cast("Callable[[Any, Any], None]", from_dds)
        self.call: Callable[..., Any] = self._call_async if self.is_async else self._call

    # -- in process ------------------------------------------------------------
    def executor(self) -> AsyncioExecutor | None:
        """The executor to deliver through now (``None``: unloaded, or its node is not on one)."""
        executor = self.node.executor
        return executor if self.alive and isinstance(executor, AsyncioExecutor) else None

    def note(self, publisher: _Pub, note: _Note) -> None:
        with self._lock:
            notes = self._notes.get(publisher)
            if notes is None:
                notes = self._notes[publisher] = collections.deque(maxlen=self.max_notes)
            notes.append(note)

    def deliver(self, message: Any, info: dict[str, Any], executor: AsyncioExecutor) -> bool:
        """Hand ``message`` to the subscription's callback through ``executor`` (what
        :meth:`executor` just gave; unloaded meanwhile, the callback does not run)."""
        args = (message, info) if self.wants_info else (message,)
        return executor.deliver(self.node, self.subscription, self.call, args)

    def _call(self, *args: Any) -> Any:
        if self.alive:  # unloaded meanwhile: nothing runs after removal
            return self.callback(*args)
        return None

    async def _call_async(self, *args: Any) -> Any:
        if self.alive:
            return await self.callback(*args)
        return None

    # -- over DDS --------------------------------------------------------------
    def _claimed(self, info: dict[str, Any]) -> bool:
        """Whether this DDS copy is of a message already delivered in process."""
        stamp = info.get("source_timestamp")
        sequence = info.get("publication_sequence_number")
        if not isinstance(stamp, int):
            return False
        with self._lock:
            for publisher, notes in list(self._notes.items()):
                for index, note in enumerate(notes):
                    if note.sequence == sequence and note.fits(stamp):
                        # DDS delivers one writer's messages in order: the
                        # notes before this one are of copies DDS dropped.
                        for _ in range(index + 1):
                            notes.popleft()
                        if not notes and not publisher.alive:
                            del self._notes[publisher]
                        return True
        return False

    def _from_dds(self, message: Any, info: dict[str, Any]) -> Any:
        if self._notes and self._claimed(info):
            return None
        return self.callback(message, info) if self.wants_info else self.callback(message)

    async def _from_dds_async(self, message: Any, info: dict[str, Any]) -> Any:
        if self._notes and self._claimed(info):
            return None
        if self.wants_info:
            return await self.callback(message, info)
        return await self.callback(message)

    def close(self) -> None:
        self.alive = False
        with self._lock:
            self._notes.clear()


class _Pub:
    """A publisher of an intra-process node."""

    def __init__(self, domain: _Domain, node: Node, publisher: Publisher[Any]) -> None:
        self.domain = domain
        self.node = node
        self.publisher = publisher
        self.topic: str = publisher.topic_name
        self.msg_type: type = publisher.msg_type  # type: ignore[assignment, unused-ignore]  # rclpy 7 annotates it as a message
        self.qos = publisher.qos_profile
        # Late joiners get a transient_local publisher's history from DDS;
        # in process it would arrive out of order with the new messages.
        self.dds_only = self.qos.durability == DurabilityPolicy.TRANSIENT_LOCAL
        self.alive = True
        self._write = publisher.publish
        self._lock = threading.Lock()
        self._sequence = 0
        #: Its gid where rclpy's message info carries one (rclpy 9).
        self._gid = publisher_gid(publisher)
        self._writes = 0
        self._targets: tuple[int, list[_Sub], int] = (-1, [], 0)
        self._dds_for_all = False
        #: The graph's last answer (see ``_graph_knows_more``): for how many known, until when, what.
        self._graph_answer: tuple[int, int, bool] = (-1, 0, False)

    def publish(self, message: Any, *, handed_over: bool = False) -> None:
        publisher = self.publisher
        if isinstance(publisher, LifecyclePublisher) and not publisher.is_activated:
            self._write(message)  # rclpy's no-op (and its warning, if any)
            return
        if not isinstance(message, self.msg_type):
            # Serialized bytes (or a wrong type, which rclpy refuses).
            with self._lock:
                self._write(message)
                self._writes += 1
            return
        with self._lock:
            self._publish(message, handed_over)

    def _publish(self, message: Any, handed_over: bool) -> None:
        self._sequence += 1
        targets, served = self.targets()
        ready = [(sub, executor) for sub in targets if (executor := sub.executor()) is not None]
        # Someone beyond the subscriptions served here needs DDS if DDS has
        # matched more readers, or the graph knows more (either may learn of
        # a new reader first). The node handle's graph counts take the
        # resolved name as it is (Node.count_subscribers expands it again: 5 us).
        dds = (
            self.dds_only
            or self.publisher.get_subscription_count() > len(ready)
            or self._graph_knows_more(len(ready) + served)
        )
        foreign = False
        if dds and ready:
            graph = self.node.handle
            with graph:
                foreign = graph.get_count_publishers(self.topic) > self.domain.publisher_count(self.topic)
        if foreign:
            # A writer outside the domain shares the topic: its DDS copies
            # could not be told from ours, so DDS serves everyone, from now
            # on (switching back could overtake copies still in flight).
            self._dds_for_all = True
        if self._dds_for_all:
            ready = []
            dds = True
        note: _Note | None = None
        if ready:
            shared = message if handed_over else copy_message(message)
            now = time.time_ns()
            if dds:
                note = _Note(self._writes + 1, now)
                for sub, _ in ready:
                    sub.note(self, note)
            for sub, executor in ready:
                info: dict[str, Any] = {
                    "source_timestamp": now,
                    "received_timestamp": now,
                    "publication_sequence_number": self._sequence,
                    "reception_sequence_number": None,
                }
                if self._gid is not None:
                    info["publisher_gid"] = dict(self._gid)
                sub.deliver(shared, info, executor)
        if dds:
            try:
                self._write(message)
            except BaseException:
                if note is not None:
                    note.sequence = -1  # never written: claims nothing
                raise
            self._writes += 1
            if note is not None:
                note.before = time.time_ns()

    def _graph_knows_more(self, known: int) -> bool:
        """Whether the graph knows more subscribers on the topic than ``known``.

        Asked again when ``known`` changes or ``_GRAPH_RECHECK_NS`` passed,
        not on every publish: the question costs 1.3 us, a sixth of a small
        message's whole hop. DDS's own match count, asked on every publish,
        covers a reader the moment DDS can deliver to it; the graph covers
        the one case it misses (this process's readers not matched yet while
        an outside one is), for which a late answer costs what DDS's own
        discovery costs a new reader anyway.
        """
        now = time.monotonic_ns()
        asked_known, until, more = self._graph_answer
        if asked_known == known and now < until:
            return more
        graph = self.node.handle
        with graph:
            count: int = graph.get_count_subscribers(self.topic)
        more = count > known
        self._graph_answer = (known, now + _GRAPH_RECHECK_NS, more)
        return more

    def targets(self) -> tuple[list[_Sub], int]:
        """The compatible subscriptions, and how many on the topic DDS would not serve."""
        version, targets, served = self._targets
        current = self.domain.version
        if version != current:
            targets, served = [], 0
            for sub in self.domain.subscriptions(self.topic):
                if sub.msg_type is not self.msg_type or _incompatible(self.qos, sub.qos):
                    served += 1  # DDS would not match it either
                elif not self.dds_only:
                    targets.append(sub)
            self._targets = (current, targets, served)
        return targets, served

    def close(self) -> None:
        self.alive = False
        self._targets = (-1, [], 0)


def _incompatible(offered: Any, requested: Any) -> bool:
    compatibility, _ = qos_check_compatible(offered, requested)
    return bool(compatibility == QoSCompatibility.ERROR)


class _Domain:
    """The intra-process publishers and subscriptions of one context."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subs: dict[str, tuple[_Sub, ...]] = {}
        self._pub_counts: dict[str, int] = {}
        self._by_entity: dict[int, _Sub | _Pub] = {}
        #: Bumped whenever a subscription comes or goes.
        self.version = 0

    def subscriptions(self, topic: str) -> tuple[_Sub, ...]:
        return self._subs.get(topic, ())

    def publisher_count(self, topic: str) -> int:
        return self._pub_counts.get(topic, 0)

    def add_publisher(self, node: Node, publisher: Publisher[Any]) -> _Pub:
        with self._lock:
            found = self._by_entity.get(id(publisher))
            if isinstance(found, _Pub) and found.publisher is publisher:
                return found
            record = _Pub(self, node, publisher)
            self._by_entity[id(publisher)] = record
            self._pub_counts[record.topic] = self._pub_counts.get(record.topic, 0) + 1
        setattr(publisher, "publish", record.publish)  # noqa: B010 (an instance attribute)
        return record

    def add_subscription(self, node: Node, subscription: Subscription[Any]) -> _Sub | None:
        if subscription.raw:
            return None  # wants serialized bytes: DDS only
        with self._lock:
            found = self._by_entity.get(id(subscription))
            if isinstance(found, _Sub) and found.subscription is subscription:
                return found
            record = _Sub(node, subscription)
            self._by_entity[id(subscription)] = record
            self._subs[record.topic] = (*self._subs.get(record.topic, ()), record)
            self.version += 1
        return record

    def remove(self, entity: object) -> None:
        with self._lock:
            record = self._by_entity.get(id(entity))
            if record is None:
                return
            if isinstance(record, _Sub):
                if record.subscription is not entity:
                    return
                del self._by_entity[id(entity)]
                rest = tuple(sub for sub in self._subs.get(record.topic, ()) if sub is not record)
                if rest:
                    self._subs[record.topic] = rest
                else:
                    self._subs.pop(record.topic, None)
                self.version += 1
            else:
                if record.publisher is not entity:
                    return
                del self._by_entity[id(entity)]
                count = self._pub_counts.get(record.topic, 1) - 1
                if count:
                    self._pub_counts[record.topic] = count
                else:
                    self._pub_counts.pop(record.topic, None)
        record.close()


_domains: weakref.WeakKeyDictionary[Context, _Domain] = weakref.WeakKeyDictionary()
_domains_lock = threading.Lock()
_enabled: weakref.WeakSet[Node] = weakref.WeakSet()


def domain_of(context: Context) -> _Domain:
    """The intra-process domain of ``context`` (one per process, normally)."""
    with _domains_lock:
        domain = _domains.get(context)
        if domain is None:
            domain = _domains[context] = _Domain()
        return domain


def intra_process_enabled(node: Node) -> bool:
    """Whether :func:`enable_intra_process` was called for ``node``."""
    return node in _enabled


def enable_intra_process(node: Node) -> None:
    """Let ``node`` exchange messages in process with the other such nodes of its context.

    Publishers and subscriptions the node has already, and every one it
    creates later, join; destroying one (or the node) leaves. Delivery in
    process needs the subscribing node to run on an
    :class:`~container.AsyncioExecutor`; everything else goes over DDS as
    before. Idempotent.
    """
    if node in _enabled:
        return
    domain = domain_of(node.context)
    cls = type(node)

    def create_publisher(*args: Any, **kwargs: Any) -> Publisher[Any]:
        publisher: Publisher[Any] = cls.create_publisher(node, *args, **kwargs)
        domain.add_publisher(node, publisher)
        return publisher

    def create_subscription(*args: Any, **kwargs: Any) -> Subscription[Any]:
        subscription: Subscription[Any] = cls.create_subscription(node, *args, **kwargs)
        domain.add_subscription(node, subscription)
        return subscription

    def destroy_publisher(publisher: Publisher[Any]) -> bool:
        domain.remove(publisher)
        return bool(cls.destroy_publisher(node, publisher))

    def destroy_subscription(subscription: Subscription[Any]) -> bool:
        domain.remove(subscription)
        return bool(cls.destroy_subscription(node, subscription))

    for name, method in (
        ("create_publisher", create_publisher),
        ("create_subscription", create_subscription),
        ("destroy_publisher", destroy_publisher),
        ("destroy_subscription", destroy_subscription),
    ):
        setattr(node, name, method)
    _enabled.add(node)
    for publisher in list(node.publishers):
        domain.add_publisher(node, publisher)
    for subscription in list(node.subscriptions):
        domain.add_subscription(node, subscription)


def hand_over(publisher: Publisher[Any], message: Any) -> None:
    """Publish ``message`` and give it up: subscribers in process get the object itself.

    The zero-copy publish, like rclcpp's ``publish(std::unique_ptr<T>)``:
    the caller must not touch ``message`` afterwards, and subscribers must
    treat it as read-only (they may share it). On a publisher without
    intra-process this is ``publisher.publish(message)``.
    """
    # An intra-process publisher's ``publish`` is its record's (see add_publisher).
    record = getattr(vars(publisher).get("publish"), "__self__", None)
    if isinstance(record, _Pub) and record.publisher is publisher:
        record.publish(message, handed_over=True)
    else:
        publisher.publish(message)
