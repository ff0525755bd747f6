"""The loop thread's chain of ``async def`` callbacks, and their first step (``fastpath/express.c``).

A message one node of this process publishes to another is reported by
the notifier, and the loop thread takes it and runs its ``async def``
callback's first step without waiting (most callbacks finish in it).
:meth:`Express.drain` does that for a whole chain: take what the notifier
reported, admit each message into its callback group's lane, run the first
step in an idle runner task of that lane (asyncio's current task and the
runner's context, as the Python lanes do) and release the lane. Timers go
the same way after a wait: :meth:`Express.call_timers` calls the ready
timers that have a route where the wait set's dispatch takes them, under
its locks, and :meth:`Express.run_fired` runs their callbacks once those
locks are released.

Only the common case is handled here; everything else is handed to the
Python path the executor uses anyway: a lane that is busy, locked by
another thread or without an idle runner (``slow``), a callback that
suspends or fails (``suspended``, ``failed``), a lane with pending work
after the step (``release_pending``), and entities that are not express
routes (``take_rest``). A lane's state is read and written only under its
lock, taken without waiting (``lanes.admit_first_step``: held by another
thread, the lane counts as locked, as the compiled chain reads it).

:func:`first_step` is the step both paths run: ``call(*args)`` up to its
first suspension, inside the runner's task (asyncio's current task while
it runs, as an eager task's is) and in a copy of the runner's context (as
each asyncio task gets a copy of the context it was created in: what one
callback sets in a ``ContextVar`` is not the next one's).

Differences: none in what happens, only in what it costs (this is the
Python the chain was compiled to save); and since this engine's notifier
never reports (see ``notifier``), :meth:`Express.drain` finds nothing to
take: subscriptions are waited on and go the Python way, timers still come
through :meth:`Express.call_timers`.
"""

from __future__ import annotations

import contextvars
import time
import types
from collections.abc import Callable, Iterable, Mapping, Sized
from typing import Any

from ..._compat import RCLError
from .lanes import (
    Route,
    Routes,
    Runner,
    Work,
    admit_first_step,
    release_first_step,
    set_started,
    undo_first_step,
)
from .lock import Lock
from .meter import Meter, begin, end, pause
from .notifier import Notifier
from .taker import Taker

__all__ = ["Express", "first_step"]

_monotonic_ns = time.monotonic_ns


class _Broken(Exception):
    """The path itself failed around a step (entering or leaving the task): ``error`` is why."""

    def __init__(self, error: BaseException) -> None:
        super().__init__(error)
        self.error = error


def _send_first(coro: Any) -> Any:
    """The first step of what the callback returned: ``PyIter_Send(coro, None)``.

    A coroutine or generator is sent ``None``; any other iterator is advanced
    with ``next``; anything else is asked for its ``send`` (an
    ``AttributeError`` for what is no coroutine at all, as in C).
    """
    if not isinstance(coro, types.CoroutineType | types.GeneratorType) and hasattr(type(coro), "__next__"):
        return next(coro)
    return coro.send(None)


class _Outcome:
    """How a first step ended: done, suspended (``coro``, ``yielded``), or failed (``error``)."""

    __slots__ = ("coro", "error", "started", "suspended", "yielded")

    def __init__(self) -> None:
        self.coro: Any = None
        self.yielded: Any = None
        self.error: BaseException | None = None
        self.suspended = False
        self.started = 0


def _step(
    loop: object,
    enter_task: Callable[..., object],
    leave_task: Callable[..., object],
    task: Any,
    call: Callable[..., Any],
    args: tuple[Any, ...],
    meter: Meter | None,
    arrived: int,
) -> _Outcome:
    """Inside the callback's context: enter the task, take the step, leave the task."""
    try:
        enter_task(loop, task)
    except BaseException as error:
        raise _Broken(error) from error
    outcome = _Outcome()
    if meter is not None:
        outcome.started = begin(meter, arrived)
    try:
        outcome.coro = call(*args)
        outcome.yielded = _send_first(outcome.coro)
        outcome.suspended = True
    except StopIteration:
        pass  # done: what it returned is nobody's
    except BaseException as error:
        outcome.error = error
    if meter is not None:
        if outcome.suspended:
            pause(meter, outcome.started)
        else:
            end(meter, outcome.started, outcome.started)
    try:
        leave_task(loop, task)
    except BaseException as error:  # leaving the task failed: nothing sane is left to do
        raise _Broken(error) from error
    return outcome


def _first_step(
    loop: object,
    enter_task: Callable[..., object],
    leave_task: Callable[..., object],
    runner: Runner,
    current: Work,
    call: Callable[..., Any],
    args: tuple[Any, ...],
    meter: Meter | None,
    arrived: int,
) -> tuple[_Outcome, contextvars.Context]:
    """The first step of ``call(*args)`` in ``runner``'s task and a copy of its context,
    with ``current`` as what the runner carries meanwhile (for the watchdog).

    Raises :class:`_Broken` when this path itself failed, before or after the step.
    """
    task = runner.task
    context = runner.context.copy()
    runner.current = current
    try:
        outcome = context.run(_step, loop, enter_task, leave_task, task, call, args, meter, arrived)
    finally:
        runner.current = None
    if not outcome.suspended:
        outcome.coro = outcome.yielded = None
    return outcome, context


