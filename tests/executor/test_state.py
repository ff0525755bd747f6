"""The executor's explicit state: every move it allows, and the ones it refuses."""

from __future__ import annotations

import threading

import pytest
from rclpy.context import Context
from rclpy.node import Node

from container import AsyncioExecutor, ExecutorError
from container.executor import ExecutorState


def state_of(executor: AsyncioExecutor) -> ExecutorState:
    """The state now (a call, so that mypy does not narrow it across moves)."""
    return executor.state


def test_idle_spinning_idle_then_shut_down(context: Context) -> None:
    executor = AsyncioExecutor(context=context)
    node = Node("state_probe", context=context)
    seen: list[ExecutorState] = []
    node.create_timer(0.01, lambda: seen.append(executor.state))
    executor.add_node(node)
    try:
        assert state_of(executor) is ExecutorState.IDLE
        executor.spin_once(timeout_sec=5.0)
        assert seen and seen[0] is ExecutorState.SPINNING
        assert state_of(executor) is ExecutorState.IDLE
        assert executor.shutdown(timeout_sec=5.0)
        assert state_of(executor) is ExecutorState.SHUT_DOWN
    finally:
        executor.shutdown()
        node.destroy_node()


def test_after_shutdown_create_task_and_spin_refuse_and_start_no_thread(context: Context) -> None:
    executor = AsyncioExecutor(context=context)
    assert executor.shutdown(timeout_sec=5.0)
    before = set(threading.enumerate())
    ran: list[int] = []
    with pytest.raises(ExecutorError, match="shut down"):
        executor.create_task(lambda: ran.append(1))
    with pytest.raises(ExecutorError, match="shut down"):
        executor.spin_once(timeout_sec=0)
    with pytest.raises(ExecutorError, match="shut down"):
        executor.spin()
    assert set(threading.enumerate()) - before == set()
    assert ran == []
    assert executor.shutdown(timeout_sec=1.0), "a second shutdown is harmless"


def test_shutdown_from_a_callback_stops_then_releases(context: Context) -> None:
    executor = AsyncioExecutor(context=context)
    node = Node("state_stopper", context=context)
    during: list[tuple[bool, ExecutorState]] = []

    def stop() -> None:
        # Inside a callback the spin is still returning: not released yet.
        during.append((executor.shutdown(timeout_sec=0), executor.state))

    node.create_timer(0.01, stop)
    executor.add_node(node)
    try:
        executor.spin()
        assert during[0] == (False, ExecutorState.STOPPING)
        assert state_of(executor) is ExecutorState.SHUT_DOWN
    finally:
        executor.shutdown()
        node.destroy_node()


def test_spinning_twice_at_once_is_refused(context: Context) -> None:
    executor = AsyncioExecutor(context=context)
    node = Node("state_twice", context=context)
    errors: list[BaseException] = []

    def again() -> None:
        try:
            executor.spin_once(timeout_sec=0)
        except ExecutorError as exc:
            errors.append(exc)
        executor.shutdown(timeout_sec=0)

    node.create_timer(0.01, again)
    executor.add_node(node)
    try:
        executor.spin()
        assert len(errors) == 1 and "already spinning" in str(errors[0])
    finally:
        executor.shutdown()
        node.destroy_node()


@pytest.mark.parametrize("keyword", ["num_threads", "reentrant_limit"])
def test_a_concurrency_below_one_is_refused(context: Context, keyword: str) -> None:
    with pytest.raises(ExecutorError, match=f"{keyword} must be at least 1, not 0"):
        if keyword == "num_threads":
            AsyncioExecutor(context=context, num_threads=0)
        else:
            AsyncioExecutor(context=context, reentrant_limit=0)


@pytest.mark.parametrize("kind", ["coroutine", "plain"])
def test_a_task_that_shuts_its_executor_down_completes_quietly(
    context: Context, kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Its future is done with its result; the done-callbacks that rclpy's
    future would now hand to the shut-down executor never run (as tasks
    created after shutdown never run), and nothing is logged for them.
    (rclpy's SingleThreadedExecutor raises AttributeError out of the spin.)"""
    executor = AsyncioExecutor(context=context)
    called: list[object] = []

    def stop() -> int:
        executor.shutdown(timeout_sec=0)
        return 42

    async def stop_async() -> int:
        return stop()

    try:
        task = executor.create_task(stop_async() if kind == "coroutine" else stop)
        task.add_done_callback(called.append)
        executor.spin_until_future_complete(task, timeout_sec=5.0)
        assert task.done() and task.result() == 42
        assert state_of(executor) is ExecutorState.SHUT_DOWN
        assert called == []
        assert [r.getMessage() for r in caplog.records if r.levelname in ("ERROR", "CRITICAL")] == []
    finally:
        executor.shutdown()
