"""Reloading nodes in a live container: ``container run --reload``, ``container reload``, the service.

The plugin is a real distribution, ``reload-probe``, installed in editable
mode with pip (into a prefix of the test's own, seen through PYTHONPATH, so
the test environment stays as set up); the test edits its source on disk
while a ``container run`` child process runs it, and reads what the nodes
publish over DDS and what the container logs.
"""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from lifecycle_container_interfaces.srv import ReloadNode
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.client import Client
from rclpy.node import Node
from std_msgs.msg import String

from container import AsyncioExecutor
from tests.component_support import IMPORT_ROOT, ContainerClient, graph_nodes, parameter
from tests.container_support import ContainerProcess
from tests.install_support import install_reload_probe
from tests.waiting import wait_until

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

#: The plugin's module, ``{word}`` filled in: what its nodes say, so a test sees which code runs.
PLUGIN = '''\
"""The reload probe: a greeter saying which code, which life and which module it runs."""

from typing import Any

from std_msgs.msg import String

from container import LifecycleNode, hookimpl

WORD = "{word}"
#: Module-level state: a reload starts it again.
CONSTRUCTED: list[str] = []


class Greeter(LifecycleNode):
    def __init__(self, node_name: str = "greeter", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("suffix", "!")
        self.reload_state["lives"] = self.reload_state.get("lives", 0) + 1
        CONSTRUCTED.append(node_name)
        self._count = 0
        self._publisher = self.create_publisher(String, "greeting", 10)
        self.create_timer(0.05, self._greet)

    def _greet(self) -> None:
        self._count += 1
        suffix = self.get_parameter("suffix").value
        self._publisher.publish(String(data=(
            f"{{WORD}}{{suffix}} {{self.get_name()}} lives={{self.reload_state['lives']}} "
            f"module={{len(CONSTRUCTED)}} n={{self._count}}"
        )))


@hookimpl
def register_node_types(register):
    register(Greeter)
'''

CONFIG = """\
container:
  name: ComponentManager
nodes:
  - package: reload_probe
    plugin: reload_probe::Greeter
    name: greeter
    parameters:
      - suffix: "!"
    extra_arguments:
      use_intra_process_comms: true
    autostart: true
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: talker
    parameters:
      - rate: 10.0
    autostart: true
  - package: reload_probe
    plugin: reload_probe::Greeter
    name: quiet_greeter
  - package: lifecycle_container
    plugin: lifecycle_container::Listener
    name: ear
    remappings: ["chatter:=greeting"]
    extra_arguments:
      use_intra_process_comms: true
    autostart: true
"""


class Probe:
    """The installed plugin's source file, edited by the tests."""

    def __init__(self, source: Path) -> None:
        self.source = source

    def write(self, word: str) -> float:
        """Save the plugin with ``word``; when it was saved (system time, as DDS source timestamps)."""
        self.source.write_text(PLUGIN.format(word=word), encoding="utf-8")
        return time.time()

    def break_syntax(self) -> None:
        text = self.source.read_text(encoding="utf-8").replace("def _greet(self) -> None:", "def _greet(self) -> None")
        self.source.write_text(text, encoding="utf-8")


@pytest.fixture
def probe(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, request: pytest.FixtureRequest) -> Probe:
    """``reload-probe`` installed with ``pip install --editable`` into a prefix on PYTHONPATH
    (``plain`` as the fixture's parameter: ``pip install``, its files in that ``site-packages``)."""
    editable = getattr(request, "param", "editable") == "editable"
    source, paths = install_reload_probe(tmp_path, PLUGIN.format(word="v1"), editable=editable)
    path = os.pathsep.join([*paths, str(IMPORT_ROOT), os.environ.get("PYTHONPATH", "")])
    monkeypatch.setenv("PYTHONPATH", path.rstrip(os.pathsep))
    return Probe(source)


