"""Respawn: a container killed with ``kill -9`` and started again comes back with its nodes.

``ComposableNodeContainer(..., respawn=True)`` makes launch start the same
command line again when the container dies; launch_ros loads the nodes only
once. With the ``state_file`` parameter the container restores them itself:
started here as launch_ros starts it (the executable from the ament index,
``--ros-args -r __node:= -r __ns:= --params-file``), the nodes loaded through
the real ``load_node`` service, driven through ``change_state``, a parameter
set through ``set_parameters``; then ``kill -9``, the same command line again,
and everything checked through the services, as ``ros2 component list``,
``ros2 lifecycle get`` and ``ros2 param get`` would.

A process killed with ``kill -9`` stays in every peer's discovery until its
lease runs out (20 s): a request may go to it alone while the new process is
not discovered yet, so each call is repeated until answered.
"""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from composition_interfaces.srv import ListNodes
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.client import Client
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python

from container import AsyncioExecutor
from container._ament import PROJECT_PACKAGE
from container._statefile import read_state
from tests.component_support import ContainerClient
from tests.container_support import ContainerProcess
from tests.process_support import (
    LoggedProcess,
    composable_node_request,
    container_command,
    executable_in_package,
    launch_params_file,
    log_time,
)
from tests.waiting import wait_until

#: What the issue asks of a respawned container: its nodes back within this many seconds.
BACK_WITHIN_S = 5.0

CONTAINER = "/robot/my_container"


def answer(client: Client[Any, Any], request: Any, executor: AsyncioExecutor, *, deadline: float) -> Any:
    """Call until answered (a dead server may be the only one matched for a while), or fail at ``deadline``."""
    while True:
        future = client.call_async(request)
        executor.spin_until_future_complete(future, timeout_sec=max(0.0, min(0.25, deadline - time.monotonic())))
        if future.done():
            return future.result()
        client.remove_pending_request(future)
        if time.monotonic() >= deadline:
            raise AssertionError(f"no answer from {client.srv_name}")


def until(probe: Callable[[], Any], expected: Any, what: str, *, deadline: float) -> None:
    """Repeat ``probe`` (itself bounded by ``deadline``) until it returns ``expected``."""
    seen = None
    while time.monotonic() < deadline:
        seen = probe()
        if seen == expected:
            return
    raise AssertionError(f"{what}: {seen!r}, not {expected!r}, by the deadline")


def recorded(path: Path) -> dict[str, str | None]:
    state = read_state(path)
    return {} if state is None else {node.full_name: node.state for node in state.nodes}


def changed_message(path: Path) -> object:
    state = read_state(path)
    for node in state.nodes if state is not None else ():
        for parameter in node.changed_parameters:
            if node.full_name == "/demo/talker" and parameter.name == "message":
                return parameter.value
    return None


class Services:
    """The calls the check makes, through ``client_node``'s clients, each repeated until answered."""

    def __init__(self, node: Node, executor: AsyncioExecutor, container: str) -> None:
        self.node = node
        self.executor = executor
        self.container = container
        self.clients: dict[str, Client[Any, Any]] = {}

    def call(self, srv_type: type[Any], service: str, request: Any, *, deadline: float) -> Any:
        client = self.clients.get(service)
        if client is None:
            client = self.clients[service] = self.node.create_client(srv_type, service)
        return answer(client, request, self.executor, deadline=deadline)

    def nodes(self, *, deadline: float) -> list[tuple[int, str]]:
        service = f"{self.container}/_container/list_nodes"
        response = self.call(ListNodes, service, ListNodes.Request(), deadline=deadline)
        return list(zip(response.unique_ids, response.full_node_names, strict=True))

    def state(self, node: str, *, deadline: float) -> str:
        return str(self.call(GetState, f"{node}/get_state", GetState.Request(), deadline=deadline).current_state.label)

    def change(self, node: str, transition: int, *, deadline: float) -> bool:
        request = ChangeState.Request()
        request.transition.id = transition
        return bool(self.call(ChangeState, f"{node}/change_state", request, deadline=deadline).success)

    def parameters(self, node: str, names: list[str], *, deadline: float) -> list[Any]:
        values = self.call(
            GetParameters, f"{node}/get_parameters", GetParameters.Request(names=names), deadline=deadline
        ).values
        return [parameter_value_to_python(value) for value in values]


