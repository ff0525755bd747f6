"""A hosted lifecycle node's standard services: every caller answered, as rclpy's own answer.

rcl's lifecycle services keep the last 10 requests: 20 ``change_state``
callers at once, with rclpy's default client QoS, got 10 to 20 answers. The
node serves them itself, keep-all, its answers paced (every client receives
every answer, and keeps its last 10); these tests call them over DDS from
clients with the default QoS, as ``ros2 lifecycle`` and launch_ros do.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetAvailableStates, GetAvailableTransitions, GetState
from rclpy.client import Client
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode as RclpyLifecycleNode
from rclpy.node import Node
from rclpy.task import Future

from container import LifecycleNode
from container._compat import state_machine
from container.testing import ContainerHost
from tests.container_support import ContainerProcess
from tests.lifecycle_support import TransitionLog
from tests.waiting import wait_until, wait_until_async

pytestmark = pytest.mark.timeout(60)

CALLERS = 20

#: Each burst's transition, and the state it leads to from the one before.
BURSTS = [("configure", "inactive"), ("cleanup", "unconfigured")] * 4

QUERIES: dict[str, type[Any]] = {
    "get_state": GetState,
    "get_available_states": GetAvailableStates,
    "get_available_transitions": GetAvailableTransitions,
    "get_transition_graph": GetAvailableTransitions,
}
LIFECYCLE_SERVICES = {"change_state", *QUERIES}

BURST_CONTAINER = """
nodes:
  - {package: lifecycle_container, plugin: lifecycle_container::Talker, name: burst}
