"""``container run``: a real process hosting the demo nodes, and its shutdown."""

from __future__ import annotations

import itertools
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from composition_interfaces.srv import ListNodes
from lifecycle_msgs.srv import GetState
from rcl_interfaces.srv import GetParameters
from rclpy.client import Client
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from container import AsyncioExecutor
from tests.component_support import ContainerClient, load_request, parameter
from tests.container_support import REPO, ContainerProcess
from tests.process_support import LoggedProcess
from tests.waiting import wait_until

DEMO = """
nodes:
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: talker
    parameters: [{rate: 20.0}]
    autostart: true
  - package: lifecycle_container
    plugin: lifecycle_container::Listener
    name: listener
    autostart: true
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_container_runs_demo_and_exits_cleanly_on_signal(
    run_container: Callable[..., ContainerProcess], sig: signal.Signals
) -> None:
    proc = run_container(DEMO)
    proc.wait_for_line("I heard: [Hello World:")
    code = proc.stop(sig=sig)
    output = "\n".join(proc.lines)
    assert code == 0, output
    # Unloaded through their lifecycle, last loaded first.
    assert output.index("Unloaded '/listener'") < output.index("Unloaded '/talker'")
    assert "threads left behind" not in output


def test_failed_entries_are_named_and_summed_up_and_the_rest_still_runs(
    run_container: Callable[..., ContainerProcess], see_plugin: Callable[..., None]
) -> None:
    see_plugin()  # test_nodes::Exploding
    proc = run_container(
        DEMO
        + """
  - package: no_such_package
    plugin: no_such_package::Nothing
  - package: test_nodes
    plugin: test_nodes::Exploding
    name: boom
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: typo
    parameters: [{rat: 5.0}]
    autostart: true
"""
    )
    proc.wait_for_line(
        "Could not start nodes[2] (type: no_such_package::Nothing): Could not find requested resource in ament index"
    )
    proc.wait_for_line("Could not start nodes[3] (name: boom): Component constructor threw an exception")
    # The constructor's traceback, trimmed to the plugin's own frames.
    proc.wait_for_line('component_support.py", line')
    assert not any("rclpy/node.py" in line for line in proc.lines), proc.output()
    proc.wait_for_line(
        "2 of the 5 node(s) the file lists failed: nodes[2] (type: no_such_package::Nothing), nodes[3] (name: boom)"
    )
    proc.wait_for_line("[typo]: Unknown parameter 'rat' ignored: this node does not read it (did you mean 'rate'?)")
    proc.wait_for_line("I heard: [Hello World:")
    assert proc.stop() == 0, proc.output()


def test_the_summary_at_ready_repeats_the_warnings_of_the_files_loads(
    run_container: Callable[..., ContainerProcess],
) -> None:
    proc = run_container(
        DEMO
        + """
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: typo
    parameters: [{rat: 5.0}]
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: started
    parameters: [{mesage: hi}]
    autostart: true
"""
    )
    ready = proc.lines.index(proc.wait_for_line("ready with 4 node(s)"))
    # After ready, in load order: a typo of what the constructor declared
    # (no configure needed), and one an autostart's configure found.
    proc.wait_for_line("2 warning(s) while loading the file's nodes:", start=ready)
    summary = proc.wait_for_line("nodes[2] (name: typo) [typo]: Unknown parameter 'rat'", start=ready)
    assert summary.endswith("ignored: this node does not read it (did you mean 'rate'?)"), summary
    proc.wait_for_line(
        "nodes[3] (name: started) [started]: Unknown parameter 'mesage' ignored: this node does not read it "
        "(did you mean 'message'?)",
        start=ready,
    )
    # Still in the log as they happened, each once.
    assert sum("[typo]: Unknown parameter 'rat'" in line for line in proc.lines[:ready]) == 1, proc.output()
    assert proc.stop() == 0, proc.output()


def test_on_failure_exit_takes_the_container_down_with_exit_1(
    run_container: Callable[..., ContainerProcess],
) -> None:
    proc = run_container(
        "container: {on_failure: exit}\n"
        + DEMO
        + "  - {package: no_such_package, plugin: no_such_package::Nothing, name: missing}\n",
        ready=False,
    )
    assert proc.process.wait(30) == 1, proc.output()
    proc.close()
    output = "\n".join(proc.lines)
    assert "1 of the 3 node(s) the file lists failed: nodes[2] (name: missing) (on_failure: exit" in output
    # What did load went down its lifecycle first.
    ready = output.index("ready with 2 node(s)")
    assert ready < output.index("Unloaded '/listener'") < output.index("Unloaded '/talker'")


def test_parameters_from_a_ros_parameter_file(
    run_container: Callable[..., ContainerProcess], tmp_path: Path
) -> None:
    params = tmp_path / "params.yaml"
    params.write_text("talker:\n  ros__parameters:\n    message: From the file\n", encoding="utf-8")
    proc = run_container(
        f"""