class Heard:
    """Messages on a topic with their source timestamps (system time, s), from a subscription of the test's node."""

    def __init__(self, node: Node, topic: str) -> None:
        self.messages: list[tuple[str, float]] = []
        self._lock = threading.Lock()
        # rclpy passes the message info to a callback of two parameters (Jazzy's annotation says one).
        node.create_subscription(String, topic, self._hear, 100)  # type: ignore[arg-type, unused-ignore]

    def _hear(self, message: String, info: dict[str, Any]) -> None:
        with self._lock:
            self.messages.append((message.data, info["source_timestamp"] / 1e9))

    def first(self, prefix: str) -> tuple[str, float] | None:
        with self._lock:
            return next((m for m in self.messages if m[0].startswith(prefix)), None)

    def latest(self) -> str:
        with self._lock:
            return self.messages[-1][0] if self.messages else "(nothing)"

    def count(self) -> int:
        with self._lock:
            return len(self.messages)

    def largest_gap(self, since: int = 0) -> float:
        with self._lock:
            stamps = [stamp for _, stamp in self.messages[since:]]
        return max((b - a for a, b in itertools.pairwise(stamps)), default=0.0)


@pytest.fixture
def start(run_container: Callable[..., ContainerProcess], probe: Probe) -> Callable[..., ContainerProcess]:
    def begin(*args: str) -> ContainerProcess:
        return run_container(CONFIG, args=args)

    return begin


def _parameter(client: ContainerClient, node: Node, name: str, parameter_name: str) -> Any:
    get: Client[Any, Any] = node.create_client(GetParameters, f"{name}/get_parameters")
    assert get.wait_for_service(timeout_sec=20.0)
    value = client.call(get, GetParameters.Request(names=[parameter_name])).values[0]
    node.destroy_client(get)
    return value


def test_a_saved_change_runs_within_2_s_with_the_same_name_parameters_and_state(
    start: Callable[..., ContainerProcess], probe: Probe, client_node: Node, executor: AsyncioExecutor
) -> None:
    container = start("--reload")
    container.wait_for_line("Reloading on change: watching reload-probe")
    greetings = Heard(client_node, "/greeting")
    chatter = Heard(client_node, "/chatter")
    client = ContainerClient(client_node, executor, process=container)
    wait_until(lambda: greetings.first("v1!") and chatter.count() >= 5, "the greeter and the talker heard",
               timeout=20.0, executor=executor)
    # A parameter set at run time is carried to the new node at its current value.
    setter: Client[Any, Any] = client_node.create_client(SetParameters, "/greeter/set_parameters")
    assert setter.wait_for_service(timeout_sec=20.0)
    answer = client.call(setter, SetParameters.Request(parameters=[parameter("suffix", "?")]))
    assert answer.results[0].successful
    wait_until(lambda: greetings.first("v1? greeter"), "the new suffix", timeout=10.0, executor=executor)
    talker_from = chatter.count()

    saved = probe.write("v2")
    wait_until(lambda: greetings.first("v2"), lambda: f"v2 on /greeting; last: {greetings.latest()}",
               timeout=10.0, executor=executor)
    heard = greetings.first("v2")
    assert heard is not None
    assert heard[1] - saved < 2.0, f"the new code published {heard[1] - saved:.2f} s after the save"
    # Same name and parameters; the node's kept state went over; module-level state started again.
    assert heard[0].startswith("v2? greeter lives=2 module=2 "), heard[0]
    line = container.wait_for_line("Reloaded 'reload-probe' in")
    assert "'/greeter' (unique_id 1 -> 5, active)" in line, line
    assert "'/quiet_greeter' (unique_id 3 -> 6, unconfigured)" in line, line  # file order, same state
    assert _parameter(client, client_node, "/greeter", "suffix").string_value == "?"
    assert "/greeter" in graph_nodes(client_node)
    # The talker beside it never missed two periods.
    wait_until(lambda: chatter.count() >= talker_from + 10, "the talker after the reload", executor=executor)
    gap = chatter.largest_gap(since=talker_from)
    assert gap < 0.3, f"the 10 Hz talker was silent for {gap:.3f} s around the reload"
    # The in-process listener hears the new node, each message once.
    container.wait_for_line("I heard: [v2? greeter lives=2")
    heard_lines = [line for line in container.lines if "I heard: [" in line]
    said = [line.split("I heard: [", 1)[1] for line in heard_lines]
    assert len(said) == len(set(said)), "a message reached the intra-process listener twice"


