"""What the executor's tasks are made of: their futures, how they settle, the plain tasks' lane.

:meth:`AsyncioExecutor.create_task` runs a coroutine as an asyncio task on
the loop and a plain callable on the loop's thread (or, for rclpy's
``await_or_execute`` hand-overs, on a lane of worker threads of its own);
what it returns is an rclpy future that cancels the task when cancelled,
as rclpy's ``Task`` does.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import logging
import weakref
from collections.abc import Callable, Generator
from typing import TYPE_CHECKING, Any

from rclpy.executors import Executor
from rclpy.task import Future as RclFuture

from .._errors import ExecutorError
from ._engine import Work
from ._inbox import Post
from ._owners import OWNER, Owner
from ._workers import WorkerPool

if TYPE_CHECKING:
    from ._gate import Gate
    from ._lanes import Lane

__all__: list[str] = []

_log = logging.getLogger(__name__)


if TYPE_CHECKING:
    _AnyRclFuture = RclFuture[Any]
else:  # rclpy 7 (Jazzy): Future is not subscriptable
    _AnyRclFuture = RclFuture


class TaskFuture(_AnyRclFuture):
    """What :meth:`AsyncioExecutor.create_task` returns: cancelling it stops the task.

    As with rclpy's ``Task``: a task cancelled before it starts never runs,
    one suspended at an ``await`` is cancelled there (asyncio's
    ``CancelledError`` where rclpy closes the coroutine), and whatever it
    returns after that leaves it cancelled. A plain callable already running
    runs to its end, as in rclpy.
    """

    def __init__(self, *, executor: Executor) -> None:
        super().__init__(executor=executor)  # type: ignore[no-untyped-call, unused-ignore]  # rclpy 7's is untyped
        self._on_cancel: Callable[[], None] | None = None

    def cancel(self) -> None:
        super().cancel()  # type: ignore[no-untyped-call, unused-ignore]  # rclpy 7's is untyped
        on_cancel = self._on_cancel
        if on_cancel is not None and self.cancelled():
            on_cancel()

    def stop_with(self, on_cancel: Callable[[], None]) -> None:
        """Have ``on_cancel`` called once this is cancelled (now, if it is)."""
        self._on_cancel = on_cancel
        if self.cancelled():
            on_cancel()


def settle(result: RclFuture[Any], task: asyncio.Task[Any]) -> None:
    if result.cancelled():
        return  # cancelled by its owner; what the coroutine did after is moot
    with _late_callbacks_dropped():
        if task.cancelled():
            result.cancel()
        elif (error := task.exception()) is not None:
            # rclpy 9 annotates Exception; a task's other BaseException is handed on as it is.
            result.set_exception(error)  # type: ignore[arg-type, unused-ignore]
        else:
            result.set_result(task.result())


@contextlib.contextmanager
def _late_callbacks_dropped() -> Generator[None, None, None]:
    """Completing a task's future after its executor shut down (the task
    shut it down): rclpy's future hands its done-callbacks to the executor,
    which refuses new tasks now. They never run, as rclpy's tasks created
    after shutdown never run; the future is complete all the same."""
    with contextlib.suppress(ExecutorError):
        yield


def plain_work(run: Callable[[], None], done: Callable[[Work, BaseException | None], None]) -> Work:
    return Work(entity=run, call=run, is_async=False, depth=1 << 16, done=done)


def settle_from(result: RclFuture[Any], call: Callable[[], Any]) -> None:
    """Complete ``result`` with what ``call()`` returns or raises (unless cancelled meanwhile)."""
    try:
        value = call()
    except BaseException as exc:  # handed to the future's owner
        if not result.cancelled():
            with _late_callbacks_dropped():
                # rclpy 9 annotates Exception; a SystemExit is handed on as it is.
                result.set_exception(exc)  # type: ignore[arg-type, unused-ignore]
    else:
        if not result.cancelled():
            with _late_callbacks_dropped():
                result.set_result(value)



class TaskLaneHooks:
    """What the lane of plain tasks (:meth:`AsyncioExecutor.create_task` with a
    plain callable) asks of the executor (:class:`LaneHooks`): it starts
    nothing eagerly and carries nothing on."""

    carries = False
    handoff = None

    def __init__(self, *, post: Post, progress: Callable[[], asyncio.Future[None]]) -> None:
        self.post = post
        self.progress = progress
        self.workers = WorkerPool(name="executor:tasks", handoff=None, carries=False)

    def on_loop_thread(self) -> bool:
        return False

    def defer(self, lane: Lane, work: Work) -> bool:
        return False

    def carry(self) -> None:
        pass

    def suspended(self) -> None:
        pass


class DoneCallbacks:
    """Where a service response's future hands its done-callbacks.

    rclpy's future hands each done-callback to its executor as
    ``create_task(callback, future)`` and drops what that returns. Through
    :meth:`AsyncioExecutor.create_task` each one built a task future,
    passed ``spin_once``'s gate and was posted: with a client's two
    callbacks per response (rclpy's own and the caller's), about a fifth of
    a service round trip's time on the loop (py-spy, the services
    benchmark). While no ``spin_once`` counts callbacks and the loop's
    thread completes the future, a plain done-callback is posted as it is,
    to run after the wait, on that thread, as the task would have; an error
    it raises is logged (a task's would have sat in a future nobody reads).
    Anything else (a coroutine function, another thread, a gate) goes the
    full way.

    :param executor: the executor, for the full way.
    :param post: runs a call on the loop's thread after the current wait.
    :param on_loop_thread: whether the caller is the loop's thread, dispatching.
    :param gate: ``spin_once``'s gate (``permits`` is ``None`` outside it).
    """

    def __init__(
        self,
        *,
        executor: Executor,
        post: Post,
        on_loop_thread: Callable[[], bool],
        gate: Gate,
    ) -> None:
        self._executor = executor
        self._post = post
        self._on_loop_thread = on_loop_thread
        self._gate = gate
        #: The node whose client's response completes the future now (``_takes.take_response``):
        #: its done-callbacks are that node's work (``None``: the executor's, or the caller's).
        #: Set and cleared by the response's taker, under the wait set's take lock (clients are
        #: taken by the hot wait set only): one taker at a time.
        self.owner: Owner | None = None
        #: The last owner whose done-callbacks were posted, and its account's call: asking
        #: the owner (a Python call and a bound method) twice a response (rclpy's client
        #: adds a done-callback of its own) was about half a point of a service call.
        #: Touched on the loop's thread only; holds one owner at most, never a node.
        self._last: tuple[Owner, Callable[..., Any]] | None = None
        #: Whether a function is a coroutine function, by the function (a
        #: bound method's ``__func__``): ``inspect`` asks in several calls.
        self._coroutine: weakref.WeakKeyDictionary[Any, bool] = weakref.WeakKeyDictionary()

    def create_task(self, callback: Callable[..., Any], *args: Any, **kwargs: Any) -> RclFuture[Any] | None:
        owner = self.owner
        if kwargs or self._gate.permits is not None or not self._on_loop_thread() or self._is_coroutine(callback):
            if owner is None:
                return self._executor.create_task(callback, *args, **kwargs)
            reset = OWNER.set(owner)  # the executor's create_task credits the caller's node
            try:
                return self._executor.create_task(callback, *args, **kwargs)
            finally:
                OWNER.reset(reset)
        if owner is not None:
            last = self._last
            if last is None or last[0] is not owner:
                self._last = last = (owner, owner.account("loop_callback").call)
            self._post(last[1], 0, _run_done_callback, callback, args)
        else:
            self._post(_run_done_callback, callback, args)
        return None

    def _is_coroutine(self, callback: Callable[..., Any]) -> bool:
        function = getattr(callback, "__func__", callback)
        try:
            return self._coroutine[function]
        except (KeyError, TypeError):  # not seen yet; or not weakly referable
            pass
        found = inspect.iscoroutinefunction(callback)
        with contextlib.suppress(TypeError):
            self._coroutine[function] = found
        return found


def _run_done_callback(callback: Callable[..., Any], args: tuple[Any, ...]) -> None:
    try:
        callback(*args)
    except KeyboardInterrupt:
        raise
    except BaseException:  # logged, never fatal: sys.exit() included, as for any callback
        _log.exception("a done-callback of a service response raised")

