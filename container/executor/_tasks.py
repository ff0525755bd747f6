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
from collections.abc import Callable, Generator
from typing import TYPE_CHECKING, Any

from rclpy.executors import Executor
from rclpy.task import Future as RclFuture

from .._errors import ExecutorError
from ._fastpath import Work
from ._inbox import Post

if TYPE_CHECKING:
    from ._lanes import Lane

__all__: list[str] = []


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

    def __init__(self, *, post: Post, progress: Callable[[], asyncio.Future[None]]) -> None:
        self.post = post
        self.progress = progress

    def on_loop_thread(self) -> bool:
        return False

    def defer(self, lane: Lane, work: Work) -> bool:
        return False

    def carry(self) -> None:
        pass

    def suspended(self) -> None:
        pass


