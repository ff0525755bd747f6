"""The one bridge between rclpy futures and asyncio.

rclpy's futures complete on whatever thread takes the response (or in an
executor's task), and ``await``-ing one yields a bare ``None`` until it is
done: to asyncio, "run me again at once", a busy loop. Everything in the
project that waits for an rclpy future from asyncio code goes through here:

* :func:`mirror` gives an asyncio future on a chosen loop that completes with
  the rclpy one, from any thread, and never touches a closed loop;
* :func:`result` awaits an rclpy future's result with an optional timeout;
* :func:`drive` runs a coroutine that may ``await`` rclpy futures directly
  (rclpy-style code), parking it on a progress signal instead of spinning;
  :func:`adapt` wraps one so that any asyncio task can await it;
  :func:`drive_in_thread` runs one on a worker thread instead;
* :func:`in_thread` awaits a plain call that may block (a constructor, a
  transition callback) on a thread of its own.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import functools
import time
import types
from collections.abc import Awaitable, Callable, Coroutine, Generator
from typing import Any, TypeVar

from rclpy.task import Future as RclFuture

from .._compat import running_loop, sleeps_zero
from ._engine import Work
from ._inbox import call_soon
from ._owners import OWNER, Owner
from ._spare import run_on_spare_thread

__all__ = [
    "Escaped",
    "adapt",
    "as_exception",
    "contained",
    "drive",
    "drive_in_thread",
    "in_thread",
    "is_adapted",
    "mirror",
    "result",
]

T = TypeVar("T")


class Escaped(Exception):
    """A ``SystemExit`` (or other non-``Exception``) a callback raised, carried as an exception.

    asyncio re-raises ``SystemExit`` and ``KeyboardInterrupt`` set on a
    future out of the event loop itself, ending the process: a plugin's
    ``sys.exit()`` must reach its awaiting caller as an ordinary error.
    """

    def __init__(self, error: BaseException) -> None:
        super().__init__(f"{type(error).__name__}: {error}")
        self.error = error


def as_exception(error: BaseException) -> Exception:
    """``error`` itself if it is an ``Exception``, else wrapped in :class:`Escaped`."""
    return error if isinstance(error, Exception) else Escaped(error)


async def contained(awaitable: Awaitable[T]) -> T:
    """Await a plugin's coroutine so that its ``sys.exit()`` cannot end the loop.

    A ``SystemExit`` escaping a task ends the event loop (asyncio re-raises
    it); here it becomes :class:`Escaped`, an ordinary error for the caller.
    Cancellation and Ctrl-C pass through unchanged.
    """
    try:
        return await awaitable
    except (KeyboardInterrupt, asyncio.CancelledError, GeneratorExit):
        raise
    except BaseException as exc:
        raise as_exception(exc) from exc


def mirror(future: RclFuture[Any], loop: asyncio.AbstractEventLoop) -> asyncio.Future[Any]:
    """An asyncio future on ``loop`` that settles as ``future`` does.

    Result, exception and cancellation carry over. Safe whichever thread
    completes ``future``; once ``loop`` is closed nothing is scheduled on it.
    """
    settled: asyncio.Future[Any] = loop.create_future()

    def copy() -> None:
        if settled.done():
            return
        if future.cancelled():
            settled.cancel()
        elif (error := future.exception()) is not None:
            settled.set_exception(as_exception(error))
        else:
            settled.set_result(future.result())

    def on_done(_: RclFuture[Any]) -> None:
        call_soon(loop, copy)

    if future.done() and running_loop() is loop:
        # Done already: copied now. rclpy would hand on_done to the future's
        # executor as a task, which one shut down (by that very task) refuses.
        copy()
        return settled
    # rclpy runs this at once if the future is already done, on the
    # completing thread if it has no executor, else as an executor task.
    future.add_done_callback(on_done)
    return settled


async def result(future: RclFuture[Any], *, timeout: float | None = None) -> Any:
    """Wait for ``future`` on the running loop and return its result (or raise its error).

    :raises TimeoutError: not done within ``timeout`` seconds; ``future`` is
        left as it is (a client may then drop its pending request).
    """
    return await asyncio.wait_for(mirror(future, asyncio.get_running_loop()), timeout)


@types.coroutine
def drive(
    coro: Coroutine[Any, Any, T],
    progress: Callable[[], asyncio.Future[None]],
    *,
    yielded: Any = None,
    thrown: BaseException | None = None,
    started: bool = False,
    on_suspend: Callable[[], object] | None = None,
    context: contextvars.Context | None = None,
    work: Work | None = None,
) -> Generator[Any, Any, T]:
    """Run ``coro`` inside a task, turning rclpy's bare ``yield`` into a real wait.

    (``asyncio.sleep(0)``'s bare ``yield`` stays what it is in asyncio: the
    task runs again at once, after what else is ready.)

    ``await`` it from an ``async def`` (it is a generator-based awaitable,
    as ``asyncio.sleep(0)``'s own ``__sleep0`` is: every supported asyncio
    accepts it inside a coroutine, where from 3.12 ``Task`` itself takes
    only coroutines). ``progress()`` is a future that completes when
    something an rclpy future may be waiting for has happened (a response
    taken, a done-callback scheduled), or after a short poll interval.

    :param started: ``coro`` already ran up to a suspension at ``yielded``
        (or is to receive ``thrown`` there): carry on from that point.
    :param on_suspend: called once if ``coro``'s first step suspends (not
        when started): where rclpy's ``spin_once`` counts a callback as run.
    :param context: each step of ``coro`` runs in it (a callback's own
        copy of its runner task's context); else in the task's.
    :param work: the callback's work, whose meter times each step.
    """
    send: Callable[[Any], Any] = coro.send
    throw: Callable[[BaseException], Any] = coro.throw
    if context is not None:
        run: Callable[..., Any] = context.run
        send = functools.partial(run, coro.send)
        throw = functools.partial(run, coro.throw)
    if work is not None and work.meter is not None:
        send = functools.partial(work.step, send)
        throw = functools.partial(work.step, throw)
    if not started:
        try:
            yielded = send(None)
        except StopIteration as stop:
            done: T = stop.value
            return done
        if on_suspend is not None:
            on_suspend()
    while True:
        value: Any = None
        if thrown is None:
            try:
                if yielded is None and not sleeps_zero(coro):
                    yield from progress()
                else:
                    # asyncio.sleep(0) yields a bare None too: to the task,
                    # "run me again at once", as asyncio does.
                    value = yield yielded
            except BaseException as exc:  # forwarded into the coroutine
                thrown = exc
        try:
            if thrown is None:
                yielded = send(value)
            else:
                error, thrown = thrown, None
                if isinstance(error, GeneratorExit) and _closed(coro):
                    # Collected with the task it ran in, ``coro`` may have been closed
                    # first: throwing into it would raise "cannot reuse already awaited".
                    raise error
                yielded = throw(error)
        except StopIteration as stop:
            finished: T = stop.value
            return finished


def _closed(coro: object) -> bool:
    """Whether ``coro`` (a coroutine, or asyncio's wrapper generator before 3.12) has finished."""
    return getattr(coro, "cr_frame", getattr(coro, "gi_frame", True)) is None


async def _adapted(
    coro: Coroutine[Any, Any, T],
    progress: Callable[[], asyncio.Future[None]],
    on_suspend: Callable[[], object] | None,
    work: Work | None,
) -> T:
    return await drive(coro, progress, on_suspend=on_suspend, work=work)


def is_adapted(coro: object) -> bool:
    """Whether ``coro`` came from :func:`adapt`: adapting it again would hide
    its ``asyncio.sleep(0)`` from the outer driver, which would park it."""
    return getattr(coro, "cr_code", None) is _adapted.__code__


def adapt(
    coro: Coroutine[Any, Any, T],
    progress: Callable[[], asyncio.Future[None]],
    *,
    on_suspend: Callable[[], object] | None = None,
    work: Work | None = None,
) -> Coroutine[Any, Any, T]:
    """``coro`` as a coroutine that :func:`drive` runs (see there): what a task takes.

    :param work: whose meter times each step (a node's task: see ``_owners``).
    """
    adapted: Coroutine[Any, Any, T] = _adapted(coro, progress, on_suspend, work)
    # Named after what it runs: task reprs and the watchdog's reports show it.
    for name in ("__name__", "__qualname__"):
        with contextlib.suppress(AttributeError, TypeError):
            setattr(adapted, name, getattr(coro, name))
    return adapted


async def in_thread(call: Callable[[], T], *, name: str) -> T:
    """Run ``call`` on a daemon thread of its own, named ``name``; await its outcome.

    A thread of its own, not a pool's: a call that never returns costs one
    idle thread, never the pool everyone else waits on (a thread whose
    call returned is reused: see ``_spare``). If the awaiting coroutine
    gives up (cancelled, timed out), the call runs on and its outcome is
    dropped. Any exception, ``SystemExit`` included, is raised to the
    awaiting coroutine.

    The call runs in a copy of the caller's context, as ``asyncio.to_thread``'s
    does: a node's transition callback, or its constructor, runs as that
    node and is metered as its call on a thread (see ``_owners``); what it
    starts is the node's.
    """
    loop = asyncio.get_running_loop()
    outcome: asyncio.Future[T] = loop.create_future()
    context = contextvars.copy_context()
    owner = OWNER.get()
    run: Callable[[], object]
    if isinstance(owner, Owner):
        run = functools.partial(context.run, owner.account("thread_call").call, 0, call)
    else:
        run = functools.partial(context.run, call)

    def settle(value: object, error: BaseException | None) -> None:
        if outcome.done():
            return
        if error is not None:
            outcome.set_exception(as_exception(error))
        else:
            outcome.set_result(value)  # type: ignore[arg-type]  # what call returned

    def deliver(value: object, error: BaseException | None) -> None:
        call_soon(loop, settle, value, error)

    run_on_spare_thread(run, deliver, name=name)
    return await outcome


#: How long :func:`drive_in_thread` sleeps when its coroutine yields bare.
_THREAD_POLL_S = 0.001


def drive_in_thread(coro: Coroutine[Any, Any, T]) -> T:
    """Run an rclpy-style coroutine to its end on the calling (worker) thread.

    For rclpy's own coroutines that call a plain, possibly blocking, callback
    (an action server's execute): they await nothing asyncio, only rclpy
    futures, which yield a bare ``None`` until done, so a short sleep between
    steps is all the waiting they need.

    :raises RuntimeError: the coroutine awaited something of asyncio's,
        which cannot run off the loop.
    """
    while True:
        try:
            yielded = coro.send(None)
        except StopIteration as stop:
            value: T = stop.value
            return value
        if yielded is not None:
            coro.close()
            raise RuntimeError(f"{getattr(coro, '__qualname__', coro)} awaited {yielded!r} off the event loop")
        time.sleep(_THREAD_POLL_S)
