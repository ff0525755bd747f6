"""The one cross-thread entry point (``_inbox``): posts to an executor's own loop take one
wake-up, posts to any other loop go through asyncio, and nothing else posts across threads."""

from __future__ import annotations

import ast
import asyncio
import concurrent.futures
import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from rclpy.task import Future as RclFuture

from container import AsyncioExecutor
from container.executor import _inbox, call_soon, in_thread, result, run_coroutine
from tests.container_support import REPO
from tests.waiting import wait_until

#: asyncio's ways to reach a loop from another thread; only ``_inbox`` calls them.
ASYNCIO_CROSS_THREAD = {"call_soon_threadsafe", "run_coroutine_threadsafe"}
TIMEOUT = 5.0


def test_only_the_inbox_posts_to_a_loop_from_another_thread() -> None:
    """Every module of the container reaches a loop from another thread through
    ``container.executor._inbox`` (``call_soon``, ``run_coroutine``, an ``Inbox``)."""
    offenders = []
    # _loop is the loop itself: it overrides call_soon_threadsafe (to meter what it runs), posting nothing.
    exempt = {REPO / "container" / "executor" / "_inbox.py", REPO / "container" / "executor" / "_loop.py"}
    for path in sorted((REPO / "container").rglob("*.py")):
        if path in exempt:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            # ``loop.call_soon_threadsafe``, a bare name, or ``from asyncio import ...``
            if isinstance(node, ast.Attribute):
                name = node.attr
            elif isinstance(node, ast.Name):
                name = node.id
            elif isinstance(node, ast.alias):
                name = node.name
            else:
                continue
            if name in ASYNCIO_CROSS_THREAD:
                offenders.append(f"{path.relative_to(REPO)}:{node.lineno} uses {name}")
    assert offenders == []


class _Counted:
    """Counts the calls of a bound method it replaces."""

    def __init__(self, method: Callable[..., Any]) -> None:
        self.method = method
        self.calls = 0

    def __call__(self, *args: Any) -> Any:
        self.calls += 1
        return self.method(*args)


@pytest.fixture
def spinning(executor: AsyncioExecutor, monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, _Counted]]:
    """``executor`` spinning its own loop on a thread, its self-pipe writes and inbox wake-ups counted."""
    loop = executor.loop
    counts = {"self-pipe": _Counted(loop._write_to_self), "wake": _Counted(executor._inbox._wake)}  # type: ignore[attr-defined]
    monkeypatch.setattr(loop, "_write_to_self", counts["self-pipe"])
    monkeypatch.setattr(executor._inbox, "_wake", counts["wake"])
    thread = threading.Thread(target=executor.spin, name="spinning", daemon=True)
    thread.start()
    wait_until(lambda: _inbox._serving.get(loop) is executor._inbox, "the executor's loop served")
    try:
        yield counts
    finally:
        executor.shutdown()
        thread.join(TIMEOUT)


def _posted_from_here(post: Callable[[Callable[[], None]], object]) -> str:
    """The name of the thread that ran what ``post`` posted."""
    ran: concurrent.futures.Future[str] = concurrent.futures.Future()
    post(lambda: ran.set_result(threading.current_thread().name))
    return ran.result(TIMEOUT)


def test_a_post_from_another_thread_to_an_executors_own_loop_is_one_wake_up(
    executor: AsyncioExecutor, spinning: dict[str, _Counted]
) -> None:
    """One guard-condition trigger through the executor's inbox; asyncio's self-pipe (and
    with it the fd watcher's wake-up of rcl) is not touched."""
    watcher = executor._selector._watcher
    wakes = watcher.wakes
    for _ in range(3):
        assert _posted_from_here(lambda run: call_soon(executor.loop, run)) == "spinning"
    assert (spinning["wake"].calls, spinning["self-pipe"].calls) == (3, 0)
    assert watcher.wakes == wakes
    # asyncio's own way, for comparison: the self-pipe, which the fd watcher sees.
    assert _posted_from_here(lambda run: executor.loop.call_soon_threadsafe(run)) == "spinning"
    assert spinning["self-pipe"].calls == 1
    wait_until(lambda: watcher.wakes > wakes, "the fd watcher woke the loop for the self-pipe")


