"""Intra-process delivery between the nodes of one process that enable it.

Every rclpy context has one *domain*: the publishers and subscriptions of
its intra-process nodes, by resolved topic name, each with its record here
(the node class that puts them there is in ``_node``). A publish from such
a node goes, in the publishing thread:

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
import contextlib
import inspect
import threading
import time
import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rclpy.lifecycle import LifecyclePublisher
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, QoSCompatibility, QoSProfile, qos_check_compatible
from rclpy.subscription import Subscription

from ..executor import AsyncioExecutor, publisher_gid
from ._copy import copy_message

if TYPE_CHECKING:
    from rclpy.context import Context

__all__ = ["Domain", "PublisherRecord", "SubscriptionRecord", "domain_of"]

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


def _takes_info(callback: Callable[..., Any]) -> bool:
    """Whether a subscription ``callback`` takes ``(message, message_info)``.

    rclpy's rule (``Subscription.callback``): by the signature, one argument
    if it accepts one, else two.

    :raises RuntimeError: it accepts neither, as rclpy's ``create_subscription`` would.
    """
    signature = inspect.signature(callback)
    for arguments in (1, 2):
        with contextlib.suppress(TypeError):
            signature.bind(*(object(),) * arguments)
            return arguments == 2
    raise RuntimeError(
        f"subscription callback {callback!r} must accept one argument (the message) "
        "or two (the message and its info)"
    )


class SubscriptionRecord:
    """A subscription of an intra-process node: its callback, reached in process and over DDS.

    Made before the subscription, whose callback is :attr:`from_dds`, and
    joins the domain before the subscription's DDS reader exists
    (:meth:`expect`): every message of this process that reader will ever
    receive was then delivered in process first, and its DDS copy is
    dropped. Joined after, a message published between the two went over
    DDS only and could arrive after later ones delivered in process (about
    once in fifty runs of a test streaming at 1 kHz). Messages delivered in
    process before the subscription exists wait here until it does
    (:meth:`attach`).
    """

    #: Set when the subscription joins the domain (:meth:`Domain.add_subscription`).
    subscription: Subscription[Any]
    topic: str
    msg_type: Any
    qos: QoSProfile
    max_notes: int

    def __init__(self, node: Node, callback: Callable[..., Any]) -> None:
        self.node = node
        self.callback = callback
        self.wants_info = _takes_info(callback)
        self.is_async = inspect.iscoroutinefunction(callback)
        self.alive = True
        self._lock = threading.Lock()
        self._notes: dict[PublisherRecord, collections.deque[_Note]] = {}
        #: What rclpy calls with every message taken from rcl: the check, then the callback.
        self.from_dds: Callable[[Any, Any], Any] = self._from_dds_async if self.is_async else self._from_dds
        self.call: Callable[..., Any] = self._call_async if self.is_async else self._call
        #: Delivered in process before the subscription exists (``None`` once it does).
        self._early: list[tuple[Any, dict[str, Any]]] | None = None

    def expect(self, topic: str, msg_type: Any, qos: QoSProfile) -> None:
        """What the subscription about to be created will be, so that it can join first."""
        self.topic = topic
        self.msg_type = msg_type
        self._set_qos(qos)
        self._early = []

    def attach(self, subscription: Subscription[Any]) -> None:
        """The subscription exists: what was delivered meanwhile goes to it, in order."""
        with self._lock:
            self.subscription = subscription
            self.topic = subscription.topic_name
            self.msg_type = subscription.msg_type
            self._set_qos(subscription.qos_profile)
            early, executor = self._early, self.executor()
            if early and executor is not None:
                for message, info in early:
                    self._hand(message, info, executor)
            self._early = None

    def _set_qos(self, qos: QoSProfile) -> None:
        self.qos = qos
        depth = qos.depth
        self.max_notes = 4 * depth + 16 if depth > 0 else _MAX_NOTES

    # -- in process ------------------------------------------------------------
    def executor(self) -> AsyncioExecutor | None:
        """The executor to deliver through now (``None``: unloaded, or its node is not on one)."""
        executor = self.node.executor
        return executor if self.alive and isinstance(executor, AsyncioExecutor) else None

    def note(self, publisher: PublisherRecord, note: _Note) -> None:
        with self._lock:
            notes = self._notes.get(publisher)
            if notes is None:
                notes = self._notes[publisher] = collections.deque(maxlen=self.max_notes)
            notes.append(note)

    def deliver(self, message: Any, info: dict[str, Any], executor: AsyncioExecutor) -> bool:
        """Hand ``message`` to the subscription's callback through ``executor`` (what
        :meth:`executor` just gave; unloaded meanwhile, the callback does not run)."""
        if self._early is not None:
            with self._lock:
                if self._early is not None:  # the subscription is still being created
                    self._early.append((message, info))
                    return True
        return self._hand(message, info, executor)

    def _hand(self, message: Any, info: dict[str, Any], executor: AsyncioExecutor) -> bool:
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


class PublisherRecord:
    """A publisher of an intra-process node: where its messages go.

    :param write: publishes a message over DDS, as the publisher's rclpy class does.
    """

    def __init__(self, domain: Domain, node: Node, publisher: Publisher[Any], write: Callable[[Any], None]) -> None:
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
        self._write = write
        #: Set for a lifecycle publisher, which publishes only while activated.
        self._managed = publisher if isinstance(publisher, LifecyclePublisher) else None
        self._lock = threading.Lock()
        self._sequence = 0
        #: Its gid where rclpy's message info carries one (rclpy 9).
        self._gid = publisher_gid(publisher, node=node)
        self._writes = 0
        self._targets: tuple[int, list[SubscriptionRecord], int] = (-1, [], 0)
        self._dds_for_all = False
        #: The graph's last answer (see ``_graph_knows_more``): for how many known, until when, what.
        self._graph_answer: tuple[int, int, bool] = (-1, 0, False)

    def publish(self, message: Any, *, handed_over: bool = False) -> None:
        if self._managed is not None and not self._managed.is_activated:
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

    def targets(self) -> tuple[list[SubscriptionRecord], int]:
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


class Domain:
    """The intra-process publishers and subscriptions of one context."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subs: dict[str, tuple[SubscriptionRecord, ...]] = {}
        self._pub_counts: dict[str, int] = {}
        self._by_subscription: dict[int, SubscriptionRecord] = {}
        #: Bumped whenever a subscription comes or goes.
        self.version = 0

    def subscriptions(self, topic: str) -> tuple[SubscriptionRecord, ...]:
        return self._subs.get(topic, ())

    def publisher_count(self, topic: str) -> int:
        return self._pub_counts.get(topic, 0)

    def add_publisher(self, node: Node, publisher: Publisher[Any], write: Callable[[Any], None]) -> PublisherRecord:
        record = PublisherRecord(self, node, publisher, write)
        with self._lock:
            self._pub_counts[record.topic] = self._pub_counts.get(record.topic, 0) + 1
        return record

    def remove_publisher(self, record: PublisherRecord) -> None:
        with self._lock:
            count = self._pub_counts.get(record.topic, 1) - 1
            if count:
                self._pub_counts[record.topic] = count
            else:
                self._pub_counts.pop(record.topic, None)
        record.close()

    def add_subscription(self, record: SubscriptionRecord) -> None:
        """Let the subscription ``record`` expects receive in process from now on (before it exists)."""
        with self._lock:
            self._subs[record.topic] = (*self._subs.get(record.topic, ()), record)
            self.version += 1

    def attach(self, record: SubscriptionRecord, subscription: Subscription[Any]) -> None:
        """``subscription`` (whose callback is ``record.from_dds``) now exists."""
        topic = record.topic
        record.attach(subscription)
        with self._lock:
            self._by_subscription[id(subscription)] = record
            if record.topic != topic:  # rclpy resolved the name otherwise than expected
                self._drop(record, topic)
                self._subs[record.topic] = (*self._subs.get(record.topic, ()), record)
            self.version += 1

    def discard(self, record: SubscriptionRecord) -> None:
        """The subscription ``record`` expected was never created."""
        with self._lock:
            self._drop(record, record.topic)
            self.version += 1
        record.close()

    def _drop(self, record: SubscriptionRecord, topic: str) -> None:
        rest = tuple(sub for sub in self._subs.get(topic, ()) if sub is not record)
        if rest:
            self._subs[topic] = rest
        else:
            self._subs.pop(topic, None)

    def remove_subscription(self, subscription: Subscription[Any]) -> None:
        with self._lock:
            record = self._by_subscription.get(id(subscription))
            if record is None or record.subscription is not subscription:
                return
            del self._by_subscription[id(subscription)]
            self._drop(record, record.topic)
            self.version += 1
        record.close()


_domains: weakref.WeakKeyDictionary[Context, Domain] = weakref.WeakKeyDictionary()
_domains_lock = threading.Lock()


def domain_of(context: Context) -> Domain:
    """The intra-process domain of ``context`` (one per process, normally)."""
    with _domains_lock:
        domain = _domains.get(context)
        if domain is None:
            domain = _domains[context] = Domain()
        return domain
