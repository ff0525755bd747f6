"""``AsyncioExecutor``: an rclpy executor driven by an asyncio event loop.

Where the time goes, measured here (design notes, ``docs/design.md``): rclpy's
executors spend most of a round trip rebuilding their wait set in Python, and
each hand-over between threads costs tens of microseconds. So:

* the loop's own thread sleeps in the rcl wait set (``_selector``) and takes
  messages itself, with a wait set that is rebuilt only when entities change
  (``_dispatch``);
* ``async def`` callbacks run as asyncio tasks on that same thread: no hop;
* plain callbacks may block, so each runs on a worker thread (``_lanes``):
  one hop to the first of a chain, none after it (the worker carries on with
  what its callback published), and a slow node delays only itself.

On a loop the executor did not create (``await executor.spin_async()`` from
``asyncio.run``), a waiter thread takes the loop thread's place in rcl and
hands async work over with ``call_soon_threadsafe``: correct, just slower.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import contextvars
import enum
import functools
import inspect
import sys
import threading
import time
import types
import weakref
from collections.abc import Callable, Coroutine, Generator, Sized
from typing import TYPE_CHECKING, Any, TypeAlias, TypeVar

from rclpy.callback_groups import CallbackGroup
from rclpy.context import Context
from rclpy.exceptions import InvalidHandle
from rclpy.executors import Executor
from rclpy.task import Future as RclFuture

from .._compat import (
    executor_guards,
    loop_is_idle,
    running_loop,
    runs_plain_callback,
    wake_guard,
    woken_by_an_addition,
    wraps_an_awaitable,
)
from .._errors import ExecutorError
from ._accounting import Accounting
from ._answers import waiting_for
from ._bridge import adapt, as_exception, contained, drive_in_thread, is_adapted, mirror
from ._culprit import Culprit, TaskOrigins, handle_culprit
from ._dispatch import Dispatcher
from ._engine import Work, announce
from ._entries import WOKEN, describe, format_error
from ._inbox import Inbox, Post, call_soon
from ._lanes import Lane
from ._loop import AccountedLoop
from ._owners import EXECUTOR, OWNER, Account, Owner, Whose, executor_context, executor_work
from ._selector import RclSelector
from ._tasks import TaskFuture, TaskLaneHooks, plain_work, settle, settle_from
from ._watchdog import LoopWatchdog

if TYPE_CHECKING:
    from rclpy.node import Node

__all__ = ["AsyncioExecutor", "CallbackErrorHandler", "ExecutorState"]

T = TypeVar("T")

if TYPE_CHECKING:
    # What asyncio hands a task factory: a coroutine; before 3.12 also the
    # generator it wraps another awaitable in (see wraps_an_awaitable).
    if sys.version_info >= (3, 12):
        _TaskCoro: TypeAlias = Coroutine[Any, Any, T]
    else:
        _TaskCoro: TypeAlias = Coroutine[Any, Any, T] | Generator[Any, None, T]


class ExecutorState(enum.Enum):
    """The life of an :class:`AsyncioExecutor`; each refuses what it cannot do.

    ``IDLE`` (created, or between spins) -> ``SPINNING`` -> ``IDLE`` ...;
    :meth:`~AsyncioExecutor.shutdown` leads to ``SHUT_DOWN``, through
    ``STOPPING`` while a spin is still returning. Once stopping, ``spin*()``
    and ``create_task()`` raise :class:`~container.ExecutorError`.
    """

    IDLE = "idle"
    SPINNING = "spinning"
    STOPPING = "stopping"
    SHUT_DOWN = "shut down"


_CLOSED = frozenset({ExecutorState.STOPPING, ExecutorState.SHUT_DOWN})

#: Called with the node, the entity and the exception a callback raised.
CallbackErrorHandler = Callable[["Node", object, BaseException], None]

#: :meth:`AsyncioExecutor.adapt`'s default owner: the caller's context says.
_CALLER: Any = object()

#: How often :meth:`AsyncioExecutor.retire` looks whether a node's callbacks ended.
_RETIRE_POLL_S = 0.01

#: How long at most :meth:`AsyncioExecutor.retire` waits for answers its node's
#: callbacks gave to clients still being discovered: one just discovered matches
#: within milliseconds, and a client that never matches holds an unload this long.
_ANSWERS_WAIT_S = 1.0

#: How often, and how long at most, :meth:`AsyncioExecutor.retire` looks
#: whether the wait sets let go of a removed node's entities (a rebuild: a
#: few ms at a hundred nodes).
_RELEASE_POLL_S = 0.001
_RELEASE_WAIT_S = 2.0

#: How long an ``await`` on an rclpy future may sleep before looking again,
#: for futures completed outside the executor (no wake-up reaches us then).
_RCL_FUTURE_POLL_S = 0.01


class AsyncioExecutor(Executor):
    """Run rclpy nodes' callbacks on an asyncio event loop.

    A drop-in for rclpy's executors (``add_node``, ``remove_node``, ``spin``,
    ``spin_once``, ``spin_until_future_complete``, ``shutdown``, and
    ``rclpy.spin(node, executor=...)``) that can also run on an already
    running loop: ``await executor.spin_async()``.

    :param context: the rclpy context; the default one if ``None``.
    :param reentrant_limit: how many callbacks of one
        ``ReentrantCallbackGroup`` may run at once.
    :param on_callback_error: called when a callback raises, after the
        error is logged through the node's logger; a place for fault
        containment (the container sends the node through error processing).
    :param shutdown_timeout: seconds :meth:`shutdown` waits for running
        callbacks by default.
    :param stall_after: seconds the loop thread may spend in one callback
        before the watchdog counts it as stuck, waits in rcl in its place and,
        for a plugin's work, reports it (``None``: no watchdog).
    :param watchdog_reports: whether the watchdog logs stalls of plugin
        work (``False``: it still relieves the loop and counts stalls for
        diagnostics, but logs nothing; for a command whose output is read).
    :param num_threads: ``MultiThreadedExecutor``'s keyword, so code written
        for it runs unchanged: here it sets ``reentrant_limit`` (plain
        callbacks of different groups always run on threads of their own).
    :param accounting: time every callback per node, group and callback
        (:attr:`accounting`); ``False`` only to measure what it costs.
    """

    def __init__(
        self,
        *,
        context: Context | None = None,
        reentrant_limit: int = 8,
        on_callback_error: CallbackErrorHandler | None = None,
        shutdown_timeout: float = 5.0,
        stall_after: float | None = 1.0,
        watchdog_reports: bool = True,
        num_threads: int | None = None,
        accounting: bool = True,
    ) -> None:
        # An engine other than the one asked for (the compiled one did not build): said once.
        announce()
        super().__init__(context=context)
        # Refused after rclpy's part is built: its __del__ needs it, and
        # releases it again (a refusal before left an AttributeError there).
        for keyword, value in (("num_threads", num_threads), ("reentrant_limit", reentrant_limit)):
            if value is not None and value < 1:
                Executor.shutdown(self, timeout_sec=0)
                raise ExecutorError(f"{keyword} must be at least 1, not {value}")
        if num_threads is not None:
            reentrant_limit = num_threads
        # The engine is not the one asked for (the compiled one did not load): said once.
        announce()
        self._reentrant_limit = reentrant_limit
        self._on_callback_error = on_callback_error
        self._shutdown_timeout = shutdown_timeout
        self._stall_after = stall_after
        self._watchdog_reports = watchdog_reports
        #: Which plugin callback each task on the loop came from, for the watchdog.
        self._origins = TaskOrigins(self._runner_work)
        #: Every task this executor's task factory made, until it is done (see :meth:`_hold`).
        self._held_tasks: set[asyncio.Task[Any]] = set()
        #: The loop watchdog while the owned loop spins (see ``watchdog``).
        self._watchdog: LoopWatchdog | None = None
        #: Its thread, started by the first spin and parked between spins.
        self._loop_watchdog: LoopWatchdog | None = None
        #: What each node's work costs (see ``accounting``).
        self._accounting = (
            Accounting(loop_thread=self._loop_thread_ident, stuck_after_s=stall_after or 1.0) if accounting else None
        )
        # One guard condition wakes the loop for everything: entities changed
        # (rclpy's base class), a file descriptor is ready (the selector's
        # watcher), a hand-over arrived in the inbox. Each guard condition in
        # the wait set costs on every single wait.
        with executor_work():  # the Python engine's watcher thread is the executor's
            self._selector = RclSelector(guard=wake_guard(self))
        self._loop: asyncio.AbstractEventLoop = (
            AccountedLoop(self._selector, unattributed=self._accounting.unattributed)
            if self._accounting is not None
            else asyncio.SelectorEventLoop(self._selector)
        )
        #: Every hand-over to a loop's thread: to the owned loop, one guard
        #: trigger instead of call_soon_threadsafe's three wake-ups.
        self._inbox = Inbox(loop=self._loop, wake=self._guard_trigger)
        self._loop.set_task_factory(self._make_task)
        self._running_loop: asyncio.AbstractEventLoop | None = None
        self._completion_waiters: list[asyncio.Future[None]] = []
        #: The loop's next select must look in rcl (a spin_once has begun).
        self._rcl_turn_owed = False
        #: When the running ``spin_once`` times out (monotonic s): past it, a select
        #: that must not block looks in rcl no more.
        self._once_deadline: float | None = None
        #: Nodes removed while nobody spun (and what they had then), retired
        #: when the next spin starts unless added back first (see :meth:`remove_node`).
        self._removed_idle: weakref.WeakKeyDictionary[Node, tuple[object, ...]] = weakref.WeakKeyDictionary()
        self._dispatcher = self._make_dispatcher(self._loop)
        self._stopped: asyncio.Future[None] | None = None
        self._progress: asyncio.Future[None] | None = None
        self._state = ExecutorState.IDLE
        #: Guards ``_state``; notified whenever it changes.
        self._state_changed = threading.Condition()
        self._task_lane: Lane | None = None
        #: What the lane of plain tasks asks of the executor, with the threads it runs them on.
        self._task_hooks = TaskLaneHooks(post=self._inbox.post, progress=self._progress_future)
        #: The outcome of releasing resources, once released.
        self._released: bool | None = None
        self._release_lock = threading.Lock()
        _live.add(self)

    # -- public surface ---------------------------------------------------------
    @property
    def shutdown_timeout(self) -> float:
        """Seconds :meth:`shutdown` waits for running callbacks by default."""
        return self._shutdown_timeout

    @property
    def accounting(self) -> Accounting | None:
        """What each node's work costs, per window (``None``: built with ``accounting=False``)."""
        return self._accounting

    def _account(self, owner: object, kind: str) -> Account | None:
        """The account of ``kind`` of ``owner`` (``OWNER``'s value; ``None`` nobody's), or
        ``None`` when nothing is metered: accounting off, or the executor's own work."""
        accounting = self._accounting
        if accounting is None or owner is EXECUTOR:
            return None
        return (owner if isinstance(owner, Owner) else accounting.unattributed).account(kind)

    def _loop_thread_ident(self) -> int | None:
        return self._dispatcher.loop_thread

    @property
    def watchdog(self) -> LoopWatchdog | None:
        """The loop watchdog while the executor spins its own loop."""
        return self._watchdog

    @property
    def state(self) -> ExecutorState:
        """Where the executor is in its life: idle, spinning, stopping or shut down."""
        return self._state

    @property
    def _closed(self) -> bool:
        # Identity, not set membership: an Enum's hash is Python code, and
        # this is asked on every intra-process delivery.
        state = self._state
        return state is ExecutorState.STOPPING or state is ExecutorState.SHUT_DOWN

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        """The event loop callbacks run on (the running one under ``spin_async``)."""
        return self._running_loop or self._loop

    def wake(self) -> None:
        """Collect entities again: a node created or destroyed one."""
        # Only a removal can leave work of an entity that is gone; looking for
        # it walks every entity of every node, which was 58% of the configure
        # of a hundred demo nodes (two entities each: two walks).
        self._dispatcher.invalidate(sweep=not woken_by_an_addition())
        super().wake()

    def add_node(self, node: Node) -> bool:
        added = super().add_node(node)
        if not added:
            # Already ours: rclpy's own add_node calls this again through
            # the node's executor setter; nothing changed.
            return False
        with self._state_changed:
            members = self._removed_idle.pop(node, None)
        if not _same(members, Dispatcher.members(node)):
            # A new node takes nothing away; one back, changed, may have lost entities meanwhile.
            self._dispatcher.invalidate(sweep=members is not None)
        # else: back before anyone spun, unchanged: the wait sets still hold it.
        return added

    def remove_node(self, node: Node) -> None:
        """Stop running ``node``'s callbacks: none that has not started yet will.

        Its ``async def`` callbacks in progress are cancelled; plain ones
        already running on a thread go on until they return (see
        :meth:`retire`, which waits for them).
        """
        super().remove_node(node)
        dispatcher = self._dispatcher
        if self._on_loop():
            dispatcher.invalidate(sweep=False)
            dispatcher.retire(node)  # which sweeps
        elif self.loop.is_running():
            dispatcher.invalidate()
            self._inbox.post_to(self.loop, dispatcher.retire, node)
        else:
            # Nobody spins: rclpy.spin_once(node, executor=...) adds and
            # removes the node around every call. The next spin retires it
            # unless it is back by then: what was taken for it and is held
            # at spin_once's gate then runs (as rcl keeps what rclpy has not
            # taken), an async callback parked at an await goes on (as
            # rclpy's tasks of a node that is back do), and an unchanged
            # node costs no rebuild of the wait sets.
            with self._state_changed:
                self._removed_idle[node] = Dispatcher.members(node)
        self._guard_trigger()

    async def retire(self, node: Node, *, timeout: float, released: bool = True) -> list[str]:
        """:meth:`remove_node`, then wait up to ``timeout`` for its running callbacks,
        and up to a second of that for the answers they gave to reach clients
        still being discovered (:meth:`_answered`).

        :param released: once none runs, also wait until the wait sets no
            longer hold the node's entities, so that destroying the node next
            takes it off the ROS graph at once: an unload answered while
            ``ros2 node list`` still showed the node, and a node of the same
            name loaded right after found the old one's ``/rosout`` publisher
            still registered (rcl warns, and the old node's end then takes
            the new one's ``/rosout`` away). Else they let go at their next
            rebuild, the node's destruction completing then.

        :return: the callbacks of ``node`` still running when ``timeout``
            ran out (plain callbacks blocked in their thread), or with
            ``released`` the wait sets if they still hold the node after
            :data:`_RELEASE_WAIT_S` (nobody serves them), described for a log
            line; empty when nothing of the node runs or is held any more.
        """
        if node.executor is self:
            # Through the node's own setter, which calls remove_node and then
            # forgets this executor: destroying the node next (an unload) no
            # longer wakes it once per entity. Each such wake collected every
            # node's entities again, twice: a hundred idle nodes' shutdown took 7.8 s.
            node.executor = None  # type: ignore[assignment]  # rclpy types the setter without None
        else:
            self.remove_node(node)
        dispatcher = self._dispatcher
        # Taken once the node left: any table begun after this holds nothing of it.
        mark = dispatcher.release_mark() if released else None
        if mark is not None:
            dispatcher.invalidate(sweep=False, prompt=True)
        loop = self.loop
        deadline = loop.time() + timeout
        while running := dispatcher.running(node):
            if loop.time() >= deadline:
                return [describe(work.entity) for work in running]
            await asyncio.sleep(_RETIRE_POLL_S)
        await self._answered(node, by=min(deadline, loop.time() + _ANSWERS_WAIT_S))
        released_by = loop.time() + _RELEASE_WAIT_S
        # Bounded: a wait set nobody serves (the executor paused) lets go at
        # its next rebuild, and the node's destruction completes then.
        while mark is not None and not dispatcher.released(mark):
            if loop.time() >= released_by:
                return [f"the executor's wait sets (not rebuilt within {_RELEASE_WAIT_S:g} s)"]
            await asyncio.sleep(_RELEASE_POLL_S)
        return []

    async def _answered(self, node: Node, *, by: float) -> None:
        """Wait until the answers its callbacks gave went out to their clients, or ``by``.

        An answer to a client not known to be matched yet (its response reader
        still being discovered) waits in the resender thread (``_answers``);
        destroying its service drops it. A ``change_state`` cancelled by the
        unload itself was answered so, and its caller waited for good.
        """
        loop = self.loop
        while waiting := waiting_for(node):
            if loop.time() >= by:
                node.get_logger().warning(
                    f"{waiting} answer(s) of its services still waited for their clients to match: dropped"
                )
                return
            await asyncio.sleep(_RETIRE_POLL_S)

    def _on_loop(self) -> bool:
        return running_loop() is self.loop
    def spin(self) -> None:
        """Run callbacks until :meth:`shutdown` or the context shuts down."""
        self._run_owned(self._until_stopped())

    def spin_once(self, timeout_sec: float | None = None) -> None:
        """Run callbacks until one of them completes, or ``timeout_sec`` passes."""
        # Listening before the gate opens: what was held since the last spin
        # (a ready timer, a task) starts as it opens and may complete before
        # the loop first runs the coroutine that waits for it.
        # rclpy's timeout runs from the call: so does this one, not from
        # once the loop runs (setting up a spin takes a few hundred us here,
        # which a spin_once(timeout_sec=period / 2) beside a 1 ms timer cannot spare).
        deadline = None if timeout_sec is None or timeout_sec < 0 else time.monotonic() + timeout_sec
        completed = self._loop.create_future()
        self._completion_waiters.append(completed)
        self._once_deadline = deadline
        try:
            self._run_owned(self._until_a_callback_completes(completed, deadline), permits=1)
        finally:
            self._once_deadline = None
            with contextlib.suppress(ValueError):
                self._completion_waiters.remove(completed)

    def spin_until_future_complete(
        self,
        future: RclFuture[Any] | asyncio.Future[Any] | Coroutine[Any, Any, Any],
        timeout_sec: float | None = None,
    ) -> None:
        """Run callbacks until ``future`` is done or ``timeout_sec`` passes.

        ``future`` may be an rclpy future, an asyncio future, or a coroutine
        (run as a task on the loop).
        """
        self._run_owned(self._until_done(future, timeout_sec))

    def spin_once_until_future_complete(
        self,
        future: RclFuture[Any],
        timeout_sec: float | None = None,  # type: ignore[override]
    ) -> None:
        self._run_owned(self._until_done(future, timeout_sec))

    async def spin_async(self) -> None:
        """Run callbacks on the running event loop until shutdown.

        On the executor's own loop (``executor.loop``) the loop thread waits in
        rcl directly; on any other loop a waiter thread does and hands work
        over, which costs one thread hop per async callback.
        """
        loop = asyncio.get_running_loop()
        if loop is self._loop:
            await self._until_stopped()
            return
        # The loop's own tasks may await rclpy futures too (see _make_task):
        # lent the task factory while spinning, unless the loop has one.
        lent = loop.get_task_factory() is None
        if lent:
            loop.set_task_factory(self._make_task)
        try:
            with self._spinning_on(loop):
                waiter = threading.Thread(
                    target=self._wait_in_thread, name="rcl-waiter", daemon=True
                )
                with executor_work():
                    waiter.start()
                try:
                    await self._stopped_future()
                finally:
                    self._signal_stopped()
                    await asyncio.to_thread(waiter.join)
        finally:
            if lent and loop.get_task_factory() == self._make_task:
                loop.set_task_factory(None)

    def create_task(  # type: ignore[override]
        self, callback: Callable[..., Any] | Coroutine[Any, Any, Any], *args: Any, **kwargs: Any
    ) -> RclFuture[Any]:
        """Run ``callback`` while the executor spins; return an rclpy future of its result.

        As in rclpy, nothing runs before the executor spins, and under
        :meth:`spin_once` a task counts as the one callback it runs.
        Coroutines and plain callables run on the loop's thread, one at a
        time, as rclpy's single-threaded executor runs them (rclpy routes
        future done-callbacks through here). One exception: a coroutine of
        rclpy's that hands a plain callback to ``await_or_execute`` (an
        action server's execute callback, which may block for the whole
        goal) runs on a worker thread instead.

        :raises ExecutorError: the executor is shut down (or shutting down).
        """
        self._refuse_if_closed("create a task")
        result = TaskFuture(executor=self)
        begin: Callable[[], None]
        # Whose it is: the caller's (a node's callback, task or thread), wherever it runs.
        owner = OWNER.get()
        if inspect.iscoroutinefunction(callback) and runs_plain_callback(callback, args):
            function: Callable[..., Any] = callback
            account = self._account(owner, "task")

            def drive_here() -> None:
                if result.cancelled():
                    return
                if account is None:
                    settle_from(result, lambda: drive_in_thread(function(*args, **kwargs)))
                    return
                OWNER.set(account.owner)  # in this call's own context: what it starts is the owner's
                account.call(0, settle_from, result, lambda: drive_in_thread(function(*args, **kwargs)))

            begin = functools.partial(self._tasks_lane().submit, plain_work(drive_here, self._task_done))
        elif inspect.iscoroutine(callback) or inspect.iscoroutinefunction(callback):
            begin = self._loop_task(callback, args, kwargs, result, owner)
        else:
            plain: Callable[..., Any] = callback  # type: ignore[assignment]  # not a coroutine here
            loop_account = self._account(owner, "loop_callback")

            def run() -> None:
                if result.cancelled():
                    self._dispatcher.gate.refund()
                    return
                if loop_account is not None:
                    loop_account.call(0, settle_from, result, lambda: plain(*args, **kwargs))
                else:
                    settle_from(result, lambda: plain(*args, **kwargs))
                self._callback_completed()
                self._notify_progress()  # a coroutine awaiting the task's future looks again now

            begin = functools.partial(self._inbox.post_to, self.loop, run)
        if self._dispatcher.gate.admit(result, 1 << 16, begin):
            begin()
        self._notify_progress()
        return result

    def _loop_task(
        self,
        callback: Callable[..., Any] | Coroutine[Any, Any, Any],
        args: tuple[Any, ...],
        kwargs: dict[str, Any],
        result: TaskFuture,
        owner: Whose,
    ) -> Callable[[], None]:
        """What starts a coroutine task of :meth:`create_task` on the loop (``owner``: the caller's)."""
        loop = self.loop
        coro: Coroutine[Any, Any, Any] = (
            callback if inspect.iscoroutine(callback) else callback(*args, **kwargs)  # type: ignore[operator]
        )

        def finished(task: asyncio.Task[Any]) -> None:
            settle(result, task)
            self._callback_completed()
            # A coroutine awaiting the task's future (parked on the progress
            # future) looks again now, not at the next 10 ms poll.
            self._notify_progress()

        def start() -> None:
            if result.cancelled():
                coro.close()
                self._dispatcher.gate.refund()
                return
            # Suspended after its first step, it counts as run (spin_once), as in rclpy.
            adapted = self.adapt(contained(coro), on_suspend=self._callback_completed, owner=owner)
            if OWNER.get() is owner:
                task = loop.create_task(adapted)
            else:  # started from another thread: it runs as the caller's all the same
                context = contextvars.copy_context()
                context.run(OWNER.set, owner)
                task = loop.create_task(adapted, context=context)
            task.add_done_callback(finished)

            def cancel() -> None:
                # At once where nobody else runs the loop: posted, the cancel
                # would queue behind a wake-up of the task already queued (an
                # await that completed), and the task would run a step past
                # the await it was cancelled at, which rclpy's never does.
                if not loop.is_running() or running_loop() is loop:
                    task.cancel()
                else:
                    call_soon(loop, task.cancel)

            result.stop_with(cancel)

        return functools.partial(call_soon, loop, start)

    def _task_done(self, work: Work, error: BaseException | None) -> None:
        self._callback_completed()

    def run_in_group(
        self,
        group: CallbackGroup,
        call: Callable[[], Any],
        *,
        node: Node | None = None,
    ) -> asyncio.Future[Any]:
        """Run ``call`` as if it were a callback of ``group``; await its result.

        Serialises container-driven work, such as lifecycle transitions, with
        the node's own callbacks of that group. A coroutine function runs on
        the loop; a plain one on the group's worker thread.

        Must be called on the executor's loop thread.
        """
        loop = self.loop
        outcome: asyncio.Future[Any] = loop.create_future()
        is_async = inspect.iscoroutinefunction(call)
        result: list[Any] = []

        def capture() -> Any:
            if is_async:

                async def run_async() -> None:
                    result.append(await call())

                return run_async()
            result.append(call())
            return None

        def settle(error: BaseException | None) -> None:
            if outcome.done():
                return
            if error is not None:
                outcome.set_exception(as_exception(error))
            else:
                outcome.set_result(result[0] if result else None)

        def done(work: Work, error: BaseException | None) -> None:
            if is_async:
                settle(error)
            else:
                self._inbox.post_to(loop, settle, error)

        lane = self._dispatcher.lane_for(group, node)
        token = self._dispatcher.node_token(node) if node is not None else None
        meter = self._dispatcher.node_meter(node) if node is not None else None
        lane.submit(Work(call, capture, is_async, 1 << 16, done, token, meter=meter))
        return outcome

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        """Stop running callbacks, wait for running ones, release resources.

        Safe from any thread and from inside a callback; in the latter case
        the release happens when the spinning call returns.

        :return: ``False`` if callbacks were still running after
            ``timeout_sec`` (default: the constructor's ``shutdown_timeout``).
        """
        timeout = self._shutdown_timeout if timeout_sec is None else max(0.0, timeout_sec)
        with self._state_changed:
            first = self._state not in _CLOSED
            if first:
                self._move(ExecutorState.STOPPING if self._state is ExecutorState.SPINNING else ExecutorState.SHUT_DOWN)
        if first:
            self._signal_stopped()
        with self._state_changed:
            if self._state is ExecutorState.STOPPING and not self._inside_executor():
                self._state_changed.wait_for(lambda: self._state is not ExecutorState.STOPPING, timeout)
            if self._state is ExecutorState.STOPPING:
                return False  # released when the spinning call returns
        return self._release(timeout)

    def _move(self, state: ExecutorState) -> None:
        """Enter ``state``; the caller holds ``_state_changed``."""
        self._state = state
        self._state_changed.notify_all()

    def _refuse_if_closed(self, what: str) -> None:
        if self._state in _CLOSED:
            raise ExecutorError(f"cannot {what}: the executor is {self._state.value}")

    def _release(self, timeout: float) -> bool:
        with self._release_lock:
            if self._released is None:
                self._released = self._release_once(timeout)
            return self._released

    def _release_once(self, timeout: float) -> bool:
        if self._loop_watchdog is not None:
            self._loop_watchdog.stop()
        joined = self._dispatcher.close(timeout=timeout)
        if self._task_lane is not None:
            joined = self._task_lane.close(timeout=timeout) and joined
        joined = self._task_hooks.workers.close(timeout=timeout) and joined
        super().shutdown(timeout_sec=0)
        if not self._loop.is_running() and not self._loop.is_closed():
            self._drain_owned_loop(timeout)
            self._loop.close()
        self._inbox.clear()
        return joined

    def _inside_executor(self) -> bool:
        current = threading.current_thread()
        if current.ident == self._dispatcher.loop_thread:
            return True
        return current in self.threads()

    def threads(self) -> list[threading.Thread]:
        """Worker threads currently alive in this executor (plain callbacks and tasks)."""
        threads = self._dispatcher.workers.threads
        if self._task_lane is not None:
            threads.extend(self._task_hooks.workers.threads)
        return threads

    def tasks(self) -> set[asyncio.Task[object]]:
        """Asyncio tasks currently running callbacks."""
        tasks: set[asyncio.Task[object]] = set()
        for lane in self._dispatcher.lanes():
            tasks |= lane.tasks
        return tasks

    def adapt(
        self,
        coro: Coroutine[Any, Any, T],
        *,
        on_suspend: Callable[[], object] | None = None,
        owner: object = _CALLER,
    ) -> Coroutine[Any, Any, T]:
        """Make ``await rclpy_future`` inside ``coro`` sleep instead of spin.

        rclpy's futures ``yield`` bare ``None`` until done; to asyncio that
        means "run me again at once", a busy loop. The adapter parks such a
        coroutine until the executor next delivers a service response or
        schedules a done-callback (or a short poll interval passes).

        :param on_suspend: called once if ``coro``'s first step suspends.
        :param owner: whose task it is (``OWNER``'s value), for the accounting:
            each of its steps is metered as that node's (by default, the
            caller's; nothing for the executor's own).
        """
        account = self._account(OWNER.get() if owner is _CALLER else owner, "task")
        # Lateness: from now, the task's creation, to its first step.
        work = None if account is None else Work(account, _never, True, 1, _untold, meter=account.meter)
        return adapt(coro, self._progress_future, on_suspend=on_suspend, work=work)

    # -- running the owned loop ------------------------------------------------
    def _run_owned(self, main: Coroutine[Any, Any, None], *, permits: int | None = None) -> None:
        started = False
        try:
            self._refuse_if_closed("spin")
            if running_loop() is not None:
                raise ExecutorError("spin*() cannot run inside a running event loop; await spin_async()")
            with self._spinning_on(self._loop, permits=permits):
                self._selector.attach(
                    self._wait,
                    idle=functools.partial(loop_is_idle, self._loop),
                    ros_turn_due=self._ros_turn_due,
                    handoff=self._dispatcher.handoff,
                )
                started = True
                watchdog = self._start_watchdog()
                try:
                    with self._inbox.serving():
                        # The executor's own context: what it schedules itself is its own
                        # (a copy of the caller's, whose ContextVars main still sees).
                        context = contextvars.copy_context()
                        context.run(OWNER.set, EXECUTOR)
                        context.run(self._loop.run_until_complete, main)
                finally:
                    if watchdog is not None:
                        watchdog.pause()
                        self._watchdog = None
                    self._selector.attach(None)
        finally:
            if not started:
                main.close()  # refused: never awaited, and not to be warned about

    @contextlib.contextmanager
    def _spinning_on(
        self, loop: asyncio.AbstractEventLoop, *, permits: int | None = None
    ) -> Generator[None, None, None]:
        """Spin on ``loop``; at most ``permits`` callbacks start (``None``: any number)."""
        with self._state_changed:
            self._refuse_if_closed("spin")
            if self._state is ExecutorState.SPINNING:
                raise ExecutorError(
                    "the executor is already spinning (in another thread, or this is one of its"
                    " callbacks: there, await the future in an async def callback instead)"
                )
            self._move(ExecutorState.SPINNING)
            owned = self._dispatcher
            removed = list(self._removed_idle)
            self._removed_idle.clear()
            if loop is not self._loop:
                self._dispatcher = self._make_dispatcher(loop)
            self._dispatcher.bind_loop_thread(threading.get_ident())
            if self._accounting is not None:
                self._accounting.loop_started()
            self._running_loop = loop
            self._stopped = None
            if self._progress is not None and self._progress.get_loop() is not loop:
                # Coroutines parked on the owned loop's progress stay parked
                # there (and look again on the next spin of it, not before).
                self._progress = None
        if removed:  # removed while nobody spun, and not added back
            owned.invalidate()
            for node in removed:
                owned.retire(node, sweep=False)
        self._dispatcher.start()
        self._dispatcher.gate.limit(permits)
        try:
            yield
        finally:
            self._dispatcher.gate.limit(0)
            with self._state_changed:
                foreign: Dispatcher | None = None
                if self._dispatcher is not owned:
                    foreign, self._dispatcher = self._dispatcher, owned
                self._running_loop = None
                self._stopped = None
                if loop is not self._loop:
                    self._progress = None
            owned.pause()
            if foreign is not None:
                foreign.close(timeout=self._shutdown_timeout)
            self._dispatcher.bind_loop_thread(None)
            if self._closed:
                self._release(self._shutdown_timeout)
            with self._state_changed:
                self._move(ExecutorState.SHUT_DOWN if self._closed else ExecutorState.IDLE)

    def _start_watchdog(self) -> LoopWatchdog | None:
        if self._stall_after is None:
            return None
        watchdog = self._loop_watchdog
        if watchdog is None:
            dispatcher = self._dispatcher  # the owned loop's, for good
            watchdog = self._loop_watchdog = LoopWatchdog(
                busy_since=lambda: dispatcher.busy_since,
                loop_thread=lambda: dispatcher.loop_thread,
                relieve=dispatcher.relieve,
                rewake=self._guard_trigger,
                describe=self._describe_loop_work,
                stall_after=self._stall_after,
                reports=self._watchdog_reports,
            )
        watchdog.resume()
        self._watchdog = watchdog
        return watchdog

    def _make_task(
        self, loop: asyncio.AbstractEventLoop, coro: _TaskCoro[T], **kwargs: Any
    ) -> asyncio.Task[T]:
        """Every task on the owned loop (and on a loop ``spin_async`` lends
        this factory to) may await rclpy futures without spinning a core.

        An rclpy future yields a bare ``None`` until it is done: to a plain
        asyncio task, "run me again at once". A background task of a plugin
        (``asyncio.create_task``) awaiting a service call, or
        ``asyncio.wait_for(client.call_async(...), timeout)``, burned a whole
        core for as long as the call took. Coroutines, and asyncio's wrapper
        of other awaitables, run under :func:`adapt` instead, as callbacks do.
        """
        if is_adapted(coro) or not (isinstance(coro, types.CoroutineType) or wraps_an_awaitable(coro)):
            task = asyncio.Task(coro, loop=loop, **kwargs)
            self._origins.note(task, asyncio.current_task(loop))
            self._hold(task)
            return task
        # Each step of a node's task is metered as its (the context it runs in names it).
        context = kwargs.get("context")
        owner = OWNER.get() if context is None else context.get(OWNER)
        # Before 3.12 ``coro`` may be asyncio's wrapper generator, which adapt drives alike.
        task = asyncio.Task(self.adapt(coro, owner=owner), loop=loop, **kwargs)  # type: ignore[arg-type, unused-ignore]
        self._origins.note(task, asyncio.current_task(loop))
        # Cancelled before its first step, the wrapper never starts ``coro``,
        # which would then warn "coroutine ... was never awaited": closed
        # here (a no-op once it ran).
        task.add_done_callback(lambda _: coro.close())
        self._hold(task)
        return task

    def _hold(self, task: asyncio.Task[Any]) -> None:
        """Keep ``task`` until it is done, as rclpy's executors keep theirs.

        asyncio keeps only weak references to tasks, and a task waiting on a
        future that nothing but the task reaches is garbage (a client's
        ``asyncio.open_connection``: its protocol holds the stream reader,
        whose future the task awaits, weakly). A caller that let go of what
        ``create_task`` returned, or a plugin's ``asyncio.create_task`` not
        kept, then lost its task to the next collection, mid-await.
        """
        self._held_tasks.add(task)
        task.add_done_callback(self._held_tasks.discard)

    def _describe_loop_work(self) -> Culprit:
        """What the loop thread runs now: which node's which callback, and whether a plugin's."""
        task = asyncio.current_task(self._loop)
        if task is None and self._accounting is not None:
            account = self._accounting.running_on_loop()  # a handle a node scheduled (a reader, a call_later)
            if account is not None:
                return handle_culprit(account.owner.name, account.owner.plugin, account.name)
        return self._origins.culprit(task)

    def _runner_work(self, task: asyncio.Task[Any]) -> Work | None:
        """The work ``task`` carries if it is a lane's runner."""
        for lane in self._dispatcher.lanes():
            work = lane.work_of(task)
            if work is not None:
                return work
        return None

    def _make_dispatcher(self, loop: asyncio.AbstractEventLoop) -> Dispatcher:
        return Dispatcher(
            context=self.context,
            loop=loop,
            hooks=_DispatcherHooks(self, self._inbox.poster(loop)),
            reentrant_limit=self._reentrant_limit,
            future_executor=self,
            loop_waits=loop is self._loop,
            accounting=self._accounting,
        )

    def _own_guards(self) -> list[tuple[Any, int]]:
        return [(guard, WOKEN) for guard in executor_guards(self)]

    def _ros_turn_due(self) -> bool:
        if self._rcl_turn_owed:
            self._rcl_turn_owed = False
            return True
        # Hand-overs from other threads (the inbox) run after a wait.
        if self._inbox:
            return True
        # A spin_once past its timeout: its last look in rcl was the wait the
        # timeout ended (rclpy's), not a poll of a loop that came back to
        # select late (a timer due then would fire in a call timed out).
        once = self._once_deadline
        if once is not None and time.monotonic() >= once:
            return False
        return self._dispatcher.ros_turn_due()

    def _wait(self, timeout_ns: int) -> int:
        self._rcl_turn_owed = False  # any wait is the look in rcl a spin_once owes
        inbox = self._inbox
        inbox.draining(threading.get_ident())
        try:
            flags = self._dispatcher.wait_and_dispatch(timeout_ns)
            inbox.run()
        finally:
            inbox.draining(None)
            if inbox:
                self._guard_trigger()  # run() raised: what is left runs after the next wait
        # Shutdown of the context and SIGINT both trigger one of our guards.
        if flags & WOKEN and not self.context.ok():
            self._signal_stopped()
        return flags

    def _wait_in_thread(self) -> None:
        while not self._closed and self.context.ok() and not self._stop_requested():
            self._wait(-1)
        self._signal_stopped()

    async def _until_stopped(self) -> None:
        await self._stopped_future()

    async def _until_a_callback_completes(self, completed: asyncio.Future[None], deadline: float | None) -> None:
        # rclpy resumes every pending task on each spin: a coroutine parked on
        # a bare yield (an rclpy future) looks again now, not at the next poll.
        self._notify_progress()
        # What is ready already (a triggered guard condition, a timer due)
        # runs in this call, also with timeout_sec=0: the loop's first
        # select looks in rcl however busy asyncio is.
        self._rcl_turn_owed = True
        await self._bounded(completed, None if deadline is None else max(0.0, deadline - time.monotonic()))
        while not completed.done() and self._dispatcher.gate.permits == 0 and not self._stop_requested():
            # A callback started within the timeout (a plain one runs on its
            # group's thread): as in rclpy, where the timeout bounds the wait
            # for work and not the work, the call returns once it has run.
            # Looked at again now and then: work that turns out to have
            # nothing to run gives its permit back without completing.
            await self._bounded(completed, _RCL_FUTURE_POLL_S)

    async def _until_done(
        self,
        future: RclFuture[Any] | asyncio.Future[Any] | Coroutine[Any, Any, Any],
        timeout_sec: float | None,
    ) -> None:
        if isinstance(future, RclFuture):
            settled = mirror(future, self.loop)
            await self._bounded(settled, timeout_sec)
            if settled.done() and not settled.cancelled():
                settled.exception()  # the caller reads it from ``future``
            return
        if not inspect.iscoroutine(future):
            await self._bounded(asyncio.ensure_future(future), timeout_sec)
            return
        # A coroutine is ours to run, so its failure is the caller's to see.
        task = self.loop.create_task(self.adapt(future))
        await self._bounded(task, timeout_sec)
        if not task.done():
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        elif not task.cancelled() and task.exception() is not None:
            raise task.exception()  # type: ignore[misc]

    async def _bounded(self, target: asyncio.Future[Any], timeout_sec: float | None) -> None:
        stopped = self._stopped_future()
        waits: set[asyncio.Future[Any]] = {target, stopped}
        timeout = None if timeout_sec is None or timeout_sec < 0 else timeout_sec
        await asyncio.wait(waits, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)

    def _drain_owned_loop(self, timeout: float) -> None:
        """Let the owned loop's leftover tasks see their cancellation, and join its
        default thread pool, as ``asyncio.run`` ends (waiting up to ``timeout``)."""
        self._selector.attach(None)
        pending = [t for t in asyncio.all_tasks(self._loop) if not t.done()]
        for task in pending:
            task.cancel()
        if running_loop() is not None:
            # Released from inside another loop (spin_async on a foreign
            # loop): the owned loop cannot run here, and has nothing to finish.
            self._held_tasks.clear()
            return
        if pending:
            self._loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
        self._loop.run_until_complete(self._loop.shutdown_asyncgens())
        # Joined, not told to end at close(): its idle threads (a plugin's
        # to_thread) then ended some time after the process counted the
        # threads it left behind, and a container stopped cleanly exited 1.
        # A job still running past the timeout is left, and reported so.
        with contextlib.suppress(TimeoutError):
            self._loop.run_until_complete(asyncio.wait_for(self._loop.shutdown_default_executor(), timeout))
        self._held_tasks.clear()  # what cancelling left pending is let go with the loop

    # -- stop / progress signalling --------------------------------------------
    def _stopped_future(self) -> asyncio.Future[None]:
        if self._stopped is None:
            self._stopped = self.loop.create_future()
            if self._closed or not self.context.ok():
                self._stopped.set_result(None)
        return self._stopped

    def _stop_requested(self) -> bool:
        return self._stopped is not None and self._stopped.done()

    def _signal_stopped(self) -> None:
        stopped = self._stopped
        if stopped is None:
            self._guard_trigger()
            return

        def settle() -> None:
            if not stopped.done():
                stopped.set_result(None)

        call_soon(stopped.get_loop(), settle)
        self._guard_trigger()

    def _guard_trigger(self) -> None:
        # The base class's wake(): triggers its guard, if not yet destroyed.
        with contextlib.suppress(InvalidHandle):
            Executor.wake(self)

    def _progress_future(self) -> asyncio.Future[None]:
        progress = self._progress
        if progress is None or progress.done():
            loop = self.loop
            progress = loop.create_future()
            self._progress = progress
            # The executor's poll, though a node's task asks for it (its await of an rclpy future).
            loop.call_later(_RCL_FUTURE_POLL_S, _resolve, progress, context=executor_context())
        return progress

    def _notify_progress(self) -> None:
        progress = self._progress
        if progress is not None and not progress.done():
            call_soon(progress.get_loop(), _resolve, progress)

    def _callback_completed(self) -> None:
        if self._completion_waiters:
            for waiter in list(self._completion_waiters):
                call_soon(waiter.get_loop(), _resolve, waiter)

    def _report_error(self, node: Node, entity: object, error: BaseException) -> None:
        if isinstance(error, asyncio.CancelledError):
            return
        node.get_logger().error(format_error(entity, error))
        if self._on_callback_error is not None:
            self._on_callback_error(node, entity, error)

    def _tasks_lane(self) -> Lane:
        with self._state_changed:
            self._refuse_if_closed("create a task")
            if self._task_lane is None:
                self._task_lane = Lane(
                    name="executor:tasks",
                    limit=self._reentrant_limit,
                    loop=self.loop,
                    hooks=self._task_hooks,
                )
            return self._task_lane

    def deliver(
        self, node: Node, subscription: object, callback: Callable[..., Any], args: tuple[Any, ...]
    ) -> bool:
        """Run ``callback(*args)`` as if ``subscription`` of ``node`` had just taken a message.

        For intra-process delivery (:mod:`container.intra`): the call goes to
        the subscription's callback-group lane, and waits there bounded by its
        QoS depth with the messages taken from rcl. Callable from any thread.

        :return: ``False`` (nothing handed over) when ``node`` is not in this
            executor or the executor is shut down.
        """
        if self._closed:
            return False
        on_loop = self._dispatcher.deliver(subscription, node, callback, args)
        if on_loop is None:
            return False
        if not on_loop:
            # From another thread: wake the loop (a woken rcl wait costs ~5 us).
            self._guard_trigger()
        return True


