"""A cached rcl wait set over the nodes' entities, and what it takes when it wakes.

rclpy's own executors rebuild the wait set in Python on every iteration
(re-collecting every entity of every node); measured here that is most of
their cost. This one collects entities only when they change (rclpy nodes
call ``executor.wake()`` whenever one is created or destroyed) and
otherwise just re-adds the cached handles before each wait, since
``rcl_wait`` clears the slots of entities that were not ready.

Subscriptions, services, clients and QoS events are not waited on at all
but reported by rmw's new-data callbacks (the notifier), so that every
node's seven parameter and type-description services cost the wait nothing
(re-adding them before every wait was a quarter of a ping-pong round trip)
and a request is taken and answered in the loop's own turn. Everything that
becomes ready is *taken at once* (see ``_takes``): rcl wait sets are
level-triggered, so an entity left untaken would wake the next wait
immediately.

On the loop thread, a chain of ``async def`` subscription callbacks runs in
C (``_fastpath.Express``): the wait set gives it the routes (:class:`Routes`,
rebuilt with the table) and takes what it has no route for (:meth:`take_rest`).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import threading
import time
from collections.abc import Callable, Iterable, Sized
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from rclpy.event_handler import EventHandler
from rclpy.exceptions import InvalidHandle
from rclpy.guard_condition import GuardCondition
from rclpy.waitable import NumberOfEntities

from .._compat import (
    WaitSet,
    callback_attribute,
    event_handle,
    loop_is_idle,
    mark_event_ready,
    set_event_index,
    timer_info_parameter,
)
from . import _engine
from ._engine import (
    CLIENT,
    EVENT,
    SERVICE,
    SUBSCRIPTION,
    Caller,
    Express,
    Lock,
    Notifier,
    Route,
    Routes,
    Server,
    Taker,
)
from ._engine import WaitSet as FastWaitSet
from ._entries import KINDS, WOKEN, Entry, entities_of, express_work
from ._message_info import HAS_PUBLISHER_GID
from ._takes import take_messages, take_request, take_response, take_timer, take_waitable

if TYPE_CHECKING:
    from ._dispatch import Dispatcher

__all__: list[str] = []

_log = logging.getLogger(__name__)

#: Tables built at most per rebuild, when entities keep being destroyed under it.
_REBUILD_TRIES = 3


class Held:
    """The handles one table keeps alive (entered), let go together, the last first.

    ``contextlib.ExitStack`` did this at about 3 us a handle (a closure per
    entry): a hundred nodes hold over a thousand handles, and the table is
    collected again whenever a node comes or goes.
    """

    __slots__ = ("_entered",)

    def __init__(self) -> None:
        self._entered: list[Any] = []

    def enter(self, handle: Any) -> None:
        """Enter ``handle`` (raising what its ``__enter__`` raises) and keep it until :meth:`close`."""
        handle.__enter__()
        self._entered.append(handle)

    def close(self) -> None:
        """Exit every handle entered, the last first; the first error is raised after all are exited."""
        entered, self._entered = self._entered, []
        error: BaseException | None = None
        for handle in reversed(entered):
            try:
                handle.__exit__(None, None, None)
            except BaseException as exc:  # every handle is let go; the first failure is reported
                if error is None:
                    error = exc
        if error is not None:
            raise error


@dataclass(slots=True)
class Table:
    """The entities one wait set waits on, collected once per change."""

    by_pointer: dict[str, dict[int, Entry]] = field(default_factory=dict)
    handles: dict[str, list[Any]] = field(default_factory=dict)
    own_guards: dict[int, int] = field(default_factory=dict)
    #: QoS event handlers, added through their event handle directly.
    events: list[tuple[Any, Entry]] = field(default_factory=list)
    #: Any other waitable (actions), through the generic Waitable API.
    waitables: list[Entry] = field(default_factory=list)
    held: Held = field(default_factory=Held)
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
    subscriptions: dict[int, Entry] = field(default_factory=dict)

    def close(self) -> None:
        """Let go of every handle: the compiled wait set's, then those held here."""
        if self.fast is not None:
            self.fast.close()
        self.held.close()



def is_hot_waitable(waitable: object) -> bool:
    """Whether a waitable belongs to the hot wait set: QoS event handlers.

    Their events reach the hot wait set's notifier through rmw's event
    callbacks (or, where rmw has none for an event type, the hot wait set
    waits on them every ``_EVENT_SKIP_MAX_NS``); nothing of theirs costs a wait.
    """
    return isinstance(waitable, EventHandler)



