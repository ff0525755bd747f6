"""Actions on AsyncioExecutor: rclpy's ActionServer and ActionClient, plain and ``async def``.

The counter server is the seed tutorial's, as written: an ``async def``
execute callback that publishes feedback every step, ``await
asyncio.sleep(1.0)``s between steps and honours cancellation. On rclpy's own
executors it fails ("no running event loop"); here it must just work.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from action_msgs.msg import GoalStatus
from lifecycle_container_interfaces.action import CountTo
from rclpy.action.client import ActionClient
from rclpy.action.server import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from container import AsyncioExecutor
from container.demo import Counter
from tests.container_support import REPO, ContainerProcess
from tests.lifecycle_support import run

#: Every wait in these tests is bounded by this (seconds).
TIMEOUT = 20.0


class CounterActionServer(Node):
    """The seed tutorial's counter, verbatim but for the context and the step."""

    def __init__(self, *, context: Context, step: float = 1.0) -> None:
        super().__init__("counter_server", context=context)
        self.step = step
        self._server = ActionServer(self, CountTo, "count_to", self.execute_callback)

    async def execute_callback(self, goal_handle: Any) -> Any:
        n = goal_handle.request.target
        feedback = CountTo.Feedback()
        for i in range(n):
            feedback.current_count = i
            goal_handle.publish_feedback(feedback)
            await asyncio.sleep(self.step)
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
                return CountTo.Result(final_count=i)
        goal_handle.succeed()
        result = CountTo.Result()
        result.final_count = n
        return result


class PlainCounter(Node):
    """The same counter with plain callbacks throughout: execute blocks its thread."""

    def __init__(self, *, context: Context, step: float = 0.05) -> None:
        super().__init__("plain_counter", context=context)
        self.step = step
        self.execute_threads: set[int] = set()
        self._server = ActionServer(
            self,
            CountTo,
            "plain_count_to",
            self.execute,
            goal_callback=self.on_goal,
            cancel_callback=self.on_cancel,
            callback_group=ReentrantCallbackGroup(),
        )

    def on_goal(self, goal: Any) -> GoalResponse:
        return GoalResponse.ACCEPT if goal.target >= 0 else GoalResponse.REJECT

    def on_cancel(self, goal_handle: Any) -> CancelResponse:
        return CancelResponse.ACCEPT

    def execute(self, goal_handle: Any) -> Any:
        self.execute_threads.add(threading.get_ident())
        feedback = CountTo.Feedback()
        for i in range(goal_handle.request.target):
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
                return CountTo.Result(final_count=i)
            feedback.current_count = i
            goal_handle.publish_feedback(feedback)
            time.sleep(self.step)
        goal_handle.succeed()
        return CountTo.Result(final_count=goal_handle.request.target)


@pytest.fixture
def spinning(executor: AsyncioExecutor) -> Iterator[AsyncioExecutor]:
    """``executor`` spinning on a thread; the nodes added to it are destroyed afterwards.

    Destroyed, not left to the context's shutdown: a node outlives it until
    collected, and a stale action server would answer the next test's goals.
    """
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    yield executor
    nodes = executor.get_nodes()
    executor.shutdown(timeout_sec=2.0)
    thread.join(5.0)
    for node in nodes:
        # destroy_node() leaves action servers and clients alive until collected.
        for waitable in list(node.waitables):
            if isinstance(waitable, ActionServer | ActionClient):
                waitable.destroy()  # type: ignore[no-untyped-call, unused-ignore]  # rclpy 7's is untyped
        node.destroy_node()


def loop_thread(executor: AsyncioExecutor) -> int:
    async def ident() -> int:
        return threading.get_ident()

    return asyncio.run_coroutine_threadsafe(ident(), executor.loop).result(TIMEOUT)


def _wait(future: Any, timeout: float = TIMEOUT) -> Any:
    """Block this (non-executor) thread until an rclpy future is done."""
    done = threading.Event()
    future.add_done_callback(lambda _: done.set())
    assert done.wait(timeout), "timed out"
    return future.result()


class Feedback(list[int]):
    """Feedback counts as they arrive, with an event per count reached."""

    def __init__(self) -> None:
        super().__init__()
        self._grew = threading.Condition()

    def __call__(self, msg: Any) -> None:
        with self._grew:
            self.append(msg.feedback.current_count)
            self._grew.notify_all()

    def wait_for(self, count: int) -> None:
        with self._grew:
            assert self._grew.wait_for(lambda: len(self) >= count, TIMEOUT), f"only {list(self)}"


def _client(node: Node, action: str) -> ActionClient[Any, Any, Any]:
    client: ActionClient[Any, Any, Any] = ActionClient(node, CountTo, action)
    assert client.wait_for_server(timeout_sec=TIMEOUT)
    return client


def _send(client: ActionClient[Any, Any, Any], target: int, feedback: Feedback) -> Any:
    return client.send_goal_async(CountTo.Goal(target=target), feedback_callback=feedback)