def test_a_syntax_error_leaves_the_old_node_running_reported_once_and_the_fix_reloads(
    start: Callable[..., ContainerProcess], probe: Probe, client_node: Node, executor: AsyncioExecutor
) -> None:
    container = start("--reload")
    container.wait_for_line("Reloading on change: watching reload-probe")
    greetings = Heard(client_node, "/greeting")
    wait_until(lambda: greetings.first("v1!"), "v1 heard", timeout=20.0, executor=executor)
    mark = len(container.lines)
    probe.break_syntax()
    error = container.wait_for_line("Could not reload 'reload-probe'", start=mark)
    assert f"{probe.source}:" in error and "SyntaxError" in error, error
    assert "the old code's nodes run on" in error, error
    # The old node goes on publishing.
    count = greetings.count()
    wait_until(lambda: greetings.count() >= count + 10, "v1 after the failed reload", executor=executor)
    assert greetings.latest().startswith("v1! greeter lives=1 "), greetings.latest()

    saved = probe.write("v3")
    wait_until(lambda: greetings.first("v3"), lambda: f"v3 on /greeting; last: {greetings.latest()}",
               timeout=10.0, executor=executor)
    heard = greetings.first("v3")
    assert heard is not None and heard[1] - saved < 2.0, (heard, saved)
    assert heard[0].startswith("v3! greeter lives=2 "), heard[0]
    errors = [line for line in container.lines[mark:] if "Could not reload" in line]
    assert len(errors) == 1, "\n".join(errors)


@pytest.mark.parametrize("probe", ["plain"], indirect=True)
def test_a_plain_install_is_watched_in_its_site_packages(
    start: Callable[..., ContainerProcess], probe: Probe, client_node: Node, executor: AsyncioExecutor
) -> None:
    container = start("--reload")
    line = container.wait_for_line("Reloading on change: watching reload-probe")
    assert f"reload-probe ({probe.source.parent})" in line, line
    greetings = Heard(client_node, "/greeting")
    wait_until(lambda: greetings.first("v1!"), "v1 heard", timeout=20.0, executor=executor)

    saved = probe.write("v2")
    wait_until(lambda: greetings.first("v2"), lambda: f"v2 on /greeting; last: {greetings.latest()}",
               timeout=10.0, executor=executor)
    heard = greetings.first("v2")
    assert heard is not None and heard[1] - saved < 2.0, (heard, saved)
    assert heard[0].startswith("v2! greeter lives=2 "), heard[0]


def test_an_import_that_never_returns_is_given_up_on_and_the_container_serves_on(
    run_container: Callable[..., ContainerProcess], probe: Probe, client_node: Node, executor: AsyncioExecutor
) -> None:
    config = CONFIG.replace("  name: ComponentManager\n", "  name: ComponentManager\n  load_timeout: 2.0\n")
    container = run_container(config)
    greetings = Heard(client_node, "/greeting")
    client = ContainerClient(client_node, executor, process=container)
    wait_until(lambda: greetings.first("v1!"), "v1 heard", timeout=20.0, executor=executor)
    probe.source.write_text("import time\n\ntime.sleep(30)\n" + PLUGIN.format(word="v2"), encoding="utf-8")
    reload: Client[Any, Any] = client_node.create_client(ReloadNode, "/ComponentManager/_container/reload_node")
    assert reload.wait_for_service(timeout_sec=20.0)

    began = time.monotonic()
    answer = client.call(reload, ReloadNode.Request(node_name="/greeter"), timeout=30.0)

    assert time.monotonic() - began < 10.0
    assert not answer.success
    assert "importing its new code did not end within 2 s (load_timeout)" in answer.error_message, answer
    assert "the old code's nodes run on" in answer.error_message, answer.error_message
    # The container's services answer, and the old node goes on publishing.
    assert client.list() == [(1, "/greeter"), (2, "/talker"), (3, "/quiet_greeter"), (4, "/ear")]
    mark = greetings.count()
    wait_until(lambda: greetings.count() >= mark + 5, "the greeter after the failed reload", executor=executor)
    assert greetings.latest().startswith("v1! greeter lives=1 "), greetings.latest()


def _run_cli(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "container", *args], capture_output=True, text=True, timeout=timeout
    )


