"""Fault containment: a callback raising in an active node sends it through error processing."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from rclpy.context import Context
from rclpy.lifecycle import LifecycleNode as RclpyLifecycleNode
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import String

from container import AsyncioExecutor
from container.demo import Talker
from container.lifecycle._faults import contain_fault
from container.lifecycle._node import LifecycleNode
from tests.lifecycle_support import TransitionLog, run

SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE

ERROR_ROUTE = [
    ("unconfigured", "configuring"),
    ("configuring", "inactive"),
    ("inactive", "activating"),
    ("activating", "active"),
    ("active", "deactivating"),
    ("deactivating", "errorprocessing"),
]


@pytest.fixture
def executor(context: Context) -> Iterator[AsyncioExecutor]:
    """An executor whose callback errors go to fault containment (as in a container)."""
    executor = AsyncioExecutor(context=context, on_callback_error=contain_fault)
    try:
        yield executor
    finally:
        executor.shutdown(timeout_sec=5.0)



class Faulty(LifecycleNode):
    """A managed timer that raises once ``explode`` is set."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.explode = False
        self.recover = SUCCESS
        self.errors: list[str] = []
        self.create_timer(0.01, self._tick)

    def _tick(self) -> None:
        if self.explode:
            raise ValueError("sensor returned garbage")

    async def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.errors.append(state.label)
        return self.recover


@pytest.mark.parametrize(("recover", "final"), [(SUCCESS, "unconfigured"), (FAILURE, "finalized")])
def test_raising_active_node_goes_through_error_processing_while_neighbours_publish(
    executor: AsyncioExecutor,
    host: Callable[..., Any],
    capfd: pytest.CaptureFixture[str],
    recover: TransitionCallbackReturn,
    final: str,
) -> None:
    faulty: Faulty = host(Faulty, "faulty")
    faulty.recover = recover
    talker: Talker = host(Talker, "talker")
    talker.set_parameters([Parameter("rate", value=100.0)])
    observer = host(Node, "observer")
    heard: list[str] = []
    observer.create_subscription(String, "/chatter", lambda msg: heard.append(msg.data), 100)
    log = TransitionLog(observer, ["/faulty", "/talker"])
    log.wait_matched()

    async def heard_at_least(count: int) -> None:
        while len(heard) < count:
            await asyncio.sleep(0.005)

    async def scenario() -> int:
        for node in (faulty, talker):
            assert await node.transition("configure")
            assert await node.transition("activate")
        await heard_at_least(5)
        faulty.explode = True
        await log.wait_for_async("/faulty", final)
        after_fault = len(heard)
        await heard_at_least(after_fault + 10)
        return after_fault

    run(executor, scenario())
    assert faulty.lifecycle_state.label == final
    assert talker.lifecycle_state.label == "active"
    assert faulty.errors == ["active"]
    assert log.pairs("/faulty") == [*ERROR_ROUTE, ("errorprocessing", final)]
    assert log.pairs("/talker")[-1] == ("activating", "active")
    err = capfd.readouterr().err
    assert "ValueError: sensor returned garbage" in err
    assert "Traceback" in err
    assert "Entering error processing" in err


class PlainFaulty(RclpyLifecycleNode):
    """An rclpy lifecycle node (not the project's base) whose subscription raises."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.create_subscription(String, "/poison", self._eat, 10)

    def _eat(self, message: String) -> None:
        raise RuntimeError(f"cannot digest {message.data}")


def test_plain_rclpy_lifecycle_node_is_contained_too(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    node: PlainFaulty = host(PlainFaulty, "plain")
    observer = host(Node, "observer")
    poison = observer.create_publisher(String, "/poison", 10)
    log = TransitionLog(observer, ["/plain"])
    log.wait_matched()
    assert node.trigger_configure() == SUCCESS
    assert node.trigger_activate() == SUCCESS

    async def scenario() -> None:
        while poison.get_subscription_count() == 0:
            await asyncio.sleep(0.01)
        poison.publish(String(data="nails"))
        await log.wait_for_async("/plain", "unconfigured", after=2)

    run(executor, scenario())
    assert log.pairs("/plain")[-3:] == [
        ("active", "deactivating"),
        ("deactivating", "errorprocessing"),
        ("errorprocessing", "unconfigured"),
    ]


def test_errors_in_inactive_nodes_change_nothing(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    node: PlainFaulty = host(PlainFaulty, "idle")
    observer = host(Node, "observer")
    poison = observer.create_publisher(String, "/poison", 10)
    received: list[str] = []
    observer.create_subscription(String, "/poison", lambda msg: received.append(msg.data), 10)
    assert node.trigger_configure() == SUCCESS

    async def scenario() -> None:
        while poison.get_subscription_count() < 2:
            await asyncio.sleep(0.01)
        poison.publish(String(data="nails"))
        # The observer's own copy arriving means the node's arrived as well.
        while not received:
            await asyncio.sleep(0.005)

    run(executor, scenario())
    assert node._state_machine.current_state[1] == "inactive"