# Three container processes one after the other, about 6 s in all.
@pytest.mark.slow
def test_a_container_killed_and_respawned_restores_its_nodes_in_their_states_within_5_s(
    ament_prefix_path: str,
    client_node: Node,
    executor: AsyncioExecutor,
    tmp_path: Path,
) -> None:
    state_file = tmp_path / "state" / "my_container.json"
    # ComposableNodeContainer(name="my_container", namespace="robot", package="lifecycle_container",
    #     executable="component_container", parameters=[{"state_file": ...}], respawn=True, ...)
    params = launch_params_file(tmp_path, CONTAINER, {"state_file": str(state_file)})
    command = container_command(
        executable_in_package(PROJECT_PACKAGE, "component_container"), name="my_container", namespace="/robot",
        params_file=params,
    )
    first = LoggedProcess(command)
    try:
        first.wait_for_line(f"Container '{CONTAINER}' ready with 0 node(s)")
        client = ContainerClient(client_node, executor, CONTAINER, process=first)
        # The composable_node_descriptions, as launch_ros sends them.
        loads = [
            composable_node_request(
                package="lifecycle_container", plugin="lifecycle_container::Talker", name="talker",
                namespace="demo", remappings=[("chatter", "/respawn_chatter")],
                parameters={"rate": 20.0, "message": "From launch"},
            ),
            composable_node_request(
                package="lifecycle_container", plugin="lifecycle_container::Listener", name="listener",
                namespace="demo", remappings=[("chatter", "/respawn_chatter")],
            ),
            composable_node_request(
                package="lifecycle_container", plugin="lifecycle_container::Talker", name="spare", namespace="demo",
            ),
        ]
        for expected_id, request in enumerate(loads, start=1):
            response = client.load(request)
            assert (response.success, response.unique_id) == (True, expected_id), response.error_message
        assert client.unload(3).success  # its id is never handed out again
        services = Services(client_node, executor, CONTAINER)
        soon = time.monotonic() + 20.0
        for transition in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
            assert services.change("/demo/talker", transition, deadline=soon)
        assert services.change("/demo/listener", Transition.TRANSITION_CONFIGURE, deadline=soon)
        message = Parameter("message", value="Set at runtime").to_parameter_msg()
        set_message = services.call(
            SetParameters, "/demo/talker/set_parameters", SetParameters.Request(parameters=[message]), deadline=soon
        )
        assert set_message.results[0].successful
        wait_until(
            lambda: recorded(state_file) == {"/demo/talker": "active", "/demo/listener": "inactive"}
            and changed_message(state_file) == "Set at runtime",
            lambda: f"the state file to record it all: {recorded(state_file)}, {changed_message(state_file)!r}",
            timeout=10.0,
        )
        assert first.stop(sig=signal.SIGKILL) == -signal.SIGKILL
    finally:
        first.close()

    # launch's respawn: the same command line again.
    started, started_wall = time.monotonic(), time.time()
    second = LoggedProcess(command)
    try:
        deadline = started + BACK_WITHIN_S
        until(lambda: services.nodes(deadline=deadline), [(1, "/demo/talker"), (2, "/demo/listener")],
              "list_nodes", deadline=deadline)
        assert services.state("/demo/talker", deadline=deadline) == "active"
        assert services.state("/demo/listener", deadline=deadline) == "inactive"
        assert services.parameters("/demo/talker", ["rate", "message"], deadline=deadline) == [20.0, "Set at runtime"]
        back = time.monotonic() - started
        restored = second.wait_for_line("Restored 2 of the 2 node(s) of the state file in ")
        # Shown by pytest -rP: most of it is the process's start (Python, rclpy, plugins) and discovery.
        print(f"respawned: nodes restored {log_time(restored) - started_wall:.2f} s after the start, "
              f"seen back in their states through their services after {back:.2f} s")
        assert back < BACK_WITHIN_S, restored
        second.wait_for_line(f"Container '{CONTAINER}' ready with 2 node(s)")
        client = ContainerClient(client_node, executor, CONTAINER, process=second)
        # The launch file's load again (a launch started anew after the whole launch died):
        # answered with the restored node, which keeps its state and its parameters set since.
        again = client.load(loads[0])
        assert (again.success, again.unique_id, again.full_node_name) == (True, 1, "/demo/talker"), again.error_message
        assert services.state("/demo/talker", deadline=time.monotonic() + 5.0) == "active"
        # A new load after the respawn: no id collides.
        late = composable_node_request(
            package="lifecycle_container", plugin="lifecycle_container::Listener", name="late", namespace="demo"
        )
        assert client.load(late).unique_id == 4
        # A clean stop (launch shutting down: SIGINT) takes the nodes down and the state file with them.
        assert second.stop(sig=signal.SIGINT) == 0
        assert not state_file.exists()
        assert f"State file '{state_file}' removed: a clean shutdown" in second.output(last=100)
    finally:
        second.close()

    third = LoggedProcess(command)
    try:
        third.wait_for_line(f"Container '{CONTAINER}' ready with 0 node(s)")
    finally:
        third.close()


# Two container processes one after the other.
@pytest.mark.slow
def test_container_run_with_a_file_restarted_after_kill_9_loads_the_files_nodes_again(
    run_container: Callable[..., ContainerProcess], client_node: Node, executor: AsyncioExecutor
) -> None:
    text = (
        "nodes:\n"
        "  - {package: lifecycle_container, plugin: Talker, name: talker, autostart: true}\n"
        "  - {package: lifecycle_container, plugin: Listener, name: listener}\n"
    )
    first = run_container(text)
    assert first.stop(sig=signal.SIGKILL) == -signal.SIGKILL
    second = ContainerProcess(first.config)
    try:
        second.wait_for_line("Container '/ComponentManager' ready with 2 node(s)")
        services = Services(client_node, executor, "/ComponentManager")
        deadline = time.monotonic() + 20.0
        assert services.nodes(deadline=deadline) == [(1, "/talker"), (2, "/listener")]
        assert services.state("/talker", deadline=deadline) == "active"
        assert services.state("/listener", deadline=deadline) == "unconfigured"
    finally:
        second.close()