def test_an_error_a_post_raises_goes_to_the_loops_exception_handler_and_the_spin_goes_on(
    executor: AsyncioExecutor, spinning: dict[str, _Counted]
) -> None:
    """As asyncio reports a handle's error, though the inbox runs inside the loop's wait."""
    reported: concurrent.futures.Future[BaseException] = concurrent.futures.Future()
    executor.loop.set_exception_handler(lambda _, context: reported.set_result(context["exception"]))

    def fails() -> None:
        raise ValueError("posted and failed")

    call_soon(executor.loop, fails)
    assert str(reported.result(TIMEOUT)) == "posted and failed"
    assert _posted_from_here(lambda run: call_soon(executor.loop, run)) == "spinning"
    assert spinning["self-pipe"].calls == 0


def test_bridge_outcomes_reach_an_executors_own_loop_through_its_inbox(
    executor: AsyncioExecutor, spinning: dict[str, _Counted]
) -> None:
    """``in_thread``'s outcome and an rclpy future's result (``mirror``), completed on other threads."""
    rcl_future: RclFuture[Any] = RclFuture()

    async def both() -> tuple[str, str]:
        made = await in_thread(lambda: threading.current_thread().name, name="made-elsewhere")
        threading.Timer(0.01, rcl_future.set_result, ("done",)).start()
        return made, await result(rcl_future, timeout=TIMEOUT)

    outcome = run_coroutine(both(), executor.loop)
    assert outcome.result(TIMEOUT) == ("made-elsewhere", "done")
    assert spinning["self-pipe"].calls == 0
    assert spinning["wake"].calls >= 3  # the coroutine's start, the thread's outcome, the future's


def test_run_coroutine_runs_on_the_loop_and_is_cancelled_from_another_thread(
    executor: AsyncioExecutor, spinning: dict[str, _Counted]
) -> None:
    started = threading.Event()
    cancelled = threading.Event()

    async def forever() -> None:
        started.set()
        try:
            await asyncio.sleep(60)
        except asyncio.CancelledError:
            cancelled.set()
            raise

    pending = run_coroutine(forever(), executor.loop)
    assert started.wait(TIMEOUT)
    assert pending.cancel()
    assert cancelled.wait(TIMEOUT)
    assert spinning["self-pipe"].calls == 0

    async def fails() -> None:
        raise ValueError("no")

    with pytest.raises(ValueError, match="no"):
        run_coroutine(fails(), executor.loop).result(TIMEOUT)


def test_posts_to_any_other_loop_go_through_asyncio() -> None:
    """A loop no executor spins as its own (a user's, under ``spin_async``): asyncio's
    ``call_soon_threadsafe`` from another thread, ``call_soon`` from its own."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="user-loop", daemon=True)
    thread.start()
    try:
        assert _posted_from_here(lambda run: call_soon(loop, run)) == "user-loop"

        async def here() -> str:
            done: asyncio.Future[str] = loop.create_future()
            call_soon(loop, done.set_result, threading.current_thread().name)
            return await done

        assert run_coroutine(here(), loop).result(TIMEOUT) == "user-loop"
    finally:
        loop.call_soon_threadsafe(loop.stop)
        thread.join(TIMEOUT)
        loop.close()
    call_soon(loop, pytest.fail, "ran on a closed loop")  # nothing, as asyncio would refuse
    coro = asyncio.sleep(0)
    with pytest.raises(RuntimeError, match="closed"):
        run_coroutine(coro, loop)
    coro.close()


def test_an_executors_own_loop_is_served_only_while_it_spins(executor: AsyncioExecutor) -> None:
    """Between spins nothing runs the inbox: posts to the own loop go through asyncio then."""
    seen: list[bool] = []

    async def look() -> None:
        seen.append(_inbox._serving.get(executor.loop) is executor._inbox)

    assert executor.loop not in _inbox._serving
    executor.spin_until_future_complete(look(), timeout_sec=TIMEOUT)
    assert seen == [True]
    assert executor.loop not in _inbox._serving