def _step_error(error: BaseException, cancelled_error: type[BaseException]) -> BaseException | None:
    """A failed first step's error: ``None`` for a callback's own cancellation (it ends that
    callback only); ``KeyboardInterrupt`` is raised (that one stops the executor)."""
    if isinstance(error, KeyboardInterrupt):
        raise error
    if isinstance(error, cancelled_error):
        return None
    return error


def first_step(
    loop: object,
    enter_task: Callable[..., object],
    leave_task: Callable[..., object],
    cancelled_error: type[BaseException],
    runner: Runner,
    work: Work,
    /,
) -> BaseException | tuple[Any, Any, contextvars.Context] | None:
    """Async ``work`` up to its first suspension, in ``runner``'s task and a copy of its
    context (the same step the chain runs): ``None`` done (or cancelled itself), the
    error it failed with, or ``(coro, yielded, context)`` suspended. Raises
    ``KeyboardInterrupt``, and what breaks the path."""
    if not isinstance(runner, Runner) or not isinstance(work, Work):
        raise TypeError("first_step(loop, enter_task, leave_task, cancelled_error, runner, work)")
    set_started(work, 0)
    try:
        outcome, context = _first_step(
            loop, enter_task, leave_task, runner, work, work.call, work.args, work.meter, work.arrived
        )
    except _Broken as broken:
        raise broken.error from None
    set_started(work, outcome.started)
    if outcome.suspended:
        return outcome.coro, outcome.yielded, context
    if outcome.error is not None:
        return _step_error(outcome.error, cancelled_error)
    return None


