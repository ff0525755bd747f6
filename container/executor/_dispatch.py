"""The dispatcher: wait sets, lanes and the gate, put together for one loop.

The *hot* wait set (see ``_waitset``) is served by the event loop's thread:
subscriptions, timers, services, clients, guard conditions and QoS event
handlers. The *cold* one (other waitables such as action servers, whose
entities rclpy's Waitable API adds itself) is waited on by a thread of its
own. What they take is handed to the entity's callback group's lane
(``_lanes``), through the spin_once gate (``_gate``); async work taken on the
loop thread starts eagerly right after the wait that found it.

On the loop thread, a chain of ``async def`` subscription callbacks (one
node's callback publishing to another's) runs in C (``_fastpath.Express``),
which hands back every case but the common one (``Dispatcher._express_*``,
``Lane.express_*``).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import contextvars
import functools
import inspect
import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any

from rclpy.callback_groups import CallbackGroup, ReentrantCallbackGroup
from rclpy.exceptions import InvalidHandle
from rclpy.guard_condition import GuardCondition
from rclpy.node import Node

from .._compat import (
    enter_task,
    leave_task,
    loop_ready_queue,
    subscription_wants_info,
)
from ._accounting import Accounting
from ._cores import usable_cpus
from ._engine import (
    Express,
    Handoff,
    Meter,
    Notifier,
    Token,
    Work,
)
from ._entries import KINDS, WOKEN, Entry, entities_of, express_work
from ._faults import WaitableFaults
from ._gate import Gate
from ._hooks import ExecutorHooks
from ._lanes import Lane, Retired
from ._owners import executor_work
from ._tasks import DoneCallbacks
from ._waitset import EntityWaitSet, is_hot_waitable
from ._workers import WorkerPool

if TYPE_CHECKING:
    from rclpy.context import Context
    from rclpy.executors import Executor

__all__ = ["Dispatcher"]

_log = logging.getLogger(__name__)

#: Pending firings kept per timer or guard condition while its group is busy.
_COALESCED = 1
#: Pending items kept for a waitable (action goals, QoS events): never drop.
_WAITABLE_DEPTH = 1 << 16


class Dispatcher:
    """Wait on every node's entities and hand what is ready to lanes.

    :meth:`wait_and_dispatch` serves the hot wait set and is called by one
    thread at a time (the loop's, or the fallback waiter); the cold wait set
    has its own thread, started by :meth:`start`.
    """

    #: Lanes' workers carry on to the plain callbacks their publishes reach (:class:`LaneHooks`).
    carries = True
    #: The workers the loop's thread woke (:class:`LaneHooks`); its selector waits for them.
    #: Its threads spin for each other's hand-overs only where the process may
    #: use more than one CPU (``handoff.spin``; see ``__init__``).
    handoff: Handoff

    def __init__(
        self,
        *,
        context: Context,
        loop: asyncio.AbstractEventLoop,
        hooks: ExecutorHooks,
        reentrant_limit: int,
        future_executor: Executor,
        loop_waits: bool = True,
        accounting: Accounting | None = None,
    ) -> None:
        self.context = context
        #: Every entity's meter (``None``: accounting is off).
        self.accounting = accounting
        # Spinning for another thread pays only while that thread has a CPU
        # of its own; with one CPU (taskset, a cpuset, a cgroup quota of one
        # CPU or less: see ``_cores``) it only keeps that thread off the CPU.
        # Counted once, here, as the executor is made: a process moved to
        # other CPUs later keeps what its executor was made with.
        self.handoff = Handoff(spin=usable_cpus() > 1)
        #: The threads every lane's plain callbacks run on (:class:`LaneHooks`).
        self.workers = WorkerPool(name="lane", handoff=self.handoff, carries=self.carries)
        #: Whether the loop's own thread waits in rcl (the executor's loop);
        #: on a loop of the user's (``spin_async``) a waiter thread does.
        self._loop_waits = loop_waits
        # The executor's hooks, bound once: several are called per callback.
        #: Triggers one of the executor's guard conditions in the hot wait set.
        self._wake = hooks.wake
        self._nodes = hooks.nodes
        self._loop = loop
        self._post = hooks.post
        self._posted = hooks.posted
        self._run_posted = hooks.run_posted
        self._reentrant_limit = reentrant_limit
        #: Whose futures the responses complete (rclpy's ``Future._set_executor``).
        self.future_executor = future_executor
        self._on_error = hooks.report_error
        self._on_done = hooks.callback_completed
        #: ``on_done`` matters only while this is non-empty (the C path skips it otherwise).
        self._done_waiters = hooks.done_waiters
        #: A client's response was taken (the takes call it).
        self.response_arrived = hooks.response_arrived
        self._progress = hooks.progress
        own_guards = hooks.own_guards
        self._lanes: dict[int, tuple[CallbackGroup, Lane]] = {}
        self._lanes_lock = threading.Lock()
        #: Entity (or node) id -> (the object, its token); see ``_token``.
        self._tokens: dict[int, tuple[object, Token]] = {}
        self._tokens_lock = threading.Lock()
        #: Entity id -> (the entity, its callback, its entry): entries outlive
        #: wait-set rebuilds (see :meth:`entry`); written under ``_tokens_lock``.
        self._entries: dict[int, tuple[object, object, Entry]] = {}
        self._loop_thread: int | None = None
        self._cold_wake = GuardCondition(callback=None, callback_group=None, context=context)
        # Async work submitted on the loop thread, started eagerly once the
        # wait set's lock is released (see ``Lane.run_eager``), each with
        # whether its lane admitted it already (else: as it starts).
        self._eager: collections.deque[tuple[Lane, Work, bool]] = collections.deque()
        #: Waitables whose own code raised (see :meth:`waitable_failed`).
        self.faults = WaitableFaults()
        self._hot = EntityWaitSet(
            self, kinds=KINDS, takes_waitable=is_hot_waitable, own_guards=own_guards
        )
        self._cold = EntityWaitSet(
            self,
            kinds=(),
            takes_waitable=lambda waitable: not is_hot_waitable(waitable),
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
        #: How many callbacks may start (``spin_once``); see :class:`Gate`.
        self.gate = Gate()
        #: Whose futures the responses complete, for their done-callbacks (see :class:`DoneCallbacks`).
        self.response_executor = DoneCallbacks(
            executor=future_executor, post=self._post, on_loop_thread=self._dispatching_burst, gate=self.gate
        )

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
            with executor_work():
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
        """Wait and dispatch from a thread other than the loop's, while it is away.

        Nothing when the loop is back at its own wait: it holds the wait set
        for as long as that wait lasts (for good, in an idle container), and
        it looked for a relief to wake before this one said it was here. The
        loop clears ``busy_since`` before it reads ``relieving``, this sets
        ``relieving`` before it reads ``busy_since``: one of the two sees the
        other (a watchdog once waited out an idle loop's whole wait here,
        its stall never ended).
        """
        self.relieving = True
        try:
            if self.busy_since is None:
                return 0
            return self.wait_and_dispatch(timeout_ns)
        finally:
            self.relieving = False

    @property
    def loop_thread(self) -> int | None:
        return self._loop_thread

    def on_loop_thread(self) -> bool:
        return threading.get_ident() == self._loop_thread

    # -- entities ---------------------------------------------------------------
    def invalidate(self, *, sweep: bool = True, prompt: bool = False) -> None:
        """Collect entities again before the next waits (any thread).

        Work already taken for an entity that is gone (destroyed, or its node
        removed) is retired at once: it will not start.

        :param sweep: look for such work; ``False`` where nothing left (a node
            added) or the caller retires it next. Looking walks every entity
            of every node: done for each of a hundred nodes added one by one,
            it took 0.15-0.3 s of a hundred-node start-up.
        :param prompt: someone waits for the rebuild (:meth:`released`): no
            spacing after the last one.
        """
        self._hot.invalidate(prompt=prompt)
        self._cold.invalidate(prompt=prompt)
        if sweep:
            self._sweep_tokens()
        with contextlib.suppress(InvalidHandle):
            self._cold_wake.trigger()

    def release_mark(self) -> tuple[int, int]:
        """A mark :meth:`released` passes once both wait sets wait on tables collected after this call."""
        return self._hot.release_mark(), self._cold.release_mark()

    def released(self, mark: tuple[int, int]) -> bool:
        """Whether neither wait set still holds what left before ``mark`` was taken.

        A destroyed entity that a wait set still holds is destroyed only as
        it lets go, at its next rebuild (its node stays on the ROS graph
        until then).
        """
        hot, cold = mark
        return self._hot.released(hot) and self._cold.released(cold)

    def nodes(self) -> list[Node]:
        return list(self._nodes())

    @staticmethod
    def members(node: Node) -> tuple[object, ...]:
        """What of ``node`` the wait sets collect: the same members, the same wait sets."""
        found: list[object] = []
        for kind in KINDS:
            found += entities_of(node, kind)
        found += list(node.waitables)
        return tuple(found)

    def entry(self, entity: Any, node: Node, kind: str) -> Entry:
        """The entry of ``entity`` of ``node``, kept across wait-set rebuilds.

        A kept one is used while it still describes the entity: the same
        object (not another at a reused address), the same callback (whether
        it is ``async def`` follows from it), the same node, its token
        not retired (the entity left the executor meanwhile) and its lane
        not closed (its callback group left, or was replaced).
        """
        key = id(entity)
        group = entity.callback_group
        # Read without the lock (a dict read is atomic): a rebuild reads one per entity.
        found = self._entries.get(key)
        if found is not None:
            kept, kept_callback, entry = found
            lane = entry.lane
            if (
                kept is entity
                and kept_callback is getattr(entity, "callback", None)
                and entry.node is node
                and not entry.token.retired
                and not lane.closed
                and self._lanes.get(id(group), (None, None))[1] is lane
            ):
                return entry
        entry = self._new_entry(entity, node, kind)
        with self._tokens_lock:
            self._entries[key] = (entity, getattr(entity, "callback", None), entry)
        return entry

    def _new_entry(self, entity: Any, node: Node, kind: str) -> Entry:
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
        accounting = self.accounting
        return Entry(
            meter=accounting.meter(entity, node, kind) if accounting is not None else None,
            owner=accounting.owner(node) if accounting is not None and kind == "client" else None,
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
        """Wait on the hot wait set and dispatch; see :class:`EntityWaitSet`.

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
            express = self.gate.permits is None
            self._hot.burst(
                self._loop,
                self._eager,
                self._run_eager,
                express=express,
                # spin_once runs no more than the wait it made.
                posted=self._posted if express else (),
                run_posted=self._run_posted,
            )
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
        return self.gate.permits is None and self._dispatching_burst()

    def _wait_and_dispatch_once(self, timeout_ns: int) -> int:
        if self._hot.rebuild_due():
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
    def waitable_failed(self, waitable: object, node: Node, where: str, error: BaseException) -> None:
        """``waitable``'s own code raised in ``where``: leave it out of the wait sets for a
        while, and for good once it keeps raising (see ``_faults``), reported then,
        once, through its node's logger. Everything else keeps running."""
        run = self.faults.failed(waitable)
        if run is None:
            self.invalidate(sweep=False)  # rebuilt without it at once, taken back later
            return
        self.invalidate()
        times, seconds = run
        message = (
            f"waitable {type(waitable).__qualname__} raised {type(error).__name__} in {where}: {error}"
            f" ({times} times in a row over {seconds:.2f} s);"
            " it is left out of the executor's wait set from now on (the node's other callbacks keep running)"
        )
        try:
            node.get_logger().error(message)
        except Exception:  # the node is being destroyed
            _log.error("%s of node %s", message, node)

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
    def express(self, notifier: Notifier, wait_set: EntityWaitSet) -> Express:
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

    def _work(self, entry: Entry, message: object, started: int = 0) -> Work:
        """The work of a message the C path took (``None``: of a timer it called)."""
        return express_work(entry, () if message is None else (message,), started=started)

    def _express_slow(self, entry: Entry, message: object) -> None:
        """A message the C path took whose lane cannot start it there (busy, locked, no idle runner)."""
        entry.lane.run_express(self._work(entry, message))

    def _express_suspended(
        self,
        entry: Entry,
        message: object,
        runner: Any,
        coro: Any,
        yielded: Any,
        context: contextvars.Context,
        started: int,
    ) -> None:
        entry.lane.express_suspended(runner, self._work(entry, message, started), coro, yielded, context)

    def _express_failed(self, entry: Entry, message: object, error: BaseException | None) -> None:
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

    def node_meter(self, node: Node) -> Meter | None:
        """The meter of work the executor runs for ``node`` itself (transitions)."""
        return self.accounting.meter(node, node, "transition") if self.accounting is not None else None

    def _sweep_tokens(self) -> None:
        """Retire the tokens of entities and nodes that left the executor."""
        nodes = self.nodes()
        live = {id(node) for node in nodes}
        for node in nodes:
            for kind in KINDS:
                live.update(id(entity) for entity in entities_of(node, kind))
            live.update(id(waitable) for waitable in list(node.waitables))
        with self._tokens_lock:
            gone = [key for key in self._tokens if key not in live]
            for key in gone:
                _, token = self._tokens.pop(key)
                token.retired = True
            for key in [key for key in self._entries if key not in live]:
                del self._entries[key]
        if self.accounting is not None:
            self.accounting.forget(live)

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

    # -- lanes ----------------------------------------------------------------
    def submit(
        self,
        entry: Entry,
        callback: Callable[..., Any],
        args: tuple[Any, ...],
        *,
        burst: bool | None = None,
        late_ns: int = 0,
    ) -> None:
        """Hand ``callback(*args)`` to the entry's lane (through the gate, if one is set).

        :param burst: :meth:`_dispatching_burst`, if the caller asked already.
        :param late_ns: how long ago the work was due (a timer's overdue
            firing), for its lateness; else it arrived now.
        """
        work = Work(
            entry.entity,
            callback,
            entry.is_async,
            entry.depth,
            entry.done,
            entry.token,
            args,
            meter=entry.meter,
            arrived=time.monotonic_ns() - late_ns if late_ns > 0 else 0,
        )
        if burst is None:
            burst = self._dispatching_burst()
        if entry.is_async and burst and self.gate.permits is None:
            # Taken on the loop thread while it dispatches: the lane admits
            # it when it starts, eagerly, right after (one call, not five).
            self._eager.append((entry.lane, work, False))
            return
        gate = self.gate
        if gate.permits is None or gate.admit(entry.entity, entry.depth, functools.partial(entry.lane.submit, work)):
            entry.lane.submit(work)

    def run(self, entry: Entry, call: Callable[[], Any]) -> None:
        self.submit(entry, call, ())

    def _done(self, node: Node, work: Work, error: BaseException | None) -> None:
        if isinstance(error, Retired):
            self.gate.refund()  # dropped, never started: nothing to report; the next runs
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
            name = node.get_fully_qualified_name() if node is not None else "executor"
            # A group of several nodes (rare) carries the first one's: see ``_owners``.
            owner = self.accounting.owner(node) if self.accounting is not None and node is not None else None
            lane = Lane(name=f"{name}:{type(group).__name__}", limit=limit, loop=self._loop, hooks=self, owner=owner)
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
        joined = self.workers.close(timeout=timeout) and joined
        self._hot.close(timeout=timeout)
        self._active.set()
        with contextlib.suppress(InvalidHandle):
            self._cold_wake.trigger()
        if self._cold_thread is not None and self._cold_thread is not threading.current_thread():
            self._cold_thread.join(timeout)
            joined = joined and not self._cold_thread.is_alive()
        self._cold.close(timeout=timeout)
        self._cold_wake.destroy()
        # Nothing takes any more: the handles the entries' compiled takes hold go.
        with self._tokens_lock:
            entries = [entry for _, _, entry in self._entries.values()]
            self._entries.clear()
        for entry in entries:
            entry.close()
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



def _groups_of(nodes: Iterable[Node]) -> Iterator[CallbackGroup]:
    for node in nodes:
        for kind in KINDS:
            for entity in entities_of(node, kind):
                yield entity.callback_group
        for waitable in list(node.waitables):
            yield waitable.callback_group


