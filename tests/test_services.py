"""Container services from another process: load, list, unload, and every refusal.

The container runs as ``container run`` in a child process; this process is
the client, over DDS, exactly like ``ros2 component``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
from composition_interfaces.srv import LoadNode
from lifecycle_msgs.srv import GetState
from rcl_interfaces.srv import GetParameters
from rclpy.client import Client
from rclpy.node import Node

from container import AsyncioExecutor
from tests.component_support import (
    ContainerClient,
    graph_nodes,
    load_request,
    parameter,
)
from tests.container_support import ContainerProcess
from tests.waiting import wait_until

EMPTY = "container:\n  name: ComponentManager\n"


@pytest.fixture
def container(run_container: Callable[..., ContainerProcess], see_plugin: Callable[..., None]) -> ContainerProcess:
    """An empty ``container run`` that also sees the ``test-nodes`` plugin."""
    see_plugin()
    return run_container(EMPTY)


@pytest.fixture
def client(container: ContainerProcess, client_node: Node, executor: AsyncioExecutor) -> ContainerClient:
    return ContainerClient(client_node, executor, process=container)


def test_load_list_unload_round_trip(
    client: ContainerClient, client_node: Node, executor: AsyncioExecutor
) -> None:
    response = client.load(load_request())
    assert (response.success, response.error_message) == (True, "")
    assert (response.unique_id, response.full_node_name) == (1, "/talker")
    assert client.list() == [(1, "/talker")]
    wait_until(lambda: "/talker" in graph_nodes(client_node), "/talker in the graph", timeout=20.0, executor=executor)

    response = client.unload(1)
    assert (response.success, response.error_message) == (True, "")
    assert client.list() == []
    wait_until(
        lambda: "/talker" not in graph_nodes(client_node),
        lambda: f"/talker gone from the graph: {sorted(graph_nodes(client_node))}",
        timeout=20.0,
        executor=executor,
    )


def test_load_honours_name_namespace_remaps_parameters_and_extras(
    client: ContainerClient, client_node: Node, executor: AsyncioExecutor
) -> None:
    response = client.load(
        load_request(
            plugin="lifecycle_container::Listener",
            name="ear",
            namespace="demo",
            remap_rules=["chatter:=/elsewhere"],
            extra_arguments=[parameter("use_intra_process_comms", True)],
            log_level=10,
        )
    )
    assert response.success, response.error_message
    assert response.full_node_name == "/demo/ear"
    wait_until(
        lambda: "/demo/ear" in graph_nodes(client_node)
        and any(
            topic == "/elsewhere"
            for topic, _ in client_node.get_subscriber_names_and_types_by_node("ear", "/demo")
        ),
        "the remapped subscription in the graph",
        timeout=20.0,
        executor=executor,
    )

    response = client.load(
        load_request(name="speaker", parameters=[parameter("message", "Remote"), parameter("rate", 7.5)])
    )
    assert response.success, response.error_message
    get: Client[Any, Any] = client_node.create_client(GetParameters, "/speaker/get_parameters")
    assert get.wait_for_service(timeout_sec=20.0)
    values = client.call(get, GetParameters.Request(names=["message", "rate"])).values
    assert (values[0].string_value, values[1].double_value) == ("Remote", 7.5)


def test_unique_ids_count_from_one_and_are_never_reused(client: ContainerClient) -> None:
    ids = []
    for _ in range(3):
        response = client.load(load_request(name="again"))
        assert response.success, response.error_message
        ids.append(response.unique_id)
        assert client.unload(response.unique_id).success
    assert ids == [1, 2, 3]


#: (what is wrong, request, words the error message must contain)
BAD_LOADS = [
    ("unknown package", load_request("no_such_package", "no_such_package::X"),
     "Could not find requested resource in ament index"),
    ("unknown type", load_request(plugin="lifecycle_container::NoSuchType"),
     "Failed to find class with the requested plugin name."),
    ("type of another package", load_request(plugin="test_nodes::Busy"),
     "Failed to find class with the requested plugin name."),
    ("constructor that raises", load_request("test_nodes", "test_nodes::Exploding"),
     "Component constructor threw an exception: RuntimeError: boom from the constructor"),
    ("duplicate name", load_request(name="first"), "'/first' is already loaded (unique_id 1)"),
    ("duplicate through remap", load_request(name="other", remap_rules=["__node:=first"]),
     "'/first' is already loaded"),
    ("the container's own name", load_request(name="ComponentManager"), "is the container itself"),
    ("parameter of the wrong type", load_request(name="typed", parameters=[parameter("rate", "fast")]),
     "InvalidParameterTypeException"),
    ("extra argument of the wrong type",
     load_request(name="extra", extra_arguments=[parameter("use_intra_process_comms", 1)]),
     "Extra component argument 'use_intra_process_comms' must be a boolean"),
    ("forward_global_arguments of the wrong type",
     load_request(name="extra", extra_arguments=[parameter("forward_global_arguments", "no")]),
     "Extra component argument 'forward_global_arguments' must be a boolean"),
    ("duplicate through a node-specific remap",
     load_request(name="talker", remap_rules=["talker:__node:=first"]), "'/first' is already loaded"),
    ("invalid node name", load_request(name="not a name!"), "Invalid node name"),
    ("invalid namespace", load_request(name="ok", namespace="/bad//ns"),
     "Invalid namespace '/bad//ns': namespace must not contain repeated '/'"),
    ("empty parameter name", load_request(name="p1", parameters=[parameter("", 1)]),
     "Invalid parameters: parameter name '' must not be empty"),
    ("parameter name with '..' and '//'", load_request(name="p2", parameters=[parameter("a..b//c", 1)]),
     "Invalid parameters: parameter name 'a..b//c' must be words"),
    ("invalid remap rule", load_request(name="remapped", remap_rules=["nonsense"]), "Invalid remap rule"),
    ("invalid log level", load_request(name="logged", log_level=7), "Invalid log_level 7"),
]


def test_every_bad_request_is_refused_and_the_container_keeps_serving(
    client: ContainerClient, container: ContainerProcess
) -> None:
    first = client.load(load_request(name="first"))
    assert (first.success, first.unique_id) == (True, 1)
    good_ids = [1]
    for index, (what, request, message) in enumerate(BAD_LOADS):
        response = client.load(request)
        assert not response.success, f"{what}: loaded as {response.full_node_name}"
        assert message in response.error_message, f"{what}: {response.error_message!r}"
        assert (response.unique_id, response.full_node_name) == (0, ""), what
        # Still serving: the next good request succeeds.
        good = client.load(load_request(name=f"good{index}"))
        assert good.success, f"after {what}: {good.error_message}"
        good_ids.append(good.unique_id)
    # Refusals use no unique id.
    assert good_ids == list(range(1, len(BAD_LOADS) + 2))
    assert [uid for uid, _ in client.list()] == good_ids
    assert container.process.poll() is None


def test_unknown_extra_arguments_are_ignored_and_logged_once_as_rclcpp_does(
    client: ContainerClient, container: ContainerProcess
) -> None:
    start = len(container.lines)
    for name in ("extra1", "extra2"):
        response = client.load(load_request(name=name, extra_arguments=[parameter("enable_rosout", False)]))
        # Each answer says so (the answer's warnings, see below); the log, once.
        assert (response.success, response.error_message) == (
            True,
            "[WARN] [ComponentManager]: Extra component argument 'enable_rosout' is not used by this container: "
            "ignored (as rclcpp's container does)",
        )
    container.wait_for_line("Loaded lifecycle_container::Talker as '/extra2'", start=start)
    ignored = [line for line in container.lines[start:] if "'enable_rosout' is not used by this container" in line]
    assert len(ignored) == 1, container.lines[start:]


def test_a_successful_answer_carries_the_warnings_its_load_caused(
    client: ContainerClient, container: ContainerProcess
) -> None:
    # rclcpp leaves error_message empty on success; here it holds the
    # warnings, one line each, as the container's log shows them.
    clean = client.load(load_request(name="clean", parameters=[parameter("rate", 5.0)]))
    assert (clean.success, clean.error_message) == (True, "")

    # A typo of what the constructor declared: told at load, before configure.
    typo = client.load(load_request(name="typo", parameters=[parameter("rat", 5.0)]))
    assert typo.success
    assert typo.error_message == (
        "[WARN] [typo]: Unknown parameter 'rat' ignored: this node does not read it (did you mean 'rate'?)"
    )
    container.wait_for_line("[typo]: Unknown parameter 'rat' ignored")

    # A name nothing is close to waits for configure: an autostart's is in the answer.
    started = client.load(load_request(
        name="started",
        parameters=[parameter("rat", 5.0), parameter("zzz_unrelated", 1)],
        extra_arguments=[parameter("autostart", True)],
    ))
    assert started.success
    assert started.error_message.splitlines() == [
        "[WARN] [started]: Unknown parameter 'rat' ignored: this node does not read it (did you mean 'rate'?)",
        "[WARN] [started]: Unknown parameter 'zzz_unrelated' ignored: this node does not read it",
    ]
    container.wait_for_line("[started]: Unknown parameter 'zzz_unrelated' ignored")
    # Each logged once: configure does not repeat what the load told.
    assert sum("[started]: Unknown parameter 'rat'" in line for line in container.lines) == 1, container.output()

    # A failed autostart's answer says why first, then the warnings.
    failed = client.load(load_request(
        name="failed",
        parameters=[parameter("rate", -1.0), parameter("mesage", "hi")],
        extra_arguments=[parameter("autostart", True)],
    ))
    assert not failed.success
    first, *warnings = failed.error_message.splitlines()
    assert first.startswith("Loaded as unique_id 4 but autostart failed: "), failed.error_message
    assert warnings == [
        "[WARN] [failed]: Unknown parameter 'mesage' ignored: this node does not read it (did you mean 'message'?)"
    ]


def test_unknown_unique_id_is_refused_with_rclcpp_wording(client: ContainerClient) -> None:
    response = client.unload(42)
    assert (response.success, response.error_message) == (False, "No node found with unique_id: 42")
    loaded = client.load(load_request())
    assert client.unload(loaded.unique_id).success
    again = client.unload(loaded.unique_id)
    assert (again.success, again.error_message) == (
        False,
        f"No node found with unique_id: {loaded.unique_id}",
    )
    assert client.load(load_request()).success


def test_unload_takes_the_node_down_its_lifecycle(
    client: ContainerClient, container: ContainerProcess
) -> None:
    loaded = client.load(load_request("test_nodes", "test_nodes::Busy"))
    assert loaded.success, loaded.error_message
    start = len(container.lines)
    assert client.unload(loaded.unique_id).success
    unloaded = container.wait_for_line("Unloaded '/busy'", start=start)
    shutdown = container.wait_for_line("[busy]: shutting down from unconfigured", start=start)
    assert container.lines.index(shutdown) < container.lines.index(unloaded)
    assert client.list() == []


def test_autostart_extra_argument_brings_the_node_to_active(
    client: ContainerClient, client_node: Node
) -> None:
    response = client.load(load_request(name="started", extra_arguments=[parameter("autostart", True)]))
    assert (response.success, response.error_message) == (True, "")
    get_state: Client[Any, Any] = client_node.create_client(GetState, "/started/get_state")
    assert get_state.wait_for_service(timeout_sec=20.0)
    assert client.call(get_state, GetState.Request()).current_state.label == "active"

    # One that cannot come up stays loaded where it stopped, and the answer says so.
    failed = client.load(load_request(
        name="failing", parameters=[parameter("rate", -1.0)], extra_arguments=[parameter("autostart", True)]
    ))
    assert not failed.success
    assert (failed.unique_id, failed.full_node_name) == (2, "/failing")
    assert failed.error_message.startswith("Loaded as unique_id 2 but autostart failed: "), failed.error_message
    assert client.list() == [(1, "/started"), (2, "/failing")]
    assert client.unload(2).success


# A load test: 500 requests in flight; answers awaited up to 120 s.
@pytest.mark.slow
@pytest.mark.timeout(150)
def test_a_burst_of_requests_is_answered_to_the_last(
    container: ContainerProcess, client_node: Node, executor: AsyncioExecutor
) -> None:
    # Five callers with 100 LoadNode requests each in flight at once, as the
    # rclpy clients of ros2 component or launch_ros make them (default QoS):
    # every one gets its answer. Nine in ten name no plugin (refused at
    # once); one in ten loads a Talker of its own name.
    clients: list[Client[Any, Any]] = [
        client_node.create_client(LoadNode, "/ComponentManager/_container/load_node") for _ in range(5)
    ]
    for caller in clients:
        assert caller.wait_for_service(timeout_sec=20.0)
    futures = []
    for index in range(100):
        for number, caller in enumerate(clients):
            loads = index % 10 == 0
            request = (
                load_request(name=f"burst_{number}_{index}")
                if loads
                else load_request("no_such_package", "no_such_package::X")
            )
            futures.append((loads, caller.call_async(request)))

    wait_until(
        lambda: all(f.done() for _, f in futures),
        lambda: f"every call answered: {sum(f.done() for _, f in futures)} of {len(futures)}\n{container.output()}",
        timeout=120.0,
        executor=executor,
    )
    results: list[tuple[bool, Any]] = [(loads, f.result()) for loads, f in futures]
    assert all(r.success for loads, r in results if loads)
    assert all(
        r.error_message == "Could not find requested resource in ament index" for loads, r in results if not loads
    )
    ids = sorted(r.unique_id for loads, r in results if loads)
    assert ids == list(range(1, 51))