class Express:
    """The loop thread's chain of async subscription callbacks: take, admit, first step, release."""

    __slots__ = (
        "_cancelled_error", "_done_waiters", "_eager", "_enter_task", "_expressed", "_failed", "_fired",
        "_leave_task", "_loop", "_notifier", "_on_done", "_ready_queue", "_release_pending", "_routes",
        "_run_eager", "_slow", "_suspended", "_take_lock", "_take_rest",
    )  # fmt: skip

    def __init__(
        self,
        *,
        notifier: Notifier,
        routes: Routes,
        take_lock: Lock,
        loop: object,
        ready_queue: Sized,
        eager: Sized,
        run_eager: Callable[[], object],
        enter_task: Callable[..., object],
        leave_task: Callable[..., object],
        on_done: Callable[[], object],
        done_waiters: Sized,
        slow: Callable[..., object],
        suspended: Callable[..., object],
        failed: Callable[..., object],
        release_pending: Callable[[Any, Work], object],
        take_rest: Callable[[list[tuple[int, int]]], object],
        cancelled_error: type[BaseException],
    ) -> None:
        for name, value, kind in (("notifier", notifier, Notifier), ("routes", routes, Routes)):
            if not isinstance(value, kind):
                raise TypeError(f"Express() argument '{name}' must be {kind.__name__}, not {type(value).__name__}")
        if not isinstance(take_lock, Lock):
            raise TypeError("Express needs the wait set's take lock to be this engine's Lock")
        self._notifier = notifier
        #: The wait set's routes and flags.
        self._routes = routes
        self._take_lock = take_lock
        self._loop = loop
        #: asyncio's ready queue: non-empty means asyncio has work.
        self._ready_queue = ready_queue
        #: The dispatcher's eager queue, run by ``run_eager``.
        self._eager = eager
        self._run_eager = run_eager
        self._enter_task = enter_task
        self._leave_task = leave_task
        #: Called only while ``done_waiters`` is non-empty.
        self._on_done = on_done
        self._done_waiters = done_waiters
        #: ``slow(entry, message)``
        self._slow = slow
        #: ``suspended(entry, message, runner, coro, yielded, context, started)``
        self._suspended = suspended
        #: ``failed(entry, message, error or None)``
        self._failed = failed
        #: ``release_pending(lane, marker)``: the slot goes to waiting work.
        self._release_pending = release_pending
        #: ``take_rest([(address, count)])``: what has no route.
        self._take_rest = take_rest
        #: A callback's own cancellation is no error.
        self._cancelled_error = cancelled_error
        #: Timer routes called by :meth:`call_timers`, whose callbacks :meth:`run_fired` runs.
        self._fired: list[Route] = []
        #: Callbacks run here (tests, diagnostics).
        self._expressed = 0

    @property
    def expressed(self) -> int:
        """How many callbacks ran on this path."""
        return self._expressed

    def _release(self, route: Route) -> None:
        """The first step's slot is given back (or, through the lane, passed to the work waiting for it)."""
        if release_first_step(route.slots):
            self._release_pending(route.lane, route.marker)

    def _run_one(self, route: Route, message: object | None) -> None:
        """Run one taken message's callback (``message`` ``None``: a called timer's,
        without arguments). Raises only what must stop the executor
        (``KeyboardInterrupt``, or a failure of this path)."""
        entry = route.entry
        if route.token.retired:
            return  # its entity or node left: dropped, as rclpy drops it
        runner = admit_first_step(route.slots)
        if runner is None:
            self._slow(entry, message)
            return
        marker = route.marker
        try:
            callback = getattr(route.entity, route.callback)
            outcome, context = _first_step(
                self._loop, self._enter_task, self._leave_task, runner, marker, callback,
                () if message is None else (message,), marker.meter, route.arrived,
            )  # fmt: skip
        except _Broken as broken:
            undo_first_step(route.slots)
            raise broken.error from None
        except BaseException:
            undo_first_step(route.slots)
            raise
        self._expressed += 1
        if outcome.suspended:
            self._suspended(entry, message, runner, outcome.coro, outcome.yielded, context, outcome.started)
            return
        if outcome.error is None:
            if len(self._done_waiters) != 0:
                self._on_done()
            self._release(route)
            return
        self._failed(entry, message, _step_error(outcome.error, self._cancelled_error))

    def _take_batch(self, batch: list[tuple[Route, object]]) -> tuple[bool, BaseException | None]:
        """Take what the notifier reported into ``batch`` under the take lock: whether
        anything may be done (``False``: the lock is busy, or the routes are stale or
        closed), and the error a take failed with (the batch taken before it runs first)."""
        now = _monotonic_ns()
        if not self._take_lock.acquire(blocking=False):
            # A worker is carrying: whoever holds it takes what is plain; the
            # caller's next round (the Python path) takes the rest.
            return False, None
        try:
            routes = self._routes
            if routes.closed or routes.dirty:
                return False, None
            by_address = routes.subscriptions
            rest: list[tuple[int, int]] = []
            failure: BaseException | None = None
            for key, count in self._notifier.ready():
                route = by_address.get(key)
                if route is None:
                    rest.append((key, count))
                    continue
                if not isinstance(route, Route) or not isinstance(route.first, Taker):
                    raise TypeError("a subscription's route is a Route whose first is a Taker")
                for _ in range(count):
                    route.arrived = now
                    try:
                        message = route.first.take()
                    except Exception as error:
                        # The rest of what was reported is taken all the same (its counts
                        # were taken from the notifier): run it, then report the first error.
                        failure = failure or error
                        break
                    if message is None:
                        break
                    batch.append((route, message))
            if rest:
                self._take_rest(rest)
        finally:
            self._take_lock.release()
        return True, failure

    def drain(self, deadline_ns: int, /) -> bool:
        """Take and run what the notifier reports until nothing is, the deadline (the next
        poll of timers) passes, or asyncio has work of its own. ``False``: the take lock
        was busy (take the Python way)."""
        notifier = self._notifier
        batch: list[tuple[Route, object]] = []
        while notifier.pending() and _monotonic_ns() < deadline_ns and len(self._ready_queue) == 0:
            taking, failure = self._take_batch(batch)
            if not taking:
                return False
            for route, message in batch:
                self._run_one(route, message)
            batch.clear()
            if failure is not None:
                raise failure
            if len(self._eager) > 0:
                self._run_eager()
        return True

    def call_timers(self, routes: Mapping[int, Route], ready: Iterable[int], /) -> list[int]:
        """Call (as ``rcl_timer_call``) each ready timer that has a route, keeping the route
        for :meth:`run_fired`: the addresses left to the Python path (no route, or anything
        unusual about the timer: not ready after all, cancelled, an rcl error, which
        rclpy's own calls there handle and report). Called under the wait set's take lock."""
        if not isinstance(routes, dict):
            raise TypeError("call_timers(routes: dict, ready: iterable)")
        rest: list[int] = []
        for key in list(ready):
            route = routes.get(key)
            if route is None:
                rest.append(key)
                continue
            if not isinstance(route, Route):
                raise TypeError("a timer's route is a Route")
            if route.timer is None:
                raise TypeError("a timer's route holds its handle")
            timer = route.timer.handle
            # Its due time, for its lateness: it was due `until` ago (until <= 0).
            try:
                until = timer.time_until_next_call()
            except RCLError:
                until = None
            route.arrived = _monotonic_ns() + min(until or 0, 0)
            try:
                called = bool(timer.is_timer_ready())
                if called:
                    timer.call_timer()
            except RCLError:
                called = False
            if not called:
                rest.append(key)
                continue
            self._fired.append(route)
        return rest

    def run_fired(self) -> None:
        """Run the callbacks of the timers :meth:`call_timers` called, as :meth:`drain` runs
        a message's. Outside the wait set's locks (user code runs). What an error stops
        before is kept for the next call."""
        fired = self._fired
        if not fired:
            return
        self._fired = []  # callbacks may fire more (through a nested spin): kept apart
        for index, route in enumerate(fired):
            try:
                self._run_one(route, None)
            except BaseException:
                # The rest goes back in front of whatever was fired meanwhile.
                self._fired[:0] = fired[index + 1 :]
                raise