#: Longest time without QoS events in the wait set (ns); see :meth:`EntityWaitSet._events_due_in`.
#: Also the timeout of a poll (a wait whose guard condition is triggered
#: already, which returns at once: see :meth:`EntityWaitSet._before_wait`).
#:
#: A bound on how late a QoS event is seen (commit 833e7cb), not a tuned
#: figure: what it saves is recorded without figures (every entity's QoS
#: events in every wait were "most of an idle-ish executor's CPU" on the
#: project's 2-core shared KVM VM, commit 0d6daf4: see ``_events_due_in``),
#: and no measurement of 50 ms against other values is recorded. Since
#: events come through rmw's event callbacks (commit 7282373) it paces only
#: the event types rmw cannot report so. Not a spin: at most one wait in
#: 50 ms includes them, on one CPU as on more.
_EVENT_SKIP_MAX_NS = 50_000_000

#: Longest time the hot wait set goes without an ``rcl_wait`` while messages
#: keep arriving (ns): timers and guard conditions are looked at least this often.
#:
#: No measurement of the value is recorded (commits 3d3a0fe, 3694b16,
#: 498fdb2 set and use it, none names a figure for it). Not a spin: a burst
#: (:meth:`EntityWaitSet.burst`) runs only while messages are reported or
#: work waits, and returns when none is, on one CPU as on more; what it
#: bounds is how long a chain of callbacks may keep the loop's thread from
#: looking at timers. A plain worker waiting for the GIL meanwhile gets it
#: through CPython's forced switch, whatever the count of CPUs (see
#: ``fastpath/waitset.c``, ``WaitSet_wait``: polls keep the GIL).
_POLL_MAX_NS = 1_000_000

#: After a rebuild that took ``d``, the next waits at least ``d`` times this (when ``d`` is
#: at least :data:`_REBUILD_SPACED_FROM_NS`): entities created or destroyed one by one
#: (a hundred nodes' configure, a shutdown) then cost a rebuild per few of them, and at
#: most a third of the thread's time, instead of one rebuild each.
#:
#: Measured on the project's 2-core VM: a hundred demo nodes' wait sets took 10-12 ms to
#: rebuild (hot and cold), and their bring-up, which creates a talker's publisher and
#: timer one by one, rebuilt for each, back to back: 58% of the loop thread's time, and
#: 2.0-2.8 s of the demo mix's 4.3-5.4 s start-up. A new entity waits that much longer
#: for its first callback (24 ms at a hundred nodes); a destroyed one is let go as late.
_REBUILD_SPACING = 2
#: Rebuilds quicker than this (ns) are never spaced: a few nodes' (0.2-1 ms) cost
#: nothing worth saving, and a test's ``spin_once`` right after creating an entity
#: would find it missing.
_REBUILD_SPACED_FROM_NS = 2_000_000

#: What the notifier watches instead of waiting, by entity kind.
_WATCHED = {"subscription": SUBSCRIPTION, "service": SERVICE, "client": CLIENT}



