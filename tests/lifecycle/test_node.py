"""The lifecycle node base: async transitions, timeouts, refusals, managed entities."""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Callable
from typing import Any

import pytest
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.context import Context
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Int64

from container import AsyncioExecutor
from container._errors import TransitionError
from container.lifecycle._node import LifecycleNode
from tests.lifecycle_support import TransitionLog, run
from tests.waiting import wait_until_async

SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE



class Gate(LifecycleNode):
    """Configure waits on an asyncio event the test (or another node) sets."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.release: asyncio.Event | None = None
        self.entered = 0

    async def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.entered += 1
        self.release = asyncio.Event()
        await self.release.wait()
        return SUCCESS

    async def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        await asyncio.Event().wait()  # never finishes
        return SUCCESS


def test_async_configure_keeps_other_nodes_running(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    gate: Gate = host(Gate, "gate")
    ticker = host(Node, "ticker")
    ticks: list[float] = []

    async def tick() -> None:
        # Only another node's timer can open the gate: a stalled loop never does.
        if gate.release is not None:
            ticks.append(time.monotonic())
            if len(ticks) == 20:
                gate.release.set()

    ticker.create_timer(0.01, tick)

    assert run(executor, gate.transition("configure"))
    assert gate.lifecycle_state.label == "inactive"
    assert len(ticks) >= 20
    assert max(b - a for a, b in itertools.pairwise(ticks)) < 0.25


def test_transition_past_its_timeout_fails_back_to_start_state(
    executor: AsyncioExecutor, host: Callable[..., Any], context: Context
) -> None:
    gate: Gate = host(
        Gate, "slow", parameter_overrides=[Parameter("transition_timeout", value=0.3)]
    )
    observer = host(Node, "observer")
    log = TransitionLog(observer, ["/slow"])

    def pending_release() -> asyncio.Event | None:
        """The event the gate's callback waits on, once it waits (set by that callback)."""
        return gate.release

    async def scenario() -> tuple[bool, float, bool, bool]:
        started = time.monotonic()
        configured = await gate.transition("configure")
        elapsed = time.monotonic() - started
        # The keyword wins over the parameter; the gate is opened from outside.
        gate.release = None
        second = asyncio.ensure_future(gate.transition("configure", timeout=5.0))
        while (release := pending_release()) is None:
            await asyncio.sleep(0.005)
        release.set()
        reconfigured = await second
        activated = await gate.transition("activate", timeout=0.2)
        return configured, elapsed, reconfigured, activated

    configured, elapsed, reconfigured, activated = run(executor, scenario())
    assert not configured
    assert 0.3 <= elapsed < 2.0
    assert reconfigured
    assert not activated
    assert gate.lifecycle_state.label == "inactive"
    log.wait_for("/slow", "inactive", after=5)
    assert log.pairs("/slow") == [
        ("unconfigured", "configuring"),
        ("configuring", "unconfigured"),
        ("unconfigured", "configuring"),
        ("configuring", "inactive"),
        ("inactive", "activating"),
        ("activating", "inactive"),
    ]


class Plain(LifecycleNode):
    """Synchronous callbacks only, like an rclpy node."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.configured_in: str | None = None

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        import threading

        self.configured_in = threading.current_thread().name
        return SUCCESS


def test_unavailable_transition_answers_false_instead_of_raising(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    node: Plain = host(Plain, "refuser")
    caller = host(Node, "caller")
    change = caller.create_client(ChangeState, "/refuser/change_state")
    get = caller.create_client(GetState, "/refuser/get_state")

    async def scenario() -> list[bool]:
        while not (change.service_is_ready() and get.service_is_ready()):
            await asyncio.sleep(0.01)
        answers = []
        for transition in (
            Transition(id=Transition.TRANSITION_ACTIVATE),
            Transition(label="cleanup"),
            Transition(label="no_such_transition"),
        ):
            response = await change.call_async(ChangeState.Request(transition=transition))
            answers.append(response.success)
        answers.append(await node.transition("deactivate"))
        state = await get.call_async(GetState.Request())
        answers.append(state.current_state.label == "unconfigured")
        response = await change.call_async(ChangeState.Request(transition=Transition(label="configure")))
        answers.append(response.success)
        return answers

    assert run(executor, scenario()) == [False, False, False, False, True, True]
    assert node.lifecycle_state.label == "inactive"
    # Plain callbacks run off the event loop's thread.
    assert node.configured_in == "transition:on_configure"
    with pytest.raises(TransitionError, match="not available"):
        node.trigger_configure()


def test_synchronous_trigger_api_still_works_for_plain_callbacks(host: Callable[..., Any]) -> None:
    node: Plain = host(Plain, "sync_api")
    assert node.trigger_configure() == SUCCESS
    assert node.trigger_activate() == SUCCESS
    assert node.lifecycle_state.label == "active"
    assert node.trigger_shutdown() == SUCCESS
    assert node.lifecycle_state.label == "finalized"
    gate: Gate = host(Gate, "async_api")
    with pytest.raises(TransitionError, match="asynchronous"):
        gate.trigger_configure()
    assert gate.lifecycle_state.label == "unconfigured"


class Raiser(LifecycleNode):
    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.recover = SUCCESS
        self.errors: list[str] = []

    async def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        await asyncio.sleep(0)
        raise RuntimeError("device missing")

    async def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.errors.append(state.label)
        return self.recover


@pytest.mark.parametrize(("recover", "final"), [(SUCCESS, "unconfigured"), (FAILURE, "finalized")])
def test_exception_in_a_transition_runs_on_error(
    executor: AsyncioExecutor,
    host: Callable[..., Any],
    recover: TransitionCallbackReturn,
    final: str,
) -> None:
    node: Raiser = host(Raiser, "raiser")
    node.recover = recover
    observer = host(Node, "observer")
    log = TransitionLog(observer, ["/raiser"])
    log.wait_matched()
    assert not run(executor, node.transition("configure"))
    assert node.lifecycle_state.label == final
    assert node.errors == ["unconfigured"]
    log.wait_for("/raiser", final)
    assert log.pairs() == [
        ("unconfigured", "configuring"),
        ("configuring", "errorprocessing"),
        ("errorprocessing", final),
    ]


class Echoer(LifecycleNode):
    """Configure echoes a megabyte parameter: in a failure's reason, or in an exception's text."""

    value = "/dev/" + "a" * (1024 * 1024 - 5)

    def __init__(self, name: str, *, raises: bool, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.raises = raises

    async def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.raises:
            raise ValueError(f"cannot open {self.value}")
        return self.fail_transition(f"cannot open {self.value}")


@pytest.mark.parametrize("raises", [False, True], ids=["fail_transition", "raised"])
def test_a_failures_reason_is_bounded_whatever_it_echoes(
    executor: AsyncioExecutor, host: Callable[..., Any], raises: bool
) -> None:
    node: Echoer = host(Echoer, "echoer", raises=raises)
    assert not run(executor, node.transition("configure"))
    failure = node.last_failure
    assert failure is not None and len(failure) < 1000
    assert failure.endswith("… (1048588 characters)"), failure[-100:]


class Counter(LifecycleNode):
    """A managed timer publishing a count; on_activate does not call super()."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.publisher = self.create_publisher(Int64, "count", 10)
        self.timer = self.create_timer(0.02, self._tick)
        self.ticks = 0
        self.clock_ticks = 0
        self.create_timer(0.02, self._measure, managed=False)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return SUCCESS

    async def _tick(self) -> None:
        self.ticks += 1
        self.publisher.publish(Int64(data=self.ticks))

    async def _measure(self) -> None:
        self.clock_ticks += 1


