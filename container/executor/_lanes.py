"""Callback-group lanes: where a callback group's callbacks actually run.

A lane enforces one callback group's concurrency limit (1 for a mutually
exclusive group, a bound for a reentrant one) over both kinds of callback:
``async def`` callbacks run on the event loop, plain ones on worker threads
(the lane's own, or one carrying on, below), so a plain callback that blocks
delays only its own group.

Async callbacks run inside a few long-lived *runner* tasks per lane rather
than one new task each: creating an asyncio task costs about 7 us on Python
3.11 (a weak-set registration, a context copy), more than the rest of a
callback's dispatch. Inside a runner, ``asyncio.current_task()`` is the
runner, so ``asyncio.timeout()`` and cancellation work as in any task.

Work dispatched on the loop thread starts *eagerly*, as Python 3.12's eager
tasks do: its first step runs right after the wait that found it, with an
idle runner entered as the current task and in that runner's context. Most
callbacks finish in that step (take, compute, publish) and never touch the
task machinery; one that suspends is handed to that same runner to finish.
Python 3.11 has no eager tasks, so this uses asyncio's own
``_enter_task``/``_leave_task`` (through ``_compat``), which its tasks call
around every step.

A worker thread that finished a plain callback *carries* on: what that
callback published to another plain callback of this process is taken on
the same thread, and if that callback's lane is free it runs there too,
rather than the event loop waking to wake another worker (two thread
switches per hand-over, each costing more than the callback); the loop is
not even woken for such a message while it wakes soon anyway (see
``_fastpath``'s ``mark_carrier``). Meanwhile the worker is busy to the
pool, so other work goes to another worker (a new thread, should every
worker be blocked): a carried callback that blocks delays nobody else for
more than the pool's :data:`~._workers.STUCK_S`.

The threads are not the lane's: every lane of a dispatcher hands its plain
work to one pool (``_workers``), which starts a thread past its size only
while every worker is blocked, so a callback that blocks for good never
holds up another group's work for long, and a hundred nodes share a few
threads.

Work waiting for a busy lane is kept per entity with a bound, like a DDS
keep-last history: a subscription keeps its QoS depth of messages, a timer
or a guard condition at most one pending firing. Without that bound a
callback that blocks for seconds would let the queue grow without limit.
"""

from __future__ import annotations

import asyncio
import collections
import contextvars
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .._compat import enter_task, leave_task
from ._bridge import drive
from ._engine import Lock, Runner, Slots, Work, first_step
from ._hooks import LaneHooks
from ._owners import OWNER, Owner

__all__: list[str] = []

class _Carrier(threading.local):
    """Per thread: where plain work submitted while a worker carries goes (one item at most)."""

    slot: list[tuple[Lane, Work]] | None = None


_carrier = _Carrier()

#: The lane whose callback runs now, set once in each lane's context (which
#: every callback's is a copy of): how :meth:`Lane.close` knows it is called
#: from one of its own plain callbacks, at no cost per callback.
_LANE: contextvars.ContextVar[Lane | None] = contextvars.ContextVar("container_lane", default=None)


class Retired(Exception):
    """Told to a work's ``done`` when it was dropped because its token retired."""


def _retired(work: Work) -> bool:
    token = work.token
    return token is not None and token.retired


def _work_of(item: Work | _Resume) -> Work:
    return item if isinstance(item, Work) else item.work


@dataclass(eq=False, slots=True)
class _Resume:
    """Async work whose first step ran eagerly and suspended on ``yielded``,
    in ``context`` (the callback's own copy of its runner's)."""

    work: Work
    coro: Any
    yielded: Any
    context: contextvars.Context