# The seed's counter as written: a second per step.
@pytest.mark.slow
def test_seed_counter_runs_as_written(context: Context, spinning: AsyncioExecutor) -> None:
    server = CounterActionServer(context=context)
    caller = Node("counter_caller", context=context)
    spinning.add_node(server)
    spinning.add_node(caller)
    feedback = Feedback()
    client = _client(caller, "count_to")
    started = time.monotonic()
    goal = _wait(_send(client, 3, feedback))
    assert goal.accepted
    outcome = _wait(goal.get_result_async())
    assert outcome.status == GoalStatus.STATUS_SUCCEEDED
    assert outcome.result.final_count == 3
    assert feedback == [0, 1, 2]
    assert 2.5 < time.monotonic() - started < 10.0  # three one-second steps


def test_seed_counter_cancelled_mid_way(context: Context, spinning: AsyncioExecutor) -> None:
    server = CounterActionServer(context=context, step=0.2)
    # rclpy's default cancel callback rejects every request: accepting is the
    # server's choice (the seed's loop then honours it).
    server._server.register_cancel_callback(lambda _: CancelResponse.ACCEPT)
    caller = Node("counter_caller", context=context)
    spinning.add_node(server)
    spinning.add_node(caller)
    feedback = Feedback()
    client = _client(caller, "count_to")
    goal = _wait(_send(client, 100, feedback))
    assert goal.accepted
    feedback.wait_for(2)
    cancel = _wait(goal.cancel_goal_async())
    assert len(cancel.goals_canceling) == 1
    outcome = _wait(goal.get_result_async())
    assert outcome.status == GoalStatus.STATUS_CANCELED
    assert 1 <= outcome.result.final_count < 100  # stopped at the step the cancel arrived in


def test_plain_callbacks_and_rejection(context: Context, spinning: AsyncioExecutor) -> None:
    server = PlainCounter(context=context)
    caller = Node("plain_caller", context=context)
    spinning.add_node(server)
    spinning.add_node(caller)
    feedback = Feedback()
    client = _client(caller, "plain_count_to")
    goal = _wait(_send(client, 4, feedback))
    outcome = _wait(goal.get_result_async())
    assert (outcome.status, outcome.result.final_count) == (GoalStatus.STATUS_SUCCEEDED, 4)
    assert feedback == [0, 1, 2, 3]
    # A blocking execute callback runs on a worker thread, never the loop's.
    assert server.execute_threads
    assert loop_thread(spinning) not in server.execute_threads
    rejected = _wait(_send(client, -1, feedback))
    assert not rejected.accepted


def test_counter_lifecycle_node_takes_goals_only_while_active(
    executor: AsyncioExecutor, host: Callable[..., Any], client_node: Node
) -> None:
    counter: Counter = host(Counter, "counter", parameter_overrides=[Parameter("step", value=0.05)])
    feedback = Feedback()

    async def scenario() -> tuple[bool, bool, Any]:
        assert await counter.transition("configure")
        client: ActionClient[Any, Any, Any] = ActionClient(client_node, CountTo, "count_to")
        await asyncio.wait_for(_server_ready(client), TIMEOUT)
        inactive = await client.send_goal_async(CountTo.Goal(target=2))
        assert await counter.transition("activate")
        negative = await client.send_goal_async(CountTo.Goal(target=-1))
        active = await client.send_goal_async(CountTo.Goal(target=3), feedback_callback=feedback)
        assert inactive is not None and negative is not None and active is not None
        outcome = await active.get_result_async()
        client.destroy()
        return inactive.accepted or negative.accepted, active.accepted, outcome

    wrongly_accepted, accepted, outcome = run(executor, scenario())
    assert not wrongly_accepted and accepted
    assert (outcome.status, outcome.result.final_count) == (GoalStatus.STATUS_SUCCEEDED, 3)
    assert list(feedback) == [0, 1, 2]


async def _server_ready(client: ActionClient[Any, Any, Any]) -> None:
    while not client.server_is_ready():
        await asyncio.sleep(0.02)


# A container process and a client process, a second per step.
@pytest.mark.slow
def test_counter_in_a_container_driven_from_another_process(
    run_container: Callable[..., ContainerProcess], tmp_path: Path
) -> None:
    config = (
        (REPO / "examples" / "counter.yaml")
        .read_text(encoding="utf-8")
        .replace("step: 1.0", "step: 0.1")
        .replace("    name: counter\n", "    name: counter\n    namespace: /far\n")
    )
    run_container(config)
    example = [sys.executable, str(REPO / "examples" / "count_to.py"), "--action", "/far/count_to"]
    done = subprocess.run(
        [*example, "3", "--wait", str(TIMEOUT)], capture_output=True, text=True, timeout=60, check=False
    )
    assert done.returncode == 0, done.stdout + done.stderr
    # Feedback may overtake the goal's acceptance: only their own order counts.
    assert [line for line in done.stdout.splitlines() if line.startswith("feedback")] == [
        "feedback: 0",
        "feedback: 1",
        "feedback: 2",
    ]
    assert "result: succeeded, final_count=3" in done.stdout
    cancelled = subprocess.run(
        [*example, "50", "--cancel-after", "0.35", "--wait", str(TIMEOUT)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert cancelled.returncode == 0, cancelled.stdout + cancelled.stderr
    assert "result: canceled" in cancelled.stdout


def test_counter_refuses_a_negative_step_at_configure(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    counter: Counter = host(Counter, "counter", parameter_overrides=[Parameter("step", value=-1.0)])
    assert not run(executor, counter.transition("configure"))
    assert counter.lifecycle_state.label == "unconfigured"