nodes:
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: talker
    parameters: [{{rate: 20.0}}, {params}]
    autostart: true
  - package: lifecycle_container
    plugin: lifecycle_container::Listener
    autostart: true
"""
    )
    proc.wait_for_line("I heard: [From the file:")
    assert proc.stop() == 0, proc.output()


#: Ten levels of nine aliases each: 449 bytes that a plain YAML load expands
#: to 9**10 (3.5 billion) strings.
BILLION_LAUGHS = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n' + "".join(
    f"{name}: &{name} [{', '.join([f'*{previous}'] * 9)}]\n" for previous, name in itertools.pairwise("abcdefghij")
)


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ("nodes:\n  - package: a\n    plugin: a::B\n    nmae: typo\n", "unknown key(s) 'nmae'"),
        ("nodes:\n  - plugin: a::B\n", "missing 'package'"),
        ("container:\n  reentrant_limit: 0\n", "must be >= 1, not 0"),
        ("nodes: [\n", "not valid YAML"),
        ("nodes:\n  - {package: a, plugin: b, remappings: [[x]]}\n", "remappings[0]"),
        ("container:\n  name: 'bad name'\n", "container.name: not a valid node name"),
        ("container:\n  namespace: '/bad//ns'\n", "container.namespace: not a valid namespace"),
        ("container:\n  parameters: [missing.yaml]\n", "missing.yaml: cannot read"),
        ("container:\n  unload_timeout: .nan\n", "container.unload_timeout: must be a finite number"),
        ("container:\n  unload_timeout: .inf\n", "container.unload_timeout: must be a finite number"),
        ("container:\n  load_timeout: -1\n", "container.load_timeout: must be positive"),
        ("container:\n  watchdog_threshold: 0\n", "container.watchdog_threshold: must be positive"),
        ("container:\n  on_failure: stop\n", "container.on_failure: expected one of continue, exit, not 'stop'"),
        ("nodes: []\nnodes: []\n", "key 'nodes' appears twice (line 2"),
        ("a: &a [*a]\n", "an alias refers to itself"),
        (BILLION_LAUGHS, "expands to more than 100,000 values"),
        (b"container:\n  name: caf\xe9\n", "not UTF-8 text"),
        ("# " + "x" * (1 << 20) + "\n", "larger than 1024 KiB"),
    ],
)
def test_invalid_config_is_refused_with_its_place(tmp_path: Path, config: str | bytes, message: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_bytes(config if isinstance(config, bytes) else config.encode("utf-8"))
    result = subprocess.run(
        [sys.executable, "-m", "container", "run", str(path)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2, result.stderr
    assert message in result.stderr
    assert "Traceback" not in result.stderr


def test_without_a_file_an_empty_container_takes_its_ros_arguments_like_rclcpps(
    client_node: Node, executor: AsyncioExecutor
) -> None:
    proc = LoggedProcess([
        sys.executable, "-m", "container", "run",
        "--use_multi_threaded_executor",  # rclcpp's component_container_isolated's
        "--ros-args", "-r", "__node:=named", "-r", "__ns:=/ns", "-p", "use_sim_time:=true", "-p", "thread_num:=2",
        "-r", "chatter:=/global_chatter", "--",
        "--verbose",  # after "--": the command's own again
    ])
    try:
        proc.wait_for_line("Container '/ns/named' ready with 0 node(s)")
        client = ContainerClient(client_node, executor, "/ns/named")
        get: Client[Any, Any] = client_node.create_client(GetParameters, "/ns/named/get_parameters")
        assert get.wait_for_service(timeout_sec=20.0)
        values = client.call(get, GetParameters.Request(names=["use_sim_time", "thread_num"])).values
        # thread_num is declared, as component_container_mt's, and takes -p.
        assert (values[0].bool_value, values[1].integer_value) == (True, 2)
        # The container's ROS arguments are its own; a load forwards them only when asked.
        forward = [parameter("forward_global_arguments", True)]
        plain = client.load(load_request(plugin="lifecycle_container::Listener", name="plain"))
        assert plain.full_node_name == "/plain", plain.error_message
        # All of them: -r __node:=named renames a forwarded node too (rclcpp warns of it).
        clash = client.load(load_request(plugin="lifecycle_container::Listener", extra_arguments=forward))
        assert "A node named '/ns/named' is the container itself" in clash.error_message
        # The request's own rules come first, as the node's local arguments do in rcl.
        forwarded = client.load(load_request(
            plugin="lifecycle_container::Listener", remap_rules=["__node:=forwarded"], extra_arguments=forward,
        ))
        assert forwarded.full_node_name == "/ns/forwarded", forwarded.error_message

        def topics(name: str, namespace: str) -> list[str]:
            return [topic for topic, _ in client_node.get_subscriber_names_and_types_by_node(name, namespace)]

        wait_until(
            lambda: "/chatter" in topics("plain", "/") and "/global_chatter" in topics("forwarded", "/ns"),
            "both subscriptions, remapped, in the graph",
            timeout=20.0,
            executor=executor,
        )
        assert proc.stop() == 0, proc.output()
    finally:
        proc.close()


def test_invalid_ros_arguments_are_a_usage_error() -> None:
    for ros_args, message in (
        (["-r", "nonsense"], "Couldn't parse remap rule: '-r nonsense'"),
        (["--bogus"], "unknown ROS arguments: ['--bogus']"),
        (["--params-file", "/no/such/file.yaml"], "Couldn't parse params file"),
    ):
        result = subprocess.run(
            [sys.executable, "-m", "container", "run", "--ros-args", *ros_args],
            cwd=REPO, capture_output=True, text=True, timeout=60,
        )
        assert result.returncode == 2, result.stderr
        assert result.stderr.startswith("container run: invalid ROS arguments: "), result.stderr
        assert message in result.stderr
        assert "Traceback" not in result.stderr


@pytest.mark.parametrize("value", ["0", "-1.5", "abc"])
def test_a_load_period_that_is_not_a_positive_number_is_a_usage_error(value: str) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "container", "run", "--ros-args", "-p", f"load_period:={value}"],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith("container run: load_period must be a positive number of seconds, not "), (
        result.stderr
    )
    assert "Traceback" not in result.stderr


def test_a_client_that_never_matches_costs_the_container_nothing_and_shutdown_exits_0(
    run_container: Callable[..., ContainerProcess], client_node: Node, executor: AsyncioExecutor
) -> None:
    """The issue's attack: a keep-all, reliable, transient-local client (its response
    reader never matches the services' volatile writers) asks the container's
    ``list_nodes`` and a hosted node's ``get_state`` 50 times each while the
    talker publishes at 20 Hz: the talker keeps its period (largest gap under
    two periods, as the test process receives it), each client is given up on
    in one log line, and SIGINT still ends the container with exit 0, its
    resender not counted as a plugin's thread."""
    unmatchable = QoSProfile(
        history=HistoryPolicy.KEEP_ALL,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    proc = run_container("container:\n  name: ComponentManager\n" + DEMO)
    proc.wait_for_line("I heard: [Hello World:")
    heard: list[float] = []
    client_node.create_subscription(String, "chatter", lambda message: heard.append(time.perf_counter()), 10)
    services: list[tuple[Any, str]] = [
        (ListNodes, "/ComponentManager/_container/list_nodes"),
        (GetState, "/talker/get_state"),
    ]
    clients: list[tuple[Client[Any, Any], Any]] = [
        (client_node.create_client(srv_type, name, qos_profile=unmatchable), srv_type.Request)
        for srv_type, name in services
    ]
    # Their own wait_for_service never returns true (rmw asks for their readers too): well-formed
    # clients of the same services wait for them, beside them in the same participant.
    for srv_type, name in services:
        assert client_node.create_client(srv_type, name).wait_for_service(timeout_sec=20.0)
    wait_until(lambda: len(heard) >= 5, "the talker heard", executor=executor)
    first = len(heard)
    start = len(proc.lines)
    futures = [client.call_async(request()) for client, request in clients for _ in range(50)]
    asked = [time.monotonic()]

    def given_up() -> bool:
        if sum("did not match" in line for line in proc.lines[start:]) >= 2:
            return True
        if time.monotonic() - asked[0] > 1.0:  # in case the first ones came before their writers matched
            asked[0] = time.monotonic()
            futures.extend(client.call_async(request()) for client, request in clients)
        return False

    wait_until(given_up, lambda: f"both clients given up on:\n{proc.output()}", timeout=20.0, executor=executor)
    wait_until(lambda: len(heard) >= first + 60, "the talker heard for 3 s more", executor=executor)
    code = proc.stop(sig=signal.SIGINT)
    output = "\n".join(proc.lines)
    lines = [line for line in proc.lines[start:] if "did not match" in line]
    assert len(lines) == 2, output  # one line per client, not per answer
    assert not any(future.done() for future in futures)
    gaps = [later - earlier for earlier, later in itertools.pairwise(heard[first - 1 :])]
    assert max(gaps) < 0.1, f"largest gap {max(gaps) * 1000:.0f} ms"
    assert code == 0, output
    assert "threads left behind" not in output