class Lane:
    """Run one callback group's work within its concurrency limit.

    Threads and runner tasks start only when first needed and end in
    :meth:`close`; a lane with only async callbacks owns no thread.
    """

    def __init__(
        self,
        *,
        name: str,
        limit: int,
        loop: asyncio.AbstractEventLoop,
        hooks: LaneHooks,
        owner: Owner | None = None,
    ) -> None:
        self.name = name
        self._hooks = hooks
        # Bound once: called per callback.
        self._defer = hooks.defer
        #: Told when an async callback's first step suspends: rclpy's
        #: ``spin_once`` counts a coroutine callback as run at that point.
        self._on_suspend = hooks.suspended
        #: What every callback's context is a copy of: the context the lane
        #: was made in (the spinning thread's), as asyncio tasks copy the
        #: context they are created in. What one callback sets in a
        #: ContextVar is not the next one's.
        self._context = contextvars.copy_context()
        if owner is not None:
            # Everything its callbacks start (tasks, loop callbacks, readers,
            # threads) carries the node along: see ``_owners``.
            self._context.run(OWNER.set, owner)
        self._context.run(_LANE.set, self)
        self._carries = hooks.carries
        self._post = hooks.post
        self._progress = hooks.progress
        self._loop = loop
        self._on_loop_thread = hooks.on_loop_thread
        #: The threads its plain work runs on (shared with the dispatcher's other lanes).
        self._workers = hooks.workers
        #: The admission state (running, limit, waiting work, idle runners),
        #: which the compiled path reads too; its lock guards the rest here.
        self._slots = Slots(limit)
        self._lock: Lock = self._slots.lock
        #: Plain side: one item per run of its plain work on a pool thread now
        #: (:meth:`_run_plain`), a deque for its atomic append and pop (no lock);
        #: once :meth:`close` waits for them, for how few and on what. Counted,
        #: not kept by thread: a dict of threads under a Condition around every
        #: callback cost plain ping-pong 15% (``bench_executor.py``, side by side).
        self._plain_runs: collections.deque[None] = collections.deque()
        self._drained_at = 0
        self._drained: threading.Event | None = None
        # Async side, touched on the loop thread only (the idle runners are parked in the slots).
        self._runners: dict[asyncio.Task[None], Runner] = {}

    @property
    def limit(self) -> int:
        """How many of the group's callbacks may run at once."""
        return self._slots.limit

    @limit.setter
    def limit(self, limit: int) -> None:
        self._slots.limit = limit

    @property
    def dropped(self) -> int:
        """Waiting invocations dropped for newer ones of their entity (keep-last)."""
        return self._slots.dropped

    @property
    def _closed(self) -> bool:
        return self._slots.closed

    @property
    def closed(self) -> bool:
        """Whether the lane was closed (its group left the executor): it starts nothing more."""
        return self._slots.closed

    # -- submission -------------------------------------------------------
    def submit(self, work: Work) -> None:
        """Start ``work`` now if the group allows it, else keep it pending."""
        if self._admit(work):
            self._start(work)

    def _admit(self, work: Work) -> bool:
        """Whether ``work`` may start now (its slot taken); if not, it is kept
        pending, or dropped once the lane is closed."""
        with self._lock:
            return self._slots.admit(work)

    def busy(self) -> bool:
        with self._lock:
            return self._slots.busy()

    def _next_pending(self, finished: Work) -> Work | None:
        """``finished`` is done: take the next pending work, or release the running slot."""
        with self._lock:
            return self._slots.next(finished)

    # -- retiring ---------------------------------------------------------------
    def retire(self, node: object) -> None:
        """Drop ``node``'s pending work and cancel its running ``async def`` work.

        Its plain callbacks already running go on (a thread cannot be
        stopped); :meth:`running` tells when they are done. Must be called
        on the loop thread, or while the loop is not running.
        """
        with self._lock:
            dropped = self._slots.retire(node)
        for work in dropped:
            work.done(work, Retired())
        for runner in list(self._runners.values()):
            current = runner.current
            if current is not None and current.token is not None and current.token.node is node:
                runner.task.cancel()

    def work_of(self, task: object) -> Work | None:
        """The work a runner task of this lane carries now, if ``task`` is one."""
        runner = self._runners.get(task)  # type: ignore[call-overload]
        return runner.current if runner is not None else None

    def running(self, node: object) -> list[Work]:
        """``node``'s work started and not yet done."""
        with self._lock:
            return self._slots.of(node)

    def _start(self, work: Work) -> None:
        if not work.is_async:
            slot = _carrier.slot
            if slot is not None and not slot:
                slot.append((self, work))  # a worker carrying on runs it next
            else:
                self._hand_to_thread(work)
        elif self._on_loop_thread():
            if not self._defer(self, work):
                self._hand_to_runner(work)
        else:
            self._post(self._hand_to_runner, work)

    # -- plain callbacks: worker threads ---------------------------------------
    def _hand_to_thread(self, work: Work) -> None:
        self._workers.hand(self, work, from_loop=self._on_loop_thread())

    def run_handed(self, work: Work) -> None:
        """Run plain ``work`` the pool handed this thread, then what its publishes made ready."""
        self._run_plain(work)
        if self._carries:
            self._carry_on(self._hooks.carry)

    def _run_plain(self, work: Work | None) -> None:
        """Run plain ``work`` (its slot taken) and the lane's pending work after it, on this thread."""
        runs = self._plain_runs
        runs.append(None)
        try:
            self._run_pending(work)
        finally:
            runs.pop()
            # Read after the pop, as close sets it before it counts: one of the two sees the other.
            drained = self._drained
            if drained is not None and len(runs) <= self._drained_at:
                drained.set()

    def _run_pending(self, work: Work | None) -> None:
        while work is not None:
            error: BaseException | None = None
            if _retired(work):
                error = Retired()
            else:
                try:
                    work.run(self._context.copy())
                except BaseException as exc:  # reported, never fatal: sys.exit() included
                    error = exc
            work.done(work, error)
            nxt = self._next_pending(work)
            if nxt is not None and nxt.is_async:
                self._start(nxt)
                nxt = None
            work = nxt

    def _carry_on(self, carry: Callable[[], None]) -> None:
        """Run, on this worker thread, plain work its callbacks' publishes made ready."""
        while True:
            slot: list[tuple[Lane, Work]] = []
            _carrier.slot = slot
            try:
                carry()
            except BaseException:
                for lane, work in slot:
                    lane._hand_to_thread(work)  # its slot is taken: it must still run
                raise
            finally:
                _carrier.slot = None
            if not slot:
                return
            lane, work = slot[0]
            lane._run_plain(work)

    # -- async callbacks: runner tasks -----------------------------------------
    def _hand_to_runner(self, item: Work | _Resume) -> None:
        if self._closed:
            return
        slots = self._slots
        while (runner := slots.idle_runner()) is not None:
            slots.unpark(runner)
            if self._wake(runner, item):
                return
        context = self._context.copy()
        # The Task itself, not the loop's task factory: a runner drives its
        # callbacks' awaits (see _run), and the executor's factory would
        # drive the runner's own in turn, hiding an asyncio.sleep(0) from it.
        task = asyncio.Task(self._run(item), loop=self._loop, name=f"lane:{self.name}", context=context)
        self._runners[task] = Runner(task, context, current=_work_of(item))
        task.add_done_callback(self._forget_runner)

    def _forget_runner(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and isinstance(task.exception(), KeyboardInterrupt):
            pass  # raised out of the spin already (see _run): seen, not to be logged again
        runner = self._runners.pop(task, None)
        if runner is not None:
            self._slots.unpark(runner)

    @staticmethod
    def _wake(runner: Runner, item: Work | _Resume) -> bool:
        """Hand ``item`` to an idle runner; ``False`` if it was cancelled meanwhile."""
        idle, runner.idle = runner.idle, None
        if idle is None or idle.done():
            return False
        runner.current = _work_of(item)
        idle.set_result(item)
        return True

    def run_express(self, work: Work) -> None:
        """:meth:`submit` and :meth:`run_eager` in one: async ``work`` taken on
        the loop thread starts now if the group allows it, else waits."""
        if self._admit(work):
            self.run_eager(work)

    @property
    def slots(self) -> Slots:
        """The admission state, which the C path (``Express``) reads and
        changes too, only while nobody holds its lock."""
        return self._slots

    def express_release(self, finished: Work) -> None:
        """The C path's first step of ``finished`` ended: its slot goes to
        pending work (started as :meth:`run_eager` would) or is given back."""
        nxt = self._next_pending(finished)
        if nxt is None:
            return
        if nxt.is_async:
            self.run_eager(nxt)
        else:
            self._hand_to_thread(nxt)

    def express_suspended(
        self, runner: Runner, work: Work, coro: Any, yielded: Any, context: contextvars.Context
    ) -> None:
        """The C path's first step of ``work`` suspended in ``runner``: that runner finishes it."""
        with self._lock:
            self._slots.activate(work)
        self._finish_in(runner, _Resume(work, coro, yielded, context))

    def _finish_in(self, runner: Runner, resume: _Resume) -> None:
        """A first step suspended in idle ``runner``: that runner (no longer
        idle) finishes it, or a new one if it was cancelled meanwhile."""
        self._slots.unpark(runner)
        if not self._wake(runner, resume):
            self._hand_to_runner(resume)

    def express_finished(self, work: Work, error: BaseException | None) -> None:
        """The C path's first step of ``work`` failed with ``error`` (``None``: cancelled)."""
        work.done(work, error)
        self.express_release(work)

    def run_eager(self, work: Work) -> None:
        """Run async ``work``, whose slot is taken, up to its first suspension.

        Called on the loop thread outside any task. Pending work of the lane
        follows eagerly too, until one suspends or a plain one needs a thread.
        """
        item: Work | None = work
        slots = self._slots
        while item is not None:
            if self._closed:
                return
            # Left parked: one whose step is done is idle again at once.
            runner = slots.idle_runner()
            if runner is None:
                self._hand_to_runner(item)
                return
            error: BaseException | None
            if _retired(item):
                error = Retired()
            else:
                # The same first step as the compiled chain's (fastpath/express.c):
                # in the runner's task, in a copy of its context.
                try:
                    outcome = first_step(self._loop, enter_task, leave_task, asyncio.CancelledError, runner, item)
                except BaseException:
                    # Ctrl-C in the callback (it stops the spin, as in rclpy) or this
                    # path broken: the slot goes on, or back, so the group runs again.
                    self._hand_on(item)
                    raise
                if isinstance(outcome, tuple):
                    coro, yielded, context = outcome
                    self._finish_in(runner, _Resume(item, coro, yielded, context))
                    self._on_suspend()
                    return
                error = outcome
            item.done(item, error)
            item = self._next_pending(item)
            if item is not None and not item.is_async:
                self._hand_to_thread(item)
                return

    def _hand_on(self, finished: Work) -> None:
        """``finished`` ends without its outcome told: its slot goes to the next
        waiting work, started in a runner task or on a thread (nothing runs here)."""
        nxt = self._next_pending(finished)
        if nxt is None:
            return
        if nxt.is_async:
            self._hand_to_runner(nxt)
        else:
            self._hand_to_thread(nxt)

    async def _run(self, item: Work | _Resume | None) -> None:
        """Run async work, one callback after another, inside one task.

        Each callback's coroutine is driven by :func:`drive` rather than
        awaited: rclpy's futures ``yield`` a bare ``None`` until done, which
        to asyncio means "run me again at once", a busy loop. Such a yield
        parks the callback on the executor's progress future instead (see
        ``AsyncioExecutor``).
        """
        thrown: BaseException | None = None
        while item is not None:
            work = item if isinstance(item, Work) else item.work
            error: BaseException | None = None
            try:
                if _retired(work) and isinstance(item, Work):
                    error = Retired()
                elif isinstance(item, Work):
                    context = contextvars.copy_context()  # of the runner's, as a task's
                    coro = context.run(work.call, *work.args)
                    await drive(coro, self._progress, on_suspend=self._on_suspend, context=context, work=work)
                else:
                    await drive(
                        item.coro,
                        self._progress,
                        yielded=item.yielded,
                        thrown=thrown,
                        started=True,
                        context=item.context,
                        work=work,
                    )
            except asyncio.CancelledError:
                if self._closed:
                    raise
                # A callback's own cancellation ends that callback only.
                task = asyncio.current_task()
                if task is not None:
                    task.uncancel()
            except KeyboardInterrupt:
                # Ctrl-C in the callback stops the spin, as in rclpy; the group runs on after it.
                self._hand_on(work)
                raise
            except GeneratorExit:
                raise
            except BaseException as exc:  # reported, never fatal: sys.exit() included
                error = exc
            thrown = None
            work.done(work, error)
            nxt = self._next_pending(work)
            if nxt is not None and not nxt.is_async:
                self._hand_to_thread(nxt)
                nxt = None
            item = nxt
            task = asyncio.current_task()
            runner = self._runners.get(task) if task is not None else None
            if runner is not None:
                runner.current = item
            if item is None and not self._closed:
                if runner is None:
                    return
                idle: asyncio.Future[Work | _Resume | None] = self._loop.create_future()
                runner.idle = idle
                self._slots.park(runner)
                try:
                    item = await idle
                except asyncio.CancelledError as exc:
                    # Cancelled (an expired asyncio.timeout) just after being
                    # handed a suspended callback: the callback gets it.
                    if self._closed or not idle.done() or idle.cancelled():
                        raise
                    item, thrown = idle.result(), exc
                    if not isinstance(item, _Resume):
                        raise

    # -- closing --------------------------------------------------------------
    def close(self, *, timeout: float) -> bool:
        """Drop pending work, cancel runners, and wait for its plain callbacks running.

        :return: ``False`` if one was still running when ``timeout`` ran out
            (on a daemon thread, which cannot be killed).
        """
        with self._lock:
            self._slots.close()
        for runner in list(self._runners):
            if self._on_loop_thread() or not self._loop.is_running():
                runner.cancel()
            else:
                self._post(runner.cancel)
        # Closed from one of its own plain callbacks: that one is not waited for.
        own = 1 if _LANE.get() is self and not self._on_loop_thread() else 0
        self._drained_at = own
        drained = self._drained
        if drained is None:
            drained = self._drained = threading.Event()
        if len(self._plain_runs) <= own:
            return True
        return drained.wait(max(0.0, timeout))

    @property
    def tasks(self) -> set[asyncio.Task[None]]:
        return set(self._runners)