def test_managed_publisher_and_timer_follow_the_state(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    node: Counter = host(Counter, "counter")
    sink = host(Node, "sink")
    heard: list[int] = []
    sink.create_subscription(Int64, "/count", lambda msg: heard.append(msg.data), 100)

    async def clock_ticks(count: int) -> None:
        """Let the always-on timer fire ``count`` times: time passes, measured by the node."""
        target = node.clock_ticks + count
        while node.clock_ticks < target:
            await asyncio.sleep(0.005)

    async def heard_at_least(count: int) -> None:
        while len(heard) < count:
            await asyncio.sleep(0.005)

    async def scenario() -> dict[str, Any]:
        seen: dict[str, Any] = {}
        await clock_ticks(10)
        seen["unconfigured"] = node.ticks
        assert await node.transition("configure")
        await clock_ticks(10)
        seen["inactive"] = node.ticks
        assert await node.transition("activate")
        await heard_at_least(5)
        assert await node.transition("deactivate")
        frozen = node.ticks
        node.publisher.publish(Int64(data=-1))
        heard_before = len(heard)
        await clock_ticks(15)
        seen["deactivated"] = (frozen, node.ticks, heard_before, len(heard), -1 in heard)
        assert await node.transition("activate")
        await heard_at_least(len(heard) + 3)
        seen["reactivated"] = node.ticks > frozen
        return seen

    seen = run(executor, scenario())
    assert seen["unconfigured"] == 0
    assert seen["inactive"] == 0
    frozen, later, heard_before, heard_after, published_inactive = seen["deactivated"]
    assert later == frozen
    assert heard_after - heard_before <= 1  # at most one message still in flight
    assert not published_inactive
    assert seen["reactivated"]


def test_heartbeats_are_published_with_the_node_name(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    bond = pytest.importorskip("bond.msg")
    node: Plain = host(Plain, "beating", heartbeat_period=0.05)
    quiet: Plain = host(Plain, "quiet", heartbeat_period=0.0)
    listener = host(Node, "listener")
    seen: list[Any] = []
    listener.create_subscription(bond.Status, "/bond", seen.append, 100)

    async def enough() -> None:
        while sum(1 for s in seen if s.id == "/beating") < 5:
            await asyncio.sleep(0.01)

    run(executor, enough(), timeout=10.0)
    mine = [s for s in seen if s.id == "/beating"]
    assert node.heartbeat is not None
    assert all(s.active and s.instance_id == node.heartbeat.instance_id for s in mine)
    assert mine[0].heartbeat_period == pytest.approx(0.05)
    assert quiet.heartbeat is None
    assert not any(s.id == "/quiet" for s in seen)


def test_heartbeats_go_out_only_while_something_listens(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    bond = pytest.importorskip("bond.msg")
    node: Plain = host(Plain, "lonely", heartbeat_period=0.05)
    heartbeat = node.heartbeat
    assert heartbeat is not None
    listener = host(Node, "ear")

    async def scenario() -> tuple[int, bool]:
        # Unheard, it stops (another test's listener may linger in discovery a moment).
        await wait_until_async(lambda: not heartbeat.beating, "the unheard heartbeat stopped")
        seen: list[Any] = []
        subscription = listener.create_subscription(bond.Status, "/bond", seen.append, 100)
        await wait_until_async(lambda: sum(1 for s in seen if s.id == "/lonely") >= 3, "3 heartbeats heard")
        listener.destroy_subscription(subscription)
        await wait_until_async(lambda: not heartbeat.beating, "the heartbeat stopped once unheard again")
        return len(seen), heartbeat.beating

    heard, after = run(executor, scenario(), timeout=15.0)
    assert heard >= 3
    assert not after