"""


async def _ready(*clients: Client[Any, Any]) -> None:
    await wait_until_async(
        lambda: all(client.service_is_ready() for client in clients),
        lambda: f"{sum(not c.service_is_ready() for c in clients)} of {len(clients)} services available",
    )


async def _answers(futures: list[Future[Any]], what: str) -> list[Any]:
    await wait_until_async(
        lambda: all(future.done() for future in futures),
        lambda: f"answers to {what}: {sum(future.done() for future in futures)} of {len(futures)} came",
    )
    return [future.result() for future in futures]


@contextlib.contextmanager
def _spun(node: Node) -> Iterator[Node]:
    """``node`` spun by rclpy's own executor on a thread of its own, as a tool's would be."""
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, name="callers", daemon=True)
    spinner.start()
    try:
        yield node
    finally:
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)
        node.destroy_node()


def _answered(futures: list[Future[Any]], what: str) -> list[Any]:
    wait_until(
        lambda: all(future.done() for future in futures),
        lambda: "answers to " + what + ": " + "".join("x" if future.done() else "." for future in futures),
    )
    return [future.result() for future in futures]


# A container process, so that its answers reach the callers on DDS's
# schedule, not interleaved with the callers' own work as in one process.
def test_every_change_state_caller_of_a_burst_is_answered(
    run_container: Callable[..., ContainerProcess], context: Context
) -> None:
    container = run_container(BURST_CONTAINER)
    with _spun(Node("callers", context=context)) as callers_node:
        # A client each, with rclpy's default QoS (keep-last 10), as twenty
        # tools would call; each receives all twenty answers (DDS sends every
        # client of a service every answer) and keeps the last ten it has not taken.
        callers: list[Client[Any, Any]] = [
            callers_node.create_client(ChangeState, "/burst/change_state") for _ in range(CALLERS)
        ]
        get_state: Client[Any, Any] = callers_node.create_client(GetState, "/burst/get_state")
        events = TransitionLog(callers_node, ["/burst"])
        wait_until(
            lambda: all(caller.service_is_ready() for caller in (get_state, *callers)),
            lambda: f"the services of /burst\n{container.output()}",
        )
        events.wait_matched()

        for burst, (label, goal) in enumerate(BURSTS):
            before = len(events)
            # All sent at once: the service's request history holds them all.
            futures = [caller.call_async(ChangeState.Request(transition=Transition(label=label))) for caller in callers]
            answers = _answered(futures, f"burst {burst} ({label!r})\n{container.output()}")

            # Transitions never overlap: the first taken moves the node, the
            # other 19 find it where the transition is no longer available.
            assert [answer.success for answer in answers].count(True) == 1, f"burst {burst}"
            # Matched on this side is not matched on the container's: its volatile
            # writer may publish the first burst's events before it has discovered
            # this reader (under load, it did). Later bursts' events cannot miss it.
            if burst > 0:
                events.wait_for("/burst", goal, after=before)
            state = _answered([get_state.call_async(GetState.Request())], "get_state")[0]
            assert state.current_state.label == goal, f"burst {burst}"

        # One transition per burst on transition_event, each through its transition state.
        starts = {"configure": "unconfigured", "cleanup": "inactive"}
        middles = {"configure": "configuring", "cleanup": "cleaningup"}
        expected = [
            step for label, goal in BURSTS for step in ((starts[label], middles[label]), (middles[label], goal))
        ]
        seen = events.pairs("/burst")
        # All of them, but for what the first burst published before the writer matched.
        assert seen in (expected, expected[1:], expected[2:]), seen


async def test_the_standard_services_are_rclpy_s_names_types_and_answers(container_host: ContainerHost) -> None:
    ours = await container_host.load("lifecycle_container::Talker", name="ours", autostart=False)
    theirs = RclpyLifecycleNode("theirs", context=container_host.client.context)
    container_host.executor.add_node(theirs)
    client = container_host.client
    try:

        def lifecycle_services(name: str) -> dict[str, list[str]]:
            graph = client.get_service_names_and_types_by_node(name, "/")
            return {service: types for service, types in graph if service.rpartition("/")[2] in LIFECYCLE_SERVICES}

        await wait_until_async(
            lambda: len(lifecycle_services("ours")) == len(lifecycle_services("theirs")) == len(LIFECYCLE_SERVICES),
            lambda: f"the lifecycle services of /ours and /theirs: {lifecycle_services('ours')}, "
            f"{lifecycle_services('theirs')}",
        )
        assert lifecycle_services("ours") == {
            service.replace("/theirs/", "/ours/"): types for service, types in lifecycle_services("theirs").items()
        }

        clients: dict[tuple[str, str], Client[Any, Any]] = {
            (name, query): client.create_client(srv_type, f"/{name}/{query}")
            for name in ("ours", "theirs")
            for query, srv_type in QUERIES.items()
        }
        await _ready(*clients.values())
        for step in ("unconfigured", "configure", "activate"):
            if step != "unconfigured":
                await container_host.transition(ours, step)
                getattr(theirs, f"trigger_{step}")()
            for query, srv_type in QUERIES.items():
                answers = await _answers(
                    [clients[name, query].call_async(srv_type.Request()) for name in ("ours", "theirs")],
                    f"{query} after {step}",
                )
                assert answers[0] == answers[1], f"{query} after {step}"
        assert answers[0].available_transitions, "the transition graph is not empty"
    finally:
        container_host.executor.remove_node(theirs)
        theirs.destroy_node()
        state_machine(theirs).destroy_when_not_in_use()


async def test_a_node_without_the_services_still_publishes_transition_events(container_host: ContainerHost) -> None:
    node = LifecycleNode("quiet", context=container_host.client.context, enable_communication_interface=False)
    container_host.executor.add_node(node)
    client: Node = container_host.client
    events = TransitionLog(client, ["/quiet"])
    try:
        await events.wait_matched_async()

        def services() -> set[str]:
            graph = client.get_service_names_and_types_by_node("quiet", "/")
            return {service.rpartition("/")[2] for service, _ in graph}

        # Its parameter services are discovered; no lifecycle service is there.
        await wait_until_async(lambda: "set_parameters" in services(), lambda: f"the services of /quiet: {services()}")
        assert not services() & LIFECYCLE_SERVICES

        assert await node.transition("configure")
        await events.wait_for_async("/quiet", "inactive")
        assert events.pairs("/quiet") == [("unconfigured", "configuring"), ("configuring", "inactive")]
    finally:
        container_host.executor.remove_node(node)
        node.destroy_node()
        state_machine(node).destroy_when_not_in_use()