def test_container_reload_reloads_a_node_and_refuses_what_it_cannot(
    start: Callable[..., ContainerProcess], probe: Probe, client_node: Node, executor: AsyncioExecutor
) -> None:
    container = start()
    greetings = Heard(client_node, "/greeting")
    client = ContainerClient(client_node, executor, process=container)
    wait_until(lambda: greetings.first("v1!"), "v1 heard", timeout=20.0, executor=executor)
    # Inactive before, inactive after.
    change: Client[Any, Any] = client_node.create_client(ChangeState, "/quiet_greeter/change_state")
    assert change.wait_for_service(timeout_sec=20.0)
    configure = ChangeState.Request(transition=Transition(id=Transition.TRANSITION_CONFIGURE))
    assert client.call(change, configure).success

    probe.write("v2")
    done = _run_cli("reload", "/greeter")
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.splitlines() == [
        "Reloaded '/greeter' in '/ComponentManager' container node as component 5",
        "Reloaded '/quiet_greeter' in '/ComponentManager' container node as component 6",
    ], done.stdout
    wait_until(lambda: greetings.first("v2! greeter lives=2"), "v2 heard", timeout=10.0, executor=executor)
    line = container.wait_for_line("Reloaded 'reload-probe' in")
    assert "'/greeter' (unique_id 1 -> 5, active), '/quiet_greeter' (unique_id 3 -> 6, inactive)" in line, line

    # The new code's constructor raises: the old code's nodes are loaded again, the error says where.
    probe.source.write_text(
        PLUGIN.format(word="v3").replace(
            'self.declare_parameter("suffix", "!")',
            'self.declare_parameter("suffix", "!")\n        raise ValueError("no")',
        ),
        encoding="utf-8",
    )
    reload: Client[Any, Any] = client_node.create_client(ReloadNode, "/ComponentManager/_container/reload_node")
    assert reload.wait_for_service(timeout_sec=20.0)
    answer = client.call(reload, ReloadNode.Request(node_name="/greeter"), timeout=60.0)
    assert not answer.success
    assert f"{probe.source}:" in answer.error_message and "ValueError: no" in answer.error_message, answer
    assert "the old code's nodes were loaded again" in answer.error_message, answer.error_message
    mark = greetings.count()
    wait_until(lambda: greetings.count() >= mark + 5, "the greeter again", executor=executor)
    assert greetings.latest().startswith("v2! greeter lives=3 "), greetings.latest()

    # The new code's activation fails: the same.
    probe.source.write_text(
        PLUGIN.format(word="v4")
        + "\n\nfrom rclpy.lifecycle import TransitionCallbackReturn\n\n\n"
        + "def _refuse(self, state):\n    return TransitionCallbackReturn.FAILURE\n\n\n"
        + "Greeter.on_activate = _refuse\n",
        encoding="utf-8",
    )
    answer = client.call(reload, ReloadNode.Request(node_name="/quiet_greeter"), timeout=60.0)
    assert not answer.success
    assert "transition 'activate': failed" in answer.error_message, answer.error_message
    assert "the old code's nodes were loaded again" in answer.error_message, answer.error_message
    mark = greetings.count()
    wait_until(lambda: greetings.count() >= mark + 5, "the greeter again", executor=executor)
    assert greetings.latest().startswith("v2! greeter lives=4 "), greetings.latest()

    # The container's own plugin is its own code; an unknown node is no node.
    answer = client.call(reload, ReloadNode.Request(node_name="/talker"), timeout=60.0)
    assert not answer.success and "restart the container" in answer.error_message, answer.error_message
    answer = client.call(reload, ReloadNode.Request(unique_id=99), timeout=60.0)
    assert (answer.success, answer.error_message) == (False, "No node found with unique_id: 99")
    refused = _run_cli("reload", "/nobody", "--spin-time", "1")
    assert refused.returncode == 1 and "No container on the ROS domain holds a node named '/nobody'" in refused.stderr
    assert container.process.poll() is None
    # Ids: 5, 6 the first reload; the old code again 7, 8; the new code's nodes 9, 10 (constructed,
    # then the activation failed), the old code again 11, 12.
    assert client.list() == [(2, "/talker"), (4, "/ear"), (11, "/greeter"), (12, "/quiet_greeter")]
