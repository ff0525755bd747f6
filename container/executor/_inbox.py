"""The one way work reaches an event loop's thread from another thread.

As trio's ``EntryQueue`` is for its loop, this module is the container's
single cross-thread entry point: no other module of the container calls
asyncio's ``call_soon_threadsafe`` or ``run_coroutine_threadsafe``
(``tests/executor/test_inbox.py`` checks it). :func:`call_soon` and
:func:`run_coroutine` post to any loop; each executor's :class:`Inbox`
holds what is posted to its own loop.

An executor's own loop sleeps in ``rcl_wait``, not in its selector: while
it spins (:meth:`Inbox.serving`), a post to it from another thread is a
deque and one guard-condition trigger (one wake-up, where
``call_soon_threadsafe`` costs three: self-pipe, fd watcher, guard
condition), run after the wait returns. Any other loop (a user's, under
``spin_async``; an executor's own one while nobody spins it) gets asyncio's
``call_soon_threadsafe``, and a post from the loop's own thread asyncio's
``call_soon``.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import functools
import threading
from collections.abc import Callable, Coroutine, Iterator
from typing import Any, TypeVar

from .._compat import running_loop

__all__ = ["Inbox", "Post", "call_soon", "run_coroutine"]

T = TypeVar("T")

#: Runs ``callback(*args)`` on a loop's thread soon; callable from any thread.
Post = Callable[..., None]

#: The inbox of each executor's own loop while that executor spins it (its
#: thread waits in rcl and runs the inbox after every wait).
_serving: dict[asyncio.AbstractEventLoop, Inbox] = {}


def call_soon(loop: asyncio.AbstractEventLoop, callback: Callable[..., object], *args: Any) -> None:
    """Run ``callback(*args)`` on ``loop``'s thread soon (any thread; nothing once ``loop`` is closed).

    From ``loop``'s own thread: in its next iteration. From another thread:
    after the next wait of the executor spinning ``loop`` as its own (one
    guard-condition trigger), else through asyncio's ``call_soon_threadsafe``.
    Either way an error ``callback`` raises goes to the loop's exception
    handler, as asyncio's.
    """
    if loop.is_closed():
        return
    if running_loop() is loop:
        loop.call_soon(callback, *args)
        return
    inbox = _serving.get(loop)
    if inbox is not None:
        inbox.post(_run_reported, loop, callback, args)
    else:
        loop.call_soon_threadsafe(callback, *args)


def _run_reported(loop: asyncio.AbstractEventLoop, callback: Callable[..., object], args: tuple[Any, ...]) -> None:
    """``callback(*args)`` as asyncio runs a handle: an error goes to the loop's exception handler
    (the inbox runs inside the loop's wait, which an error would end)."""
    try:
        callback(*args)
    except (SystemExit, KeyboardInterrupt):
        raise
    except BaseException as exc:  # reported as asyncio reports a handle's
        loop.call_exception_handler({"message": f"Exception in callback {callback!r}", "exception": exc})


def run_coroutine(coro: Coroutine[Any, Any, T], loop: asyncio.AbstractEventLoop) -> concurrent.futures.Future[T]:
    """asyncio's ``run_coroutine_threadsafe``, posted through :func:`call_soon`.

    ``coro`` runs as a task on ``loop`` (made by the loop's task factory);
    the returned future settles as the task does, and cancelling it (from
    any thread) cancels the task.

    :raises RuntimeError: ``loop`` is closed.
    """
    if loop.is_closed():
        raise RuntimeError("Event loop is closed")
    outcome: concurrent.futures.Future[T] = concurrent.futures.Future()

    def start() -> None:
        try:
            task = loop.create_task(coro)
        except (SystemExit, KeyboardInterrupt):
            raise
        except BaseException as exc:  # the waiting thread's, and reported as asyncio does
            if outcome.set_running_or_notify_cancel():
                outcome.set_exception(exc)
            raise
        task.add_done_callback(functools.partial(_copy_outcome, outcome))

        def cancel_task(_: concurrent.futures.Future[T]) -> None:
            if outcome.cancelled():
                call_soon(loop, task.cancel)

        outcome.add_done_callback(cancel_task)

    call_soon(loop, start)
    return outcome


def _copy_outcome(outcome: concurrent.futures.Future[T], task: asyncio.Future[T]) -> None:
    """``task``'s end, told to ``outcome`` (as asyncio's ``_set_concurrent_future_state``)."""
    if task.cancelled():
        outcome.cancel()
    if not outcome.set_running_or_notify_cancel():
        return
    error = task.exception()
    if error is not None:
        outcome.set_exception(error)
    else:
        outcome.set_result(task.result())


class Inbox:
    """Hand-overs to an executor's own loop, and to any other loop.

    :param loop: the executor's own loop.
    :param wake: wakes that loop's thread out of ``rcl_wait``.
    """

    def __init__(self, *, loop: asyncio.AbstractEventLoop, wake: Callable[[], None]) -> None:
        self._loop = loop
        self._wake = wake
        self._queue: collections.deque[tuple[Callable[..., object], tuple[Any, ...]]] = collections.deque()
        #: The thread between a wait and the :meth:`run` after it (see :meth:`draining`).
        self._drainer: int | None = None

    @contextlib.contextmanager
    def serving(self) -> Iterator[None]:
        """The own loop spins, its thread waiting in rcl: :func:`call_soon` from
        other threads posts to it here, not through asyncio's self-pipe."""
        _serving[self._loop] = self
        try:
            yield
        finally:
            _serving.pop(self._loop, None)

    def post(self, callback: Callable[..., object], *args: Any) -> None:
        """Run ``callback(*args)`` on the own loop's thread after its next wait (any thread)."""
        self._queue.append((callback, args))
        if self._drainer is None or self._drainer != threading.get_ident():
            self._wake()

    def draining(self, thread: int | None) -> None:
        """``thread`` (``None``: nobody) dispatches a wait and then calls :meth:`run`:
        what it posts meanwhile runs then, without a wake-up (a guard
        condition's trigger, and the next wait returning at once for it)."""
        self._drainer = thread

    def post_to(self, loop: asyncio.AbstractEventLoop, callback: Callable[..., object], *args: Any) -> None:
        """:meth:`post` for the own loop (spinning or not), :func:`call_soon` for any other."""
        if loop is self._loop:
            self.post(callback, *args)
        else:
            call_soon(loop, callback, *args)

    def poster(self, loop: asyncio.AbstractEventLoop) -> Post:
        """What posts to ``loop`` from any thread: :meth:`post` for the own loop."""
        if loop is self._loop:
            return self.post

        def post(callback: Callable[..., object], *args: Any) -> None:
            loop.call_soon_threadsafe(callback, *args)

        return post

    def run(self) -> None:
        """Run what was posted (on the own loop's thread, after a wait)."""
        queue = self._queue
        while queue:
            callback, args = queue.popleft()
            callback(*args)

    def clear(self) -> None:
        self._queue.clear()

    def __bool__(self) -> bool:
        return bool(self._queue)

    def __len__(self) -> int:
        return len(self._queue)
