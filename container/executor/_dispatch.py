"""The rcl side of the executor: cached wait sets, take, hand to lanes.

rclpy's own executors rebuild the wait set in Python on every iteration
(re-collecting every entity of every node); measured here that is most of
their cost. The dispatcher collects entities only when they change (rclpy
nodes call ``executor.wake()`` whenever one is created or destroyed) and
otherwise just re-adds the cached handles before each wait, since ``rcl_wait``
clears the slots of entities that were not ready.

Entities are split over two wait sets. The *hot* one (subscriptions,
timers, services, clients, guard conditions, QoS event handlers) is served
by the event loop's thread; of those, subscriptions, services, clients and
QoS events are not waited on at all but reported by rmw's new-data
callbacks (the notifier), so that every node's seven parameter and
type-description services cost the wait nothing (re-adding them before
every wait was a quarter of a ping-pong round trip) and a request is taken
and answered in the loop's own turn. The *cold* one (other waitables such
as action servers, whose entities rclpy's Waitable API adds itself) is
waited on by a thread of its own.

Everything that becomes ready is *taken at once* and handed to its callback
group's lane. rcl wait sets are level-triggered, so an entity left untaken
would wake the next wait immediately; taking eagerly and bounding what is
pending per entity (see ``_lanes``) avoids both the busy loop and a wait-set
rebuild whenever a group becomes busy or idle.

On the loop thread, a chain of ``async def`` subscription callbacks (one
node's callback publishing to another's) runs in C (``_fastpath.Express``):
this module gives it the routes (``_Table.express``) and takes back every
case but the common one (``Dispatcher._express_*``, ``Lane.express_*``).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import contextvars
import functools
import inspect
import itertools
import logging
import threading
import time
import traceback
import weakref
from collections.abc import Callable, Iterable, Iterator, Sized
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from rclpy.callback_groups import CallbackGroup, ReentrantCallbackGroup
from rclpy.event_handler import EventHandler
from rclpy.exceptions import InvalidHandle
from rclpy.guard_condition import GuardCondition
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile
from rclpy.waitable import NumberOfEntities

from .._compat import (
    WaitSet,
    adopt_future,
    callback_attribute,
    enter_task,
    event_handle,
    fire_timer,
    leave_task,
    loop_is_idle,
    loop_ready_queue,
    mark_event_ready,
    set_event_index,
    subscription_wants_info,
    timer_info_parameter,
    waitable_futures,
)
from . import _fastpath
from ._answers import respond
from ._fastpath import (
    CLIENT,
    EVENT,
    SERVICE,
    SUBSCRIPTION,
    Express,
    KeepLast,
    Lock,
    Notifier,
    Route,
    Routes,
    Taker,
    Token,
    Work,
)
from ._fastpath import WaitSet as FastWaitSet
from ._hooks import ExecutorHooks
from ._lanes import Lane, Retired
from ._message_info import HAS_PUBLISHER_GID

if TYPE_CHECKING:
    from rclpy.context import Context
    from rclpy.executors import Executor

__all__: list[str] = []

_log = logging.getLogger(__name__)

#: Pending firings kept per timer or guard condition while its group is busy.
_COALESCED = 1
#: Pending items kept for a waitable (action goals, QoS events): never drop.
_WAITABLE_DEPTH = 1 << 16
#: Empty takes a keep-all client goes through before its reader counts as
#: drained (see ``Dispatcher.take_response``).
_KEEP_ALL_DRAINED = 1024

#: What :meth:`Dispatcher.wait_and_dispatch` returns when one of the
#: executor's own guard conditions fired.
WOKEN = 1

ErrorHandler = Callable[["Node", object, BaseException], None]


@dataclass(slots=True)
class _Entry:
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
    #: A subscription whose callback takes ``(message, message_info)``.
    wants_info: bool = False


@dataclass(slots=True)
class _Table:
    """The entities one wait set waits on, collected once per change."""

    by_pointer: dict[str, dict[int, _Entry]] = field(default_factory=dict)
    handles: dict[str, list[Any]] = field(default_factory=dict)
    own_guards: dict[int, int] = field(default_factory=dict)
    #: QoS event handlers, added through their event handle directly.
    events: list[tuple[Any, _Entry]] = field(default_factory=list)
    #: Any other waitable (actions), through the generic Waitable API.
    waitables: list[_Entry] = field(default_factory=list)
    held: contextlib.ExitStack = field(default_factory=contextlib.ExitStack)
    wait_set: Any = None
    #: The compiled wait set, where every entity is known by address (no
    #: generic waitable, no QoS event left to the wait set).
    fast: FastWaitSet | None = None
    #: Subscriptions whose messages :class:`Express` takes and runs, by
    #: handle address (see :func:`_route`).
    express: dict[int, Route] = field(default_factory=dict)
    #: Timers whose calls and callbacks :class:`Express` makes, by handle address.
    express_timers: dict[int, Route] = field(default_factory=dict)
    #: Subscription entries by the subscription object's ``id`` (intra-process
    #: deliveries look theirs up on every message: no handle address to read).
    subscriptions: dict[int, _Entry] = field(default_factory=dict)


def describe(entity: object) -> str:
    """Name an entity the way a ROS user would recognise it in a log."""
    # Work the executor runs for a node itself (a transition) is the callable.
    callback = getattr(entity, "callback", entity)
    name = getattr(callback, "__qualname__", None) or repr(callback)
    for attribute, kind in (("topic_name", "subscription"), ("srv_name", "service")):
        value = getattr(entity, attribute, None)
        if isinstance(value, str):
            return f"{kind} {value!r} callback {name}"
    return f"{type(entity).__name__.lower()} callback {name}"


def format_error(entity: object, error: BaseException) -> str:
    details = "".join(traceback.format_exception(error)).rstrip()
    return f"{describe(entity)} raised {type(error).__name__}: {error}\n{details}"


def _is_hot_waitable(waitable: object) -> bool:
    """Whether a waitable belongs to the hot wait set: QoS event handlers.

    Their events reach the hot wait set's notifier through rmw's event
    callbacks (or, where rmw has none for an event type, the hot wait set
    waits on them every ``_EVENT_SKIP_MAX_NS``); nothing of theirs costs a wait.
    """
    return isinstance(waitable, EventHandler)


#: Longest time without QoS events in the wait set (ns); see :meth:`_WaitSet._events_due_in`.
_EVENT_SKIP_MAX_NS = 50_000_000

#: Longest time the hot wait set goes without an ``rcl_wait`` while messages
#: keep arriving (ns): timers and guard conditions are looked at least this often.
_POLL_MAX_NS = 1_000_000

#: Entity kinds, all in the loop's wait set (services and clients are
#: event-driven too, so requests are taken and answered on the loop's thread
#: without a hop); the other thread's wait set serves generic waitables only.
_KINDS = ("subscription", "timer", "client", "guard_condition", "service")

#: What the notifier watches instead of waiting, by entity kind.
_WATCHED = {"subscription": SUBSCRIPTION, "service": SERVICE, "client": CLIENT}


class _WaitSet:
    """One rcl wait set over some kinds of entity, used by one thread at a time."""

    def __init__(
        self,
        dispatcher: Dispatcher,
        *,
        kinds: tuple[str, ...],
        takes_waitable: Callable[[Any], bool],
        own_guards: Callable[[], Iterable[tuple[GuardCondition, int]]],
    ) -> None:
        self._dispatcher = dispatcher
        self._kinds = kinds
        self._takes_waitable = takes_waitable
        self._own_guards = own_guards
        self._table = _Table()
        #: The express routes of the table, and whether it is stale (dirty) or
        #: closed: what the compiled path reads of this wait set.
        self._routes = Routes()
        #: Held by the thread in ``rcl_wait`` (one at a time per wait set).
        self._lock = threading.Lock()
        #: Held while taking and while the table changes: a lane's worker
        #: thread takes (``carry``) while the loop thread sleeps in rcl.
        self._take_lock = Lock()
        #: When the next wait must include the QoS events (monotonic ns).
        self._events_next = 0
        #: New-message callbacks instead of waiting on subscriptions (hot only).
        self._notifier: Notifier | None = None
        self._notifier_guard: GuardCondition | None = None
        #: Takes and runs reported ``async def`` subscription callbacks in C.
        self._express: Express | None = None
        if "subscription" in kinds:
            self._notifier_guard = GuardCondition(
                callback=None, callback_group=None, context=dispatcher.context
            )
            self._notifier = Notifier(guard=self._notifier_guard.handle.pointer)
            if isinstance(self._notifier, _fastpath.Notifier):  # not a stand-in (tests)
                self._express = dispatcher.express(self._notifier, self)
        #: When timers and guard conditions were last looked at (monotonic ns):
        #: as a wait returns, which reports what was ready then.
        self._polled = 0
        #: Handle addresses the notifier calls back for (their handles held).
        self._watched: set[int] = set()
        #: How many times this wait set entered ``rcl_wait`` (tests, diagnostics).
        self.waits = 0

    def invalidate(self) -> None:
        self._routes.dirty = True

    @property
    def dirty(self) -> bool:
        """Whether the entities changed since the table was collected."""
        return self._routes.dirty

    @property
    def routes(self) -> Routes:
        return self._routes

    def take_rest(self, reported: list[tuple[int, int]]) -> None:
        """Take what the compiled path found reported but has no route for (under the take lock)."""
        self._take_ready(self._table, reported)

    @property
    def take_lock(self) -> Lock:
        return self._take_lock

    def _rebuild(self) -> None:
        self._routes.dirty = False
        dispatcher = self._dispatcher
        table = _Table()
        held = table.held
        extra = NumberOfEntities()
        for kind in _KINDS:
            table.by_pointer[kind] = {}
            table.handles[kind] = []
        table.by_pointer["event"] = {}
        notifier = self._notifier
        for node in dispatcher.nodes():
            for kind in self._kinds:
                for entity in _entities_of(node, kind):
                    if _hold(held, entity.handle):
                        entry = dispatcher.entry(entity, node, kind)
                        table.by_pointer[kind][entity.handle.pointer] = entry
                        if kind == "subscription":
                            table.subscriptions[id(entity)] = entry
                        watched = _WATCHED.get(kind)
                        if watched is None or not self._watch(
                            entity.handle.pointer, watched, plain=kind == "subscription" and not entry.is_async
                        ):
                            # Not event-driven (an rmw without new-data callbacks): waited on.
                            table.handles[kind].append(entity.handle)
                            if (
                                kind == "timer"
                                and entry.is_async
                                and self._express is not None
                                and timer_info_parameter(entity.callback) is None
                            ):
                                table.express_timers[entity.handle.pointer] = _route(entity.handle.pointer, entry)
                        elif kind == "subscription" and not entity.raw:
                            entry.taker = taker = _taker(entity)
                            if taker is not None and entry.is_async and not entry.wants_info:
                                table.express[entity.handle.pointer] = _route(taker, entry)
            for waitable in list(node.waitables):
                if not self._takes_waitable(waitable) or dispatcher.is_set_aside(waitable):
                    continue
                event = event_handle(waitable)
                where = "__enter__()"
                try:
                    if not _hold(held, waitable):
                        continue
                    where = "get_num_entities()"
                    counts = waitable.get_num_entities() if event is None else None
                except Exception as error:  # a waitable's own code: never the executor's end
                    dispatcher.set_aside(waitable, node, where, error)
                    continue
                entry = dispatcher.entry(waitable, node, "waitable")
                if event is not None:
                    if notifier is not None and self._watch(event.pointer, EVENT):
                        table.by_pointer["event"][event.pointer] = entry
                    else:
                        table.events.append((event, entry))
                else:
                    assert counts is not None  # get_num_entities() ran: no event handle
                    table.waitables.append(entry)
                    extra += counts
        guards = table.handles["guard_condition"]
        own = list(self._own_guards())
        if self._notifier_guard is not None:
            own.append((self._notifier_guard, 0))
        for gc, flag in own:
            if _hold(held, gc.handle):
                table.own_guards[gc.handle.pointer] = flag
                guards.append(gc.handle)
        context = dispatcher.context
        held.enter_context(context.handle)  # type: ignore[arg-type]
        if not table.waitables and not table.events:
            handles = table.handles
            context_handle: Any = context.handle  # rclpy's typing omits its address
            table.fast = FastWaitSet(
                context_handle.pointer,
                subscriptions=[handle.pointer for handle in handles["subscription"]],
                guard_conditions=[handle.pointer for handle in guards],
                timers=[handle.pointer for handle in handles["timer"]],
                clients=[handle.pointer for handle in handles["client"]],
                services=[handle.pointer for handle in handles["service"]],
                # Told how long each wait may last: a carrier's publish need not wake it.
                notifier=self._notifier if isinstance(self._notifier, _fastpath.Notifier) else None,
            )
        else:
            table.wait_set = WaitSet(
                len(table.handles["subscription"]) + extra.num_subscriptions,
                len(guards) + extra.num_guard_conditions,
                len(table.handles["timer"]) + extra.num_timers,
                len(table.handles["client"]) + extra.num_clients,
                len(table.handles["service"]) + extra.num_services,
                len(table.events) + extra.num_events,
                context.handle,
            )
        old, self._table = self._table, table
        self._routes.subscriptions = table.express
        self._routes.timers = table.express_timers
        if notifier is not None:
            # Entities gone stop calling back before their handles are let go.
            live = set().union(*(table.by_pointer[kind].keys() for kind in (*_WATCHED, "event")))
            for pointer in self._watched - live:
                notifier.unwatch(pointer)
            self._watched &= live
        old.held.close()

    def _watch(self, pointer: int, kind: int, *, plain: bool = False) -> bool:
        """Have rmw report new data of the entity at ``pointer``; ``False`` where it cannot
        (no notifier, or an rmw without that callback: the entity is then waited on).

        :param plain: its callback is plain: a worker thread may take it (:meth:`carry`).
        """
        if self._notifier is None:
            return False
        try:
            self._notifier.watch(pointer, kind, plain)
        except NotImplementedError:
            return False
        except RuntimeError as exc:
            _log.warning("rmw refused a new-data callback (%s); waiting on the entity instead", exc)
            return False
        self._watched.add(pointer)
        return True

    def wait_and_dispatch(self, timeout_ns: int) -> int:
        """Block in rcl until something is ready (or timeout) and dispatch it.

        :return: the flags of the executor's own guards that fired.
        """
        with self._lock:
            if self._routes.closed:
                return WOKEN
            try:
                if self._routes.dirty:
                    with self._take_lock:
                        self._rebuild()
                return self._wait_and_dispatch(self._table, timeout_ns)
            except Exception:
                self._routes.dirty = True
                if not self._dispatcher.context.ok():
                    # rclpy.shutdown() while spinning: handles went invalid
                    # under us; the executor stops, nothing to report.
                    return WOKEN
                # Whatever went wrong stays ready (rcl wait sets are
                # level-triggered) and is tried again; the executor lives on.
                _log.exception("dispatching ROS work failed")
                return WOKEN

    def burst(
        self, loop: asyncio.AbstractEventLoop, eager: Sized, run_eager: Callable[[], None], *, express: bool
    ) -> None:
        """Take what the notifier reports and run it, without waiting, for as
        long as asyncio has nothing to run and no wait is due (timers and
        guard conditions looked at within ``_POLL_MAX_NS``).

        The hot path of a chain of callbacks in one process: one call per
        round, the checks inlined.
        """
        notifier = self._notifier
        fast = self._express if express else None
        monotonic_ns = time.monotonic_ns
        routes = self._routes
        while loop_is_idle(loop) and not routes.dirty and monotonic_ns() - self._polled < _POLL_MAX_NS:
            if notifier is not None and notifier.pending():
                if fast is not None:
                    try:
                        if fast.drain(self._polled + _POLL_MAX_NS):
                            continue  # it ran what it took, and the eager work after
                    except Exception:
                        self._taking_failed()
                        continue
                with self._take_lock:
                    if self._routes.closed or self._routes.dirty:
                        return
                    try:
                        self._take_ready(self._table, notifier.ready())
                    except Exception:
                        self._taking_failed()
            elif not eager:
                return
            run_eager()

    def _wait_and_dispatch(self, table: _Table, timeout_ns: int) -> int:
        notifier = self._notifier
        if notifier is not None and notifier.pending():
            if self.poll_is_recent():
                # Messages are ready and timers were looked at just now:
                # take them without a wait (no attach, no detach, no syscall).
                with self._take_lock:
                    self._take_ready(table, notifier.ready())
                return 0
            timeout_ns = 0
        if table.fast is not None:
            return self._wait_fast(table, table.fast, notifier, timeout_ns)
        wait_set = table.wait_set
        handles = table.handles
        dispatcher = self._dispatcher
        wait_set.clear_entities()
        add = wait_set.add_subscription
        for handle in handles["subscription"]:
            add(handle)
        add = wait_set.add_guard_condition
        for handle in handles["guard_condition"]:
            add(handle)
        add = wait_set.add_timer
        for handle in handles["timer"]:
            add(handle)
        add = wait_set.add_client
        for handle in handles["client"]:
            add(handle)
        add = wait_set.add_service
        for handle in handles["service"]:
            add(handle)
        due_in = self._events_due_in() if table.events else 0
        events = table.events if due_in == 0 else ()
        if events:
            add = wait_set.add_event
            indices = [add(event) for event, _ in events]
        elif table.events and not 0 <= timeout_ns <= due_in:
            # Blocking without the events: the next wait (with them) comes soon.
            timeout_ns = due_in
        for entry in table.waitables:
            try:
                entry.entity.add_to_wait_set(wait_set)
            except Exception as error:
                dispatcher.set_aside(entry.entity, entry.node, "add_to_wait_set()", error)
                timeout_ns = 0  # rebuilt without it at once
        timeout_ns, poll = self._before_wait(notifier, timeout_ns)
        try:
            if poll:
                # rclpy's wait lets go of the GIL even for a poll: see WaitSet_wait in fastpath/waitset.c.
                _fastpath.poll(wait_set.pointer, timeout_ns)
            else:
                wait_set.wait(timeout_ns)
        finally:
            self._waited(notifier)
        if self._routes.closed:
            return WOKEN

        def ready(kind: str) -> list[int]:
            return wait_set.get_ready_entities(kind) if handles[kind] else []

        with self._take_lock:
            flags = self._dispatch_ready(
                table,
                notifier,
                guards=wait_set.get_ready_entities("guard_condition"),
                timers=ready("timer"),
                subscriptions=ready("subscription"),
                clients=ready("client"),
                services=ready("service"),
            )
            if events:
                is_ready = wait_set.is_ready
                for index, (_, entry) in zip(indices, events, strict=True):
                    if is_ready("event", index):
                        # Hand over to rclpy's own handler for the rare ready path.
                        set_event_index(entry.entity, index)
                        if entry.entity.is_ready(wait_set):
                            dispatcher.take_waitable(entry)
            for entry in table.waitables:
                try:
                    ready_now = entry.entity.is_ready(wait_set)
                except Exception as error:
                    dispatcher.set_aside(entry.entity, entry.node, "is_ready()", error)
                    continue
                if ready_now:
                    dispatcher.take_waitable(entry)
        return flags

    def _before_wait(self, notifier: Notifier | None, timeout_ns: int) -> tuple[int, bool]:
        """Arm the notifier and count the wait: the timeout to wait with, and
        whether the wait is a poll (a guard condition already triggered)."""
        poll = False
        if notifier is not None and notifier.arm():
            timeout_ns = 0
        if timeout_ns == 0 and self._notifier_guard is not None:
            # A wait with a zero timeout costs ~90 us here (Fast DDS sleeps on
            # its condition variable until the timeout, plus the kernel's timer
            # slack); with a guard condition already triggered it returns at
            # once (~5 us) and still reports everything else that is ready.
            self._notifier_guard.trigger()
            timeout_ns, poll = _EVENT_SKIP_MAX_NS, True
        self.waits += 1
        return timeout_ns, poll

    def _waited(self, notifier: Notifier | None) -> None:
        """Back from ``rcl_wait``: what it reported is what was ready now.

        A burst of callbacks right after a long wait (a timer's callback
        publishing to another node) may then run without another wait.
        """
        self._polled = time.monotonic_ns()
        if notifier is not None:
            notifier.disarm()

    def _wait_fast(self, table: _Table, fast: FastWaitSet, notifier: Notifier | None, timeout_ns: int) -> int:
        """:meth:`_wait_and_dispatch` on the compiled wait set: one call fills, waits and reads it."""
        timeout_ns, poll = self._before_wait(notifier, timeout_ns)
        try:
            # A poll keeps the GIL: see WaitSet_wait in fastpath/waitset.c.
            ready = fast.wait(timeout_ns, poll)
        finally:
            self._waited(notifier)
        if self._routes.closed:
            return WOKEN
        with self._take_lock:
            if not ready:  # timed out
                return self._dispatch_ready(table, notifier)
            subscriptions, guards, timers, clients, services, _ = ready
            return self._dispatch_ready(
                table,
                notifier,
                guards=guards,
                timers=timers,
                subscriptions=subscriptions,
                clients=clients,
                services=services,
            )

    def _dispatch_ready(
        self,
        table: _Table,
        notifier: Notifier | None,
        *,
        guards: Iterable[int] = (),
        timers: Iterable[int] = (),
        subscriptions: Iterable[int] = (),
        clients: Iterable[int] = (),
        services: Iterable[int] = (),
    ) -> int:
        """Hand what a wait found ready, and what the notifier reported, to lanes.

        Ready addresses that are not in the table belong to waitables (an
        action server's services, a custom waitable's guard condition): the
        waitable itself finds and takes them.

        :return: the flags of the executor's own guards that fired.
        """
        dispatcher = self._dispatcher
        by_pointer = table.by_pointer
        flags = 0
        for pointer in guards:
            own = table.own_guards.get(pointer)
            if own is not None:
                flags |= own
            elif (guard := by_pointer["guard_condition"].get(pointer)) is not None:
                dispatcher.submit(guard, guard.entity.callback, ())
        entries = by_pointer["timer"]
        if timers and table.express_timers and dispatcher.expressing():
            assert self._express is not None  # routes are made only with it
            # Called here, under the locks; their callbacks run once released.
            timers = self._express.call_timers(table.express_timers, timers)
        for pointer in timers:
            if (timer := entries.get(pointer)) is not None:
                dispatcher.take_timer(timer)
        if notifier is not None:
            self._take_ready(table, notifier.ready())
        entries = by_pointer["subscription"]
        for pointer in subscriptions:
            if (subscription := entries.get(pointer)) is not None:
                dispatcher.take_messages(subscription, 1)
        entries = by_pointer["client"]
        for pointer in clients:
            if (client := entries.get(pointer)) is not None:
                dispatcher.take_response(client)
        entries = by_pointer["service"]
        for pointer in services:
            if (service := entries.get(pointer)) is not None:
                dispatcher.take_request(service)
        return flags

    def carry(self) -> None:
        """Take, on a lane's worker thread, what plain callbacks are reported ready for.

        Called by a worker that just ran a plain callback: what that callback
        published to this process's other plain subscriptions is taken here
        and the next callback runs on this same thread (see ``Lane``), instead
        of the loop thread waking to hand it to yet another thread: a plain
        ping-pong costs no thread switch. Left to the loop (which the
        notifier woke anyway) while the table is being rebuilt.
        """
        notifier = self._notifier
        if notifier is None or not self._take_lock.acquire(blocking=False):
            # Whoever takes now (the loop, another worker) takes this too:
            # waiting here would only line threads up behind the lock.
            return
        try:
            if not self._routes.closed and not self._routes.dirty:
                self._take_ready(self._table, notifier.carry())
        except Exception:
            self._taking_failed()
        finally:
            self._take_lock.release()

    def ready_without_wait(self) -> bool:
        """Whether messages wait to be taken and the next ``rcl_wait`` is not due yet."""
        notifier = self._notifier
        return notifier is not None and notifier.pending() and self.poll_is_recent()

    def poll_is_recent(self) -> bool:
        """Whether timers and guard conditions were looked at less than ``_POLL_MAX_NS`` ago."""
        return time.monotonic_ns() - self._polled < _POLL_MAX_NS and not self._routes.dirty

    def entry_of(self, subscription: Any) -> _Entry | None:
        """The current entry of ``subscription`` (``None``: not collected, or collecting)."""
        if self._routes.dirty:
            return None
        entry = self._table.subscriptions.get(id(subscription))
        return entry if entry is not None and entry.entity is subscription else None

    def _take_ready(self, table: _Table, reported: list[tuple[int, int]]) -> None:
        """Take what the notifier reported: every message of the subscriptions
        that had new data, every request and response waiting, and the QoS
        events that fired."""
        by_pointer = table.by_pointer
        subscriptions = by_pointer["subscription"]
        dispatcher = self._dispatcher
        take = dispatcher.take_messages
        for pointer, count in reported:
            if (subscription := subscriptions.get(pointer)) is not None:
                take(subscription, count)
            elif (service := by_pointer["service"].get(pointer)) is not None:
                dispatcher.take_request(service)
            elif (client := by_pointer["client"].get(pointer)) is not None:
                dispatcher.take_response(client, count)
            elif (event := by_pointer["event"].get(pointer)) is not None:
                mark_event_ready(event.entity)
                dispatcher.take_waitable(event)

    def _taking_failed(self) -> None:
        """A take outside a wait raised: rebuild before the next wait; log unless shutting down."""
        self._routes.dirty = True
        if self._dispatcher.context.ok():
            _log.exception("dispatching ROS work failed")

    def _events_due_in(self) -> int:
        """Nanoseconds until a wait must include the QoS events again (0: this one).

        Every publisher and subscription carries QoS event handlers (rclpy
        adds incompatible-QoS and incompatible-type ones by default): ten
        nodes bring sixty of them, and Fast DDS attaches and detaches every
        entity of a wait set on every wait, which measured here was most of
        an idle-ish executor's CPU. Events are rare and level-triggered (a
        ready one stays ready until taken), so they are waited on at most
        every ``_EVENT_SKIP_MAX_NS``: a QoS event is seen within 50 ms.
        """
        now = time.monotonic_ns()
        left = self._events_next - now
        if left > 0:
            return left
        self._events_next = now + _EVENT_SKIP_MAX_NS
        return 0

    def settle(self, *, timeout: float) -> None:
        """Wait until no thread is inside this wait set (it was woken first)."""
        if self._lock.acquire(timeout=timeout):
            self._lock.release()

    def close(self, *, timeout: float) -> None:
        """Release every handle, once no thread waits any more.

        A thread still inside ``rcl_wait`` holds the lock; whoever calls this
        has woken it first through one of its own guard conditions.
        """
        self._routes.closed = True
        if self._lock.acquire(timeout=max(timeout, 0.1)):
            self._take_lock.acquire()
            try:
                notifier = self._notifier
                if notifier is not None:
                    for pointer in self._watched:
                        notifier.unwatch(pointer)
                    self._watched.clear()
                    notifier.close()
                self._table.held.close()
                self._table = _Table()
                self._routes.subscriptions = {}
                self._routes.timers = {}
                if self._notifier_guard is not None:
                    self._notifier_guard.destroy()
                    self._notifier_guard = None
            finally:
                self._take_lock.release()
                self._lock.release()


class Dispatcher:
    """Wait on every node's entities and hand what is ready to lanes.

    :meth:`wait_and_dispatch` serves the hot wait set and is called by one
    thread at a time (the loop's, or the fallback waiter); the cold wait set
    has its own thread, started by :meth:`start`.
    """

    #: Lanes' workers carry on to the plain callbacks their publishes reach (:class:`LaneHooks`).
    carries = True

    def __init__(
        self,
        *,
        context: Context,
        loop: asyncio.AbstractEventLoop,
        hooks: ExecutorHooks,
        reentrant_limit: int,
        future_executor: Executor,
        loop_waits: bool = True,
    ) -> None:
        self.context = context
        #: Whether the loop's own thread waits in rcl (the executor's loop);
        #: on a loop of the user's (``spin_async``) a waiter thread does.
        self._loop_waits = loop_waits
        # The executor's hooks, bound once: several are called per callback.
        #: Triggers one of the executor's guard conditions in the hot wait set.
        self._wake = hooks.wake
        self._nodes = hooks.nodes
        self._loop = loop
        self._post = hooks.post
        self._reentrant_limit = reentrant_limit
        self._future_executor = future_executor
        self._on_error = hooks.report_error
        self._on_done = hooks.callback_completed
        #: ``on_done`` matters only while this is non-empty (the C path skips it otherwise).
        self._done_waiters = hooks.done_waiters
        self._on_response = hooks.response_arrived
        self._progress = hooks.progress
        own_guards = hooks.own_guards
        self._lanes: dict[int, tuple[CallbackGroup, Lane]] = {}
        self._lanes_lock = threading.Lock()
        #: Entity (or node) id -> (the object, its token); see ``_token``.
        self._tokens: dict[int, tuple[object, Token]] = {}
        self._tokens_lock = threading.Lock()
        self._loop_thread: int | None = None
        self._cold_wake = GuardCondition(callback=None, callback_group=None, context=context)
        # Async work submitted on the loop thread, started eagerly once the
        # wait set's lock is released (see ``Lane.run_eager``), each with
        # whether its lane admitted it already (else: as it starts).
        self._eager: collections.deque[tuple[Lane, Work, bool]] = collections.deque()
        self._hot = _WaitSet(
            self, kinds=_KINDS, takes_waitable=_is_hot_waitable, own_guards=own_guards
        )
        self._cold = _WaitSet(
            self,
            kinds=(),
            takes_waitable=lambda waitable: not _is_hot_waitable(waitable),
            own_guards=lambda: [(self._cold_wake, WOKEN)],
        )
        self._cold_thread: threading.Thread | None = None
        self._active = threading.Event()
        self._closed = False
        #: When the loop thread last came back from rcl (``None`` while it
        #: waits there, or while nobody spins): the watchdog's evidence.
        self.busy_since: float | None = None
        #: Whether another thread (the loop watchdog) waits in the loop's place.
        self.relieving = False
        #: How many more callbacks may start (``None``: no limit); see :meth:`admit`.
        self._permits: int | None = 0
        #: Work taken while no permit was left: its starts, keep-last per entity.
        self._held = KeepLast()
        #: Whether a spin holds the gate open (``limit`` other than 0): a
        #: permit given back after the spin returned must not start anything.
        self._gate_open = False
        self._gate_lock = threading.Lock()
        #: Waitables whose own code raised (see :meth:`set_aside`), by identity.
        self._set_aside: dict[int, weakref.ref[object] | object] = {}

    # -- threads ----------------------------------------------------------------
    def start(self) -> None:
        """Let the cold wait set's thread take work (idempotent).

        Like rclpy's executors, nothing new is taken while nobody spins.
        """
        if self._closed:
            return
        self._active.set()
        if self._cold_thread is None:
            self._cold_thread = threading.Thread(
                target=self._serve_cold, name="rcl-cold-waiter", daemon=True
            )
            self._cold_thread.start()

    def pause(self) -> None:
        """Stop taking cold work until the next :meth:`start`; return once it stopped.

        As with rclpy's executors, nothing waits on a node's entities once
        the spin returned: the caller may destroy them (a waitable's own
        handles, which the wait set cannot hold, included).
        """
        self._active.clear()
        with contextlib.suppress(InvalidHandle):
            self._cold_wake.trigger()
        if self._cold_thread is not None and self._cold_thread is not threading.current_thread():
            self._cold.settle(timeout=1.0)

    def _serve_cold(self) -> None:
        while True:
            self._active.wait()
            if self._closed:
                return
            self._cold.wait_and_dispatch(-1)

    def bind_loop_thread(self, ident: int | None) -> None:
        self._loop_thread = ident
        self.busy_since = time.monotonic() if ident is not None else None

    def relieve(self, timeout_ns: int) -> int:
        """Wait and dispatch from a thread other than the loop's, while it is away."""
        self.relieving = True
        try:
            return self.wait_and_dispatch(timeout_ns)
        finally:
            self.relieving = False

    def describe_task(self, task: object) -> str | None:
        """Which node's which callback a lane's runner task carries, if it is one."""
        for lane in self.lanes():
            work = lane.work_of(task)
            if work is not None:
                owner = work.token.node if work.token is not None else None
                try:
                    name = owner.get_fully_qualified_name() if isinstance(owner, Node) else None
                except Exception:  # a node destroyed meanwhile
                    name = None
                return f"{describe(work.entity)} of node {name}" if name else describe(work.entity)
        return None

    @property
    def loop_thread(self) -> int | None:
        return self._loop_thread

    def on_loop_thread(self) -> bool:
        return threading.get_ident() == self._loop_thread

    # -- entities ---------------------------------------------------------------
    def invalidate(self) -> None:
        """Collect entities again before the next waits (any thread).

        Work already taken for an entity that is gone (destroyed, or its node
        removed) is retired at once: it will not start.
        """
        self._hot.invalidate()
        self._cold.invalidate()
        self._sweep_tokens()
        with contextlib.suppress(InvalidHandle):
            self._cold_wake.trigger()

    def nodes(self) -> list[Node]:
        return list(self._nodes())

    @staticmethod
    def members(node: Node) -> tuple[object, ...]:
        """What of ``node`` the wait sets collect: the same members, the same wait sets."""
        found: list[object] = []
        for kind in _KINDS:
            found += _entities_of(node, kind)
        found += list(node.waitables)
        return tuple(found)

    def entry(self, entity: Any, node: Node, kind: str) -> _Entry:
        if kind == "waitable":
            is_async, depth = True, _WAITABLE_DEPTH
        elif kind == "subscription":
            is_async = inspect.iscoroutinefunction(entity.callback)
            depth = max(1, entity.qos_profile.depth)
        elif kind == "service":
            # A request dropped here would leave its caller waiting for good:
            # every request taken is answered (DDS's own history bounds them).
            is_async, depth = inspect.iscoroutinefunction(entity.callback), _WAITABLE_DEPTH
        elif kind == "client":
            is_async, depth = False, 1
        else:
            is_async, depth = inspect.iscoroutinefunction(entity.callback), _COALESCED
        return _Entry(
            wants_info=kind == "subscription" and subscription_wants_info(entity),
            entity=entity,
            node=node,
            lane=self.lane_for(entity.callback_group, node),
            is_async=is_async,
            depth=depth,
            done=functools.partial(self._done, node),
            token=self._token(entity, node),
        )

    def wait_and_dispatch(self, timeout_ns: int) -> int:
        """Wait on the hot wait set and dispatch; see :class:`_WaitSet`.

        On the loop thread, messages that the callbacks just run published to
        this process's other subscriptions are taken and run in the same call,
        for as long as no wait is due and asyncio has nothing else to run:
        a chain of callbacks never leaves this loop for asyncio's.
        """
        if self._eager and self._dispatching_burst() and self._hot.poll_is_recent():
            # Work handed over on this thread since (intra-process deliveries
            # from an asyncio task): run it; no wait is due yet.
            self._run_eager()
            flags = 0
        else:
            if self._eager and self.on_loop_thread():
                timeout_ns = 0  # a poll, then that work runs
            flags = self._wait_and_dispatch_once(timeout_ns)
        if not flags and self._dispatching_burst():
            self._hot.burst(self._loop, self._eager, self._run_eager, express=self._permits is None)
        return flags

    def ros_turn_due(self) -> bool:
        """Whether the loop thread should look at rcl before running more asyncio work.

        Yes when work waits here (messages reported, work handed over on
        the loop thread), when the watchdog waits in the loop's place (the
        loop takes over again), or when timers and guard conditions were
        last looked at ``_POLL_MAX_NS`` or more ago.
        """
        hot = self._hot
        return self.relieving or bool(self._eager) or not hot.poll_is_recent() or hot.ready_without_wait()

    def _dispatching_burst(self) -> bool:
        return self.on_loop_thread() and not self.relieving

    def expressing(self) -> bool:
        """Whether async work taken now may start on the C path (``Express``):
        on the loop thread, nobody relieving it, no ``spin_once`` gate."""
        return self._permits is None and self._dispatching_burst()

    def _wait_and_dispatch_once(self, timeout_ns: int) -> int:
        if self._hot.dirty:
            self._retire_lanes()
        eager = self.on_loop_thread()
        if eager:
            self.busy_since = None
            if self.relieving:
                self._wake()  # it holds the wait set; let it go at once
        try:
            flags = self._hot.wait_and_dispatch(timeout_ns)
        finally:
            if eager:
                self.busy_since = time.monotonic()
        if eager:
            express = self._hot._express
            if express is not None:
                express.run_fired()  # the timers its dispatch called
            self._run_eager()
        return flags

    def _run_eager(self) -> None:
        queue = self._eager
        while queue:
            lane, work, admitted = queue.popleft()
            if admitted:
                lane.run_eager(work)
            else:
                lane.run_express(work)

    def defer(self, lane: Lane, work: Work) -> bool:
        """Keep async ``work`` (submitted on the loop thread) to start eagerly.

        During a dispatch it starts once the wait set's lock is released;
        submitted elsewhere on the loop thread (an intra-process delivery from
        a task) it starts at the loop's next select, which does not block
        while such work waits (see :meth:`wait_and_dispatch`).
        """
        if self.relieving or not self._loop_waits:
            # Nobody drains the queue on this loop's thread: start it now.
            return False
        self._eager.append((lane, work, True))
        return True

    # -- waitables whose own code fails ---------------------------------------------------
    def set_aside(self, waitable: object, node: Node, where: str, error: BaseException) -> None:
        """Leave ``waitable`` out of every wait set from now on: its own code raised in ``where``.

        A waitable is user code run inside the wait itself (rclpy 9's
        ``Waitable.__enter__`` raises ``NotImplementedError`` unless a
        subclass defines it: a waitable written for Jazzy). Raising again on
        every wait would flood the log and starve the node's other entities;
        it is reported once, through its node's logger, and everything else
        keeps running. rclpy's own executors raise out of ``spin`` instead.
        """
        key = id(waitable)
        if self.is_set_aside(waitable):
            return
        try:
            self._set_aside[key] = weakref.ref(waitable)
        except TypeError:  # not weakly referenceable: kept alive here
            self._set_aside[key] = waitable
        self.invalidate()
        message = (
            f"waitable {type(waitable).__qualname__} raised {type(error).__name__} in {where}: {error};"
            " it is left out of the executor's wait set from now on (the node's other callbacks keep running)"
        )
        try:
            node.get_logger().error(message)
        except Exception:  # the node is being destroyed
            _log.error("%s of node %s", message, node)

    def is_set_aside(self, waitable: object) -> bool:
        """Whether :meth:`set_aside` took ``waitable`` out of the wait sets."""
        kept = self._set_aside.get(id(waitable))
        if kept is None:
            return False
        held = kept() if isinstance(kept, weakref.ref) else kept
        if held is waitable:
            return True
        del self._set_aside[id(waitable)]  # another object at a reused address
        return False

    # -- what lanes ask of the dispatcher (LaneHooks) ---------------------------
    def post(self, callback: Callable[..., object], *args: Any) -> None:
        self._post(callback, *args)

    def progress(self) -> asyncio.Future[None]:
        return self._progress()

    def carry(self) -> None:
        self._hot.carry()

    def suspended(self) -> None:
        self._on_done()

    # -- express: the C path's hand-overs (see ``_fastpath.Express``) -----------------
    def express(self, notifier: Notifier, wait_set: _WaitSet) -> Express:
        """The C path that takes and runs ``notifier``'s async subscriptions of
        ``wait_set``, and calls and runs its async timers."""
        return Express(
            notifier=notifier,
            routes=wait_set.routes,
            take_lock=wait_set.take_lock,
            loop=self._loop,
            ready_queue=loop_ready_queue(self._loop),
            eager=self._eager,
            run_eager=self._run_eager,
            enter_task=enter_task,
            leave_task=leave_task,
            on_done=self._on_done,
            done_waiters=self._done_waiters,
            slow=self._express_slow,
            suspended=self._express_suspended,
            failed=self._express_failed,
            release_pending=Lane.express_release,
            take_rest=wait_set.take_rest,
            cancelled_error=asyncio.CancelledError,
        )

    def _work(self, entry: _Entry, message: object) -> Work:
        """The work of a message the C path took (``None``: of a timer it called)."""
        return _express_work(entry, () if message is None else (message,))

    def _express_slow(self, entry: _Entry, message: object) -> None:
        """A message the C path took whose lane cannot start it there (busy, locked, no idle runner)."""
        entry.lane.run_express(self._work(entry, message))

    def _express_suspended(
        self, entry: _Entry, message: object, runner: Any, coro: Any, yielded: Any, context: contextvars.Context
    ) -> None:
        entry.lane.express_suspended(runner, self._work(entry, message), coro, yielded, context)

    def _express_failed(self, entry: _Entry, message: object, error: BaseException | None) -> None:
        entry.lane.express_finished(self._work(entry, message), error)

    # -- tokens: which work may still start ----------------------------------------
    def _token(self, entity: object, node: Node) -> Token:
        """The token of ``entity``, the same across wait-set rebuilds."""
        key = id(entity)
        with self._tokens_lock:
            found = self._tokens.get(key)
            if found is not None and found[0] is entity:
                return found[1]
            token = Token(node)
            self._tokens[key] = (entity, token)
            return token

    def node_token(self, node: Node) -> Token:
        """The token of work the executor runs for ``node`` itself (transitions)."""
        return self._token(node, node)

    def _sweep_tokens(self) -> None:
        """Retire the tokens of entities and nodes that left the executor."""
        nodes = self.nodes()
        live = {id(node) for node in nodes}
        for node in nodes:
            for kind in _KINDS:
                live.update(id(entity) for entity in _entities_of(node, kind))
            live.update(id(waitable) for waitable in list(node.waitables))
        with self._tokens_lock:
            gone = [key for key in self._tokens if key not in live]
            for key in gone:
                _, token = self._tokens.pop(key)
                token.retired = True

    def retire(self, node: Node, *, sweep: bool = True) -> None:
        """Drop and cancel ``node``'s work: it was removed (on the loop thread, or not running).

        :param sweep: also retire the tokens of what left the executor, so
            that its work held at ``spin_once``'s gate is dropped when its
            turn comes; ``False`` keeps that work for the node's return.
        """
        if sweep:
            self._sweep_tokens()
        for lane in self.lanes():
            lane.retire(node)

    def running(self, node: Node) -> list[Work]:
        """``node``'s work that started and has not finished."""
        return [work for lane in self.lanes() for work in lane.running(node)]

    # -- taking ---------------------------------------------------------------
    def take_timer(self, entry: _Entry) -> None:
        tmr = entry.entity
        try:
            with tmr.handle:
                arguments = fire_timer(tmr)
        except InvalidHandle:
            return
        if arguments is None:
            return
        if arguments:
            self.submit(entry, functools.partial(tmr.callback, **arguments), ())
        else:
            self.submit(entry, tmr.callback, ())

    def take_messages(self, entry: _Entry, count: int) -> None:
        """Take up to ``count`` messages: what its new-data callbacks reported (fewer if
        DDS dropped some), or one for a subscription a wait found ready."""
        sub = entry.entity
        callback = sub.callback
        submit = self.submit
        taker = entry.taker
        with_info = entry.wants_info
        if taker is None:
            msg_type, raw = sub.msg_type, sub.raw
            for _ in range(count):
                taken = sub.handle.take_message(msg_type, raw)
                if taken is None:
                    return
                submit(entry, callback, tuple(taken) if with_info else (taken[0],))
        elif with_info:
            for _ in range(count):
                pair = taker.take_with_info()
                if pair is None:
                    return
                submit(entry, callback, pair)
        else:
            for _ in range(count):
                message = taker.take()
                if message is None:
                    return
                submit(entry, callback, (message,))

    def take_response(self, entry: _Entry, count: int = _fastpath.DRAIN) -> None:
        """Take ``count`` times (what the new-response callbacks reported), or
        every response waiting (a wait found the client ready; a fresh watch).

        A client's reader receives the responses to every client of its
        service, and a take of another client's response takes nothing
        (rmw drops it): only a count of takes reaches this client's own
        response behind those. Stopping at the first empty take left it in
        the reader, with no callback to come: a caller among twenty waited
        forever, about once in thirty runs. Without a count, an empty take
        is either, so taking goes on until as many empty takes as the
        reader holds responses.
        """
        cli = entry.entity
        drain = count >= _fastpath.DRAIN
        empty_left = _held_at_most(cli.qos_profile) if drain else 0
        for _ in itertools.repeat(None) if drain else range(count):
            try:
                with cli.handle:
                    header, response = cli.handle.take_response(cli.srv_type.Response)
            except InvalidHandle:
                return
            if header is None:
                if drain:
                    empty_left -= 1
                    if empty_left <= 0:
                        return
                continue  # another client's response (or, draining, none left)
            try:
                future = cli.get_pending_request(header.request_id.sequence_number)
            except KeyError:
                continue  # the caller cancelled the request
            adopt_future(future, self._future_executor)
            future.set_result(response)
            self._on_response()

    def take_request(self, entry: _Entry) -> None:
        """Take every request waiting, each to be answered.

        All at once, not one per wait: service requests sit in a keep-last
        history (depth 10 by default), and twenty peers asking at once would
        otherwise lose the oldest before their turn came.
        """
        srv = entry.entity
        while True:
            try:
                with srv.handle:
                    request, header = srv.handle.service_take_request(srv.srv_type.Request)
            except InvalidHandle:
                return
            if header is None:
                return
            self.run(entry, _serving(srv, request, header, is_async=entry.is_async))

    def take_waitable(self, entry: _Entry) -> None:
        waitable = entry.entity
        try:
            data = waitable.take_data()
        except Exception as error:
            self.set_aside(waitable, entry.node, "take_data()", error)
            return
        for future in waitable_futures(waitable):
            adopt_future(future, self._future_executor)

        async def execute() -> None:
            await waitable.execute(data)

        self.run(entry, execute)

    # -- lanes ----------------------------------------------------------------
    def submit(
        self, entry: _Entry, callback: Callable[..., Any], args: tuple[Any, ...], *, burst: bool | None = None
    ) -> None:
        """Hand ``callback(*args)`` to the entry's lane (through the gate, if one is set).

        :param burst: :meth:`_dispatching_burst`, if the caller asked already.
        """
        work = Work(entry.entity, callback, entry.is_async, entry.depth, entry.done, entry.token, args)
        if burst is None:
            burst = self._dispatching_burst()
        if entry.is_async and burst and self._permits is None:
            # Taken on the loop thread while it dispatches: the lane admits
            # it when it starts, eagerly, right after (one call, not five).
            self._eager.append((entry.lane, work, False))
            return
        if self._permits is None or self.admit(entry.entity, entry.depth, functools.partial(entry.lane.submit, work)):
            entry.lane.submit(work)

    # -- the gate: how many callbacks may start (spin_once) ------------------------
    def admit(self, entity: object, depth: int, start: Callable[[], None]) -> bool:
        """Whether a callback may start now; if not, ``start`` is kept until it may.

        Without a limit (``spin``) everything starts. Under ``spin_once`` one
        callback starts per call, as in rclpy: what was taken meanwhile waits
        here, bounded per entity by its depth like the rcl queue it came from.
        """
        with self._gate_lock:
            permits = self._permits
            if permits is None:
                return True
            if permits > 0:
                self._permits = permits - 1
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
        with self._gate_lock:
            self._gate_open = permits != 0
        while True:
            with self._gate_lock:
                if not self._held or left == 0:
                    self._permits = left
                    return
                self._permits = 0
                start = self._pop_held()
                if left is not None:
                    left -= 1
            start()

    def refund(self) -> None:
        """Give back the permit of a callback that turned out to have nothing
        to run (a task cancelled before its turn, work of a removed node):
        under ``spin_once`` the next one starts instead, as rclpy passes
        over what it will not run. Nothing once the spin has returned."""
        with self._gate_lock:
            if self._permits is None or not self._gate_open:
                return
            if not self._held:
                self._permits += 1
                return
            start = self._pop_held()
        start()

    def _pop_held(self) -> Callable[[], None]:
        """The oldest held work's start (under the gate lock)."""
        start: Callable[[], None] = self._held.pop()
        return start

    def run(self, entry: _Entry, call: Callable[[], Any]) -> None:
        self.submit(entry, call, ())

    def _done(self, node: Node, work: Work, error: BaseException | None) -> None:
        if isinstance(error, Retired):
            self.refund()  # dropped, never started: nothing to report; the next runs
            return
        if error is not None:
            self._on_error(node, work.entity, error)
        self._on_done()

    def lane_for(self, group: CallbackGroup, node: Node | None) -> Lane:
        key = id(group)
        with self._lanes_lock:
            found = self._lanes.get(key)
            if found is not None and found[0] is group:
                return found[1]
            limit = self._reentrant_limit if isinstance(group, ReentrantCallbackGroup) else 1
            owner = node.get_fully_qualified_name() if node is not None else "executor"
            lane = Lane(name=f"{owner}:{type(group).__name__}", limit=limit, loop=self._loop, hooks=self)
            self._lanes[key] = (group, lane)
            return lane

    def _retire_lanes(self) -> None:
        """Close the lanes of groups no entity of any node refers to any more."""
        live = {id(group) for group in _groups_of(self.nodes())}
        with self._lanes_lock:
            dead = [
                (key, lane)
                for key, (_, lane) in self._lanes.items()
                if key not in live and not lane.busy()
            ]
            for key, _ in dead:
                del self._lanes[key]
        for _, lane in dead:
            lane.close(timeout=1.0)

    def lanes(self) -> list[Lane]:
        with self._lanes_lock:
            return [lane for _, lane in self._lanes.values()]

    def close(self, *, timeout: float) -> bool:
        """Stop dispatching, close every lane, release every handle."""
        self._closed = True
        with self._lanes_lock:
            lanes = [lane for _, lane in self._lanes.values()]
            self._lanes.clear()
        joined = all([lane.close(timeout=timeout) for lane in lanes])
        self._hot.close(timeout=timeout)
        self._active.set()
        with contextlib.suppress(InvalidHandle):
            self._cold_wake.trigger()
        if self._cold_thread is not None and self._cold_thread is not threading.current_thread():
            self._cold_thread.join(timeout)
            joined = joined and not self._cold_thread.is_alive()
        self._cold.close(timeout=timeout)
        self._cold_wake.destroy()
        return joined

    def deliver(
        self, subscription: Any, node: Node, callback: Callable[..., Any], args: tuple[Any, ...]
    ) -> bool | None:
        """Hand ``callback(*args)`` to ``subscription``'s lane like a taken message (any thread).

        :return: ``None`` if ``node`` is not in the executor (nothing handed
            over); else whether it was handed over on the loop thread, where
            the loop will see it without being woken.
        """
        entry = self._hot.entry_of(subscription)
        if entry is None or entry.node is not node:
            if node not in self.nodes():
                return None
            entry = self.entry(subscription, node, "subscription")
        burst = self._dispatching_burst()
        self.submit(entry, callback, args, burst=burst)
        return burst


def _held_at_most(qos: QoSProfile) -> int:
    """How many samples a reader with ``qos`` holds at most (keep-all: a bound of ours)."""
    if qos.history == HistoryPolicy.KEEP_LAST and qos.depth > 0:
        return int(qos.depth)
    return _KEEP_ALL_DRAINED


def _route(first: Any, entry: _Entry) -> Route:
    """An express route of ``entry`` (see ``_Table.express``); ``first``: its taker or timer address."""
    entity = entry.entity
    lane = entry.lane
    return Route(
        first=first,
        entry=entry,
        lane=lane,
        slots=lane.slots,
        # The marker is what the runner carries, for the watchdog's report.
        marker=_express_work(entry, ()),
        entity=entity,
        token=entry.token,
        callback=callback_attribute(entity),
    )


def _express_work(entry: _Entry, args: tuple[Any, ...]) -> Work:
    """Async work of ``entry``'s callback called with ``args``, as the C path runs it."""
    entity = entry.entity
    return Work(entity, entity.callback, True, entry.depth, entry.done, entry.token, args)


def _taker(subscription: Any) -> Taker | None:
    """A compiled take for ``subscription``; ``None`` (rclpy's take) for a type it cannot handle."""
    try:
        return Taker(
            subscription=subscription.handle.pointer,
            message_type=subscription.msg_type,
            publisher_gid=HAS_PUBLISHER_GID,
        )
    except (AttributeError, TypeError, ValueError, MemoryError):
        return None


def _serving(srv: Any, request: Any, header: Any, *, is_async: bool) -> Callable[[], Any]:
    """The call that runs a service callback on ``request`` and sends its answer."""
    callback = srv.callback
    response_type = srv.srv_type.Response
    if is_async:

        async def serve_async() -> None:
            respond(srv, await callback(request, response_type()), header)

        return serve_async

    def serve() -> None:
        respond(srv, callback(request, response_type()), header)

    return serve


def _entities_of(node: Node, kind: str) -> list[Any]:
    if kind == "subscription":
        return list(node.subscriptions)
    if kind == "timer":
        return list(node.timers)
    if kind == "client":
        return list(node.clients)
    if kind == "service":
        return list(node.services)
    return list(node.guards)


def _groups_of(nodes: Iterable[Node]) -> Iterator[CallbackGroup]:
    for node in nodes:
        for kind in _KINDS:
            for entity in _entities_of(node, kind):
                yield entity.callback_group
        for waitable in list(node.waitables):
            yield waitable.callback_group


def _hold(stack: contextlib.ExitStack, handle: Any) -> bool:
    """Keep ``handle`` alive while it sits in the wait set; skip destroyed ones."""
    try:
        stack.enter_context(handle)
    except InvalidHandle:
        return False
    return True