class EntityWaitSet:
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
        #: Waitables left out after their code raised (see ``_faults``): looked at before each wait.
        self._faults = dispatcher.faults
        self._kinds = kinds
        self._takes_waitable = takes_waitable
        self._own_guards = own_guards
        self._table = Table()
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
            self._notifier = Notifier(guard=self._notifier_guard.handle)
            if isinstance(self._notifier, _engine.Notifier):  # not a stand-in (tests)
                self._express = dispatcher.express(self._notifier, self)
        #: When timers and guard conditions were last looked at (monotonic ns):
        #: as a wait returns, which reports what was ready then.
        self._polled = 0
        #: The handles the notifier calls back for (it holds them), by address.
        self._watched: dict[int, Any] = {}
        #: How many times this wait set entered ``rcl_wait`` (tests, diagnostics).
        self.waits = 0
        #: No rebuild before this (monotonic ns): see :data:`_REBUILD_SPACING`.
        self._rebuild_after = 0
        #: Someone waits for the next rebuild (:meth:`invalidate`): not spaced.
        #: A flag, not ``_rebuild_after = 0``, which a rebuild under way would
        #: overwrite as it ends.
        self._prompt = False
        #: Tables begun (under ``_lock``), and the number of the one in use:
        #: whether the table waited on was collected after some moment (see
        #: :meth:`release_mark`).
        self._begun = 0
        self._installed = 0

    def invalidate(self, *, prompt: bool = False) -> None:
        """Collect the entities again before the next wait.

        :param prompt: not later than that: someone waits for the rebuild
            (see :meth:`release_mark`), so the spacing between rebuilds is waived once.
        """
        if prompt:
            self._prompt = True
        self._routes.dirty = True

    def release_mark(self) -> int:
        """A mark :meth:`released` passes once this wait set waits on a table begun after this call.

        Such a table holds nothing of what left before the call: a node
        removed, then destroyed, is really destroyed (off the ROS graph) only
        once no table holds its entities any more.
        """
        return self._begun + 1

    def released(self, mark: int) -> bool:
        """Whether the table in use was begun at or after ``mark`` (or this wait set is closed)."""
        return self._installed >= mark or self._routes.closed

    @property
    def dirty(self) -> bool:
        """Whether the entities changed since the table was collected."""
        return self._routes.dirty

    def rebuild_due(self) -> bool:
        """Whether the next wait rebuilds the table: it is stale, and the last rebuild not too recent."""
        return self._routes.dirty and self._spaced_ns() <= 0

    def _spaced_ns(self) -> int:
        """How long before the next rebuild may start (ns; 0 or less: now)."""
        return 0 if self._prompt else self._rebuild_after - time.monotonic_ns()

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
        self._prompt = False  # whoever asked sees a table begun from now on
        began = time.monotonic_ns()
        try:
            self._build()
        finally:
            ended = time.monotonic_ns()
            took = ended - began
            self._rebuild_after = ended + _REBUILD_SPACING * took if took >= _REBUILD_SPACED_FROM_NS else 0

    def _build(self) -> None:
        for attempt in range(_REBUILD_TRIES):
            self._begun += 1
            number = self._begun
            self._routes.dirty = False
            table = Table()
            try:
                self._collect(table)
            except BaseException as exc:
                # Never a table's holds left behind: a destroyed entity's handle is
                # let go only once nothing holds it (its node would stay on the graph).
                table.close()
                if isinstance(exc, InvalidHandle) and attempt + 1 < _REBUILD_TRIES:
                    continue  # destroyed by another thread after it was held here: again, without it
                raise
            self._install(table)
            self._installed = number
            return

    def _collect(self, table: Table) -> None:
        """Fill ``table`` with every entity of the dispatcher's nodes, each held; build its wait set."""
        dispatcher = self._dispatcher
        faults = dispatcher.faults
        held = table.held
        extra = NumberOfEntities()
        for kind in KINDS:
            table.by_pointer[kind] = {}
            table.handles[kind] = []
        table.by_pointer["event"] = {}
        notifier = self._notifier
        for node in dispatcher.nodes():
            for kind in self._kinds:
                for entity in entities_of(node, kind):
                    if _hold(held, entity.handle):
                        entry = dispatcher.entry(entity, node, kind)
                        table.by_pointer[kind][entity.handle.pointer] = entry
                        if kind == "subscription":
                            table.subscriptions[id(entity)] = entry
                        if kind == "service" and entry.server is None:  # entries are kept across rebuilds
                            entry.server = _server(entity)
                        elif kind == "client" and entry.caller is None:
                            entry.caller = _caller(entity)
                        watched = _WATCHED.get(kind)
                        if watched is None or not self._watch(
                            entity.handle, watched, plain=kind == "subscription" and not entry.is_async
                        ):
                            # Not event-driven (an rmw without new-data callbacks): waited on.
                            table.handles[kind].append(entity.handle)
                            if (
                                kind == "timer"
                                and entry.is_async
                                and self._express is not None
                                and timer_info_parameter(entity.callback) is None
                            ):
                                table.express_timers[entity.handle.pointer] = _route(entity.handle, entry)
                        elif kind == "subscription" and not entity.raw:
                            taker = entry.taker
                            if taker is None:  # a new entry (entries are kept across rebuilds)
                                entry.taker = taker = _taker(entity)
                            if taker is not None and entry.is_async and not entry.wants_info:
                                table.express[entity.handle.pointer] = _route(taker, entry)
            for waitable in list(node.waitables):
                if not self._takes_waitable(waitable) or faults.left_out(waitable):
                    continue
                event = event_handle(waitable)
                where = "__enter__()"
                try:
                    if not _hold(held, waitable):
                        continue
                    where = "get_num_entities()"
                    counts = waitable.get_num_entities() if event is None else None
                except Exception as error:  # a waitable's own code: never the executor's end
                    dispatcher.waitable_failed(waitable, node, where, error)
                    continue
                entry = dispatcher.entry(waitable, node, "waitable")
                if event is not None:
                    if notifier is not None and self._watch(event, EVENT):
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
        held.enter(context.handle)
        if not table.waitables and not table.events:
            handles = table.handles
            context_handle: Any = context.handle  # rclpy types it optional; an initialised context has one
            table.fast = FastWaitSet(
                context_handle,
                subscriptions=handles["subscription"],
                guard_conditions=guards,
                timers=handles["timer"],
                clients=handles["client"],
                services=handles["service"],
                # Told how long each wait may last: a carrier's publish need not wake it.
                notifier=self._notifier if isinstance(self._notifier, _engine.Notifier) else None,
                # Stays awake, before blocking, for the answer of plain work it handed over.
                handoff=dispatcher.handoff,
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

    def _install(self, table: Table) -> None:
        """Wait on ``table`` from now on; let go of the one before."""
        notifier = self._notifier
        old, self._table = self._table, table
        self._routes.subscriptions = table.express
        self._routes.timers = table.express_timers
        if notifier is not None:
            # Entities gone stop calling back before their handles are let go.
            live = set().union(*(table.by_pointer[kind].keys() for kind in (*_WATCHED, "event")))
            for pointer in self._watched.keys() - live:
                notifier.unwatch(self._watched.pop(pointer))
        old.close()

    def _watch(self, handle: Any, kind: int, *, plain: bool = False) -> bool:
        """Have rmw report new data of ``handle``'s entity; ``False`` where it cannot
        (no notifier, or an rmw without that callback: the entity is then waited on).

        :param plain: its callback is plain: a worker thread may take it (:meth:`carry`).
        """
        if self._notifier is None:
            return False
        pointer = handle.pointer
        if self._watched.get(pointer) is handle:
            return True  # watched since an earlier rebuild (the notifier keeps it)
        try:
            self._notifier.watch(handle, kind, plain)
        except NotImplementedError:
            return False
        except RuntimeError as exc:
            _log.warning("rmw refused a new-data callback (%s); waiting on the entity instead", exc)
            return False
        self._watched[pointer] = handle
        return True

    def wait_and_dispatch(self, timeout_ns: int) -> int:
        """Block in rcl until something is ready (or timeout) and dispatch it.

        :return: the flags of the executor's own guards that fired.
        """
        with self._lock:
            if self._routes.closed:
                return WOKEN
            try:
                retry_at = self._faults.retry_at_ns
                if retry_at:
                    # A waitable left out after it raised is tried again then (see ``_faults``).
                    left = retry_at - time.monotonic_ns()
                    if left > 0:
                        if timeout_ns < 0 or timeout_ns > left:
                            timeout_ns = left
                    elif self._faults.retries_due():
                        self._dispatcher.invalidate(sweep=False)
                if self._routes.dirty:
                    spaced = self._spaced_ns()
                    if spaced <= 0:
                        with self._take_lock:
                            self._rebuild()
                    elif timeout_ns < 0 or timeout_ns > spaced:
                        # The table as it was until then: what it holds stays valid (held),
                        # what left is not dispatched (its work retired), what came waits.
                        timeout_ns = spaced
                return self._wait_and_dispatch(self._table, timeout_ns)
            except Exception:
                self._routes.dirty = True
                self._rebuild_after = 0  # whatever failed: rebuilt at once
                if not self._dispatcher.context.ok():
                    # rclpy.shutdown() while spinning: handles went invalid
                    # under us; the executor stops, nothing to report.
                    return WOKEN
                # Whatever went wrong stays ready (rcl wait sets are
                # level-triggered) and is tried again; the executor lives on.
                _log.exception("dispatching ROS work failed")
                return WOKEN

    def burst(
        self,
        loop: asyncio.AbstractEventLoop,
        eager: Sized,
        run_eager: Callable[[], None],
        *,
        express: bool,
        posted: Sized,
        run_posted: Callable[[], None],
    ) -> None:
        """Take what the notifier reports and run it, without waiting, for as
        long as asyncio has nothing to run and no wait is due (timers and
        guard conditions looked at within ``_POLL_MAX_NS``).

        The hot path of a chain of callbacks in one process: one call per
        round, the checks inlined. What was ``posted`` to the loop's thread
        meanwhile runs here as well (``run_posted``): a response's
        done-callbacks, which make the next call, so a chain of service
        calls stays in this loop too.
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
                if not posted:
                    return
                run_posted()
                continue
            run_eager()

    def _wait_and_dispatch(self, table: Table, timeout_ns: int) -> int:
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
                dispatcher.waitable_failed(entry.entity, entry.node, "add_to_wait_set()", error)
                timeout_ns = 0  # rebuilt without it at once
        timeout_ns, poll = self._before_wait(notifier, timeout_ns)
        try:
            if poll:
                # rclpy's wait lets go of the GIL even for a poll: see WaitSet_wait in fastpath/waitset.c.
                _engine.poll(wait_set, timeout_ns)
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
                            take_waitable(dispatcher, entry)
            for entry in table.waitables:
                try:
                    ready_now = entry.entity.is_ready(wait_set)
                except Exception as error:
                    dispatcher.waitable_failed(entry.entity, entry.node, "is_ready()", error)
                    continue
                if ready_now:
                    take_waitable(dispatcher, entry)
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

    def _wait_fast(self, table: Table, fast: FastWaitSet, notifier: Notifier | None, timeout_ns: int) -> int:
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
        table: Table,
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
                take_timer(dispatcher, timer)
        if notifier is not None:
            self._take_ready(table, notifier.ready())
        entries = by_pointer["subscription"]
        for pointer in subscriptions:
            if (subscription := entries.get(pointer)) is not None:
                take_messages(dispatcher, subscription, 1)
        entries = by_pointer["client"]
        for pointer in clients:
            if (client := entries.get(pointer)) is not None:
                take_response(dispatcher, client)
        entries = by_pointer["service"]
        for pointer in services:
            if (service := entries.get(pointer)) is not None:
                take_request(dispatcher, service)
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

    def entry_of(self, subscription: Any) -> Entry | None:
        """The current entry of ``subscription`` (``None``: not collected, or collecting)."""
        if self._routes.dirty:
            return None
        entry = self._table.subscriptions.get(id(subscription))
        return entry if entry is not None and entry.entity is subscription else None

    def _take_ready(self, table: Table, reported: list[tuple[int, int]]) -> None:
        """Take what the notifier reported: every message of the subscriptions
        that had new data, every request and response waiting, and the QoS
        events that fired."""
        by_pointer = table.by_pointer
        subscriptions = by_pointer["subscription"]
        dispatcher = self._dispatcher
        take = functools.partial(take_messages, dispatcher)
        for pointer, count in reported:
            if (subscription := subscriptions.get(pointer)) is not None:
                take(subscription, count)
            elif (service := by_pointer["service"].get(pointer)) is not None:
                take_request(dispatcher, service, count)
            elif (client := by_pointer["client"].get(pointer)) is not None:
                take_response(dispatcher, client, count)
            elif (event := by_pointer["event"].get(pointer)) is not None:
                mark_event_ready(event.entity)
                take_waitable(dispatcher, event)

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
                    self._watched.clear()
                    notifier.close()  # unwatches everything
                self._table.close()
                self._table = Table()
                self._routes.subscriptions = {}
                self._routes.timers = {}
                if self._notifier_guard is not None:
                    self._notifier_guard.destroy()
                    self._notifier_guard = None
            finally:
                self._take_lock.release()
                self._lock.release()



def _route(first: Any, entry: Entry) -> Route:
    """An express route of ``entry`` (see ``Table.express``); ``first``: its taker or timer's handle."""
    entity = entry.entity
    lane = entry.lane
    return Route(
        first=first,
        entry=entry,
        lane=lane,
        slots=lane.slots,
        # The marker is what the runner carries, for the watchdog's report.
        marker=express_work(entry, ()),
        entity=entity,
        token=entry.token,
        callback=callback_attribute(entity),
    )



def _taker(subscription: Any) -> Taker | None:
    """A compiled take for ``subscription``; ``None`` (rclpy's take) for a type it cannot handle."""
    try:
        return Taker(
            subscription=subscription.handle,
            message_type=subscription.msg_type,
            publisher_gid=HAS_PUBLISHER_GID,
        )
    except (AttributeError, TypeError, ValueError, MemoryError):
        return None



def _server(service: Any) -> Server | None:
    """Compiled takes and answers for ``service``; ``None`` (rclpy's) for a type it cannot handle."""
    try:
        return Server(service=service.handle, srv_type=service.srv_type)
    except (AttributeError, TypeError, ValueError, MemoryError):
        return None


def _caller(client: Any) -> Caller | None:
    """Compiled takes of ``client``'s responses; ``None`` (rclpy's) for a type it cannot handle."""
    try:
        return Caller(client=client.handle, srv_type=client.srv_type)
    except (AttributeError, TypeError, ValueError, MemoryError):
        return None


def _hold(held: Held, handle: Any) -> bool:
    """Keep ``handle`` alive while it sits in the wait set; skip destroyed ones."""
    try:
        held.enter(handle)
    except InvalidHandle:
        return False
    return True