class _DispatcherHooks:
    """The executor as a dispatcher sees it (:class:`ExecutorHooks`), posting through ``post``."""

    def __init__(self, executor: AsyncioExecutor, post: Post) -> None:
        self.done_waiters = executor._completion_waiters
        # Bound methods as attributes: the dispatcher calls several per callback.
        self.nodes = executor.get_nodes
        self.own_guards = executor._own_guards
        self.post = post
        # What the own loop's inbox holds, run by a burst too (see EntityWaitSet.burst);
        # another loop's posts go through that loop, and nothing is left here to run.
        self.posted: Sized = executor._inbox if post == executor._inbox.post else ()
        self.run_posted = executor._inbox.run
        self.report_error = executor._report_error
        self.callback_completed = executor._callback_completed
        self.response_arrived = executor._notify_progress
        self.progress = executor._progress_future
        self.wake = executor._guard_trigger


def _never(*_: object) -> None:
    """A task's ``Work`` is stepped by ``drive``, never called."""


def _untold(work: Work, error: BaseException | None) -> None:
    """A task's outcome is its own, told by asyncio."""


def _resolve(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)


def _same(members: tuple[object, ...] | None, now: tuple[object, ...]) -> bool:
    return members is not None and len(members) == len(now) and all(a is b for a, b in zip(members, now, strict=True))


#: Executors not yet shut down. Their waiter threads sit in ``rcl_wait``; one
#: still there when the interpreter tears rclpy's C++ objects down aborts the
#: process ("terminate called without an active exception"), so whatever a
#: program forgot to shut down is shut down at exit.
_live: weakref.WeakSet[AsyncioExecutor] = weakref.WeakSet()


@atexit.register
def _shutdown_forgotten_executors() -> None:
    for executor in list(_live):
        with contextlib.suppress(Exception):
            executor.shutdown(timeout_sec=1.0)
