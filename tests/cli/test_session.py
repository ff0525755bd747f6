"""Every command starts ROS and ends alike: one session runner (``container._session``).

And no client command waits forever for a node that is gone or stuck.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest
from rclpy.context import Context
from rclpy.node import Node

from container._session import Session, run_session
from container.cli import main
from container.executor._engine import ENGINE
from tests.container_support import REPO, LoggedProcess
from tests.waiting import wait_until


@pytest.fixture
def observer(context: Context) -> Iterator[Node]:
    node = Node("_session_observer", context=context)
    yield node
    node.destroy_node()


def wait_for_node(observer: Node, predicate: str, *, timeout: float = 20.0) -> None:
    """Poll the ROS graph (discovery offers no event to wait on: rclpy#929) until a
    node whose name contains ``predicate`` shows up."""
    wait_until(
        lambda: any(predicate in name for name, _ in observer.get_node_names_and_namespaces()),
        f"a node named like {predicate!r}",
        timeout=timeout,
    )


def start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "container", *args],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def interrupt(process: subprocess.Popen[str], sig: int = signal.SIGINT) -> tuple[int, str]:
    process.send_signal(sig)
    try:
        output, _ = process.communicate(timeout=15)
    except subprocess.TimeoutExpired:
        process.kill()
        output, _ = process.communicate()
        raise AssertionError(f"still running 15 s after signal {sig}:\n{output}") from None
    return process.returncode, output


@pytest.mark.parametrize(
    ("command", "hidden_node"),
    [
        (("list", "--spin-time", "60"), "_container_cli_"),
        (("lifecycle", "nodes", "--spin-time", "60"), "_container_lifecycle_cli_"),
    ],
)
def test_ctrl_c_ends_a_client_command_with_130_and_no_traceback(
    observer: Node, command: tuple[str, ...], hidden_node: str
) -> None:
    process = start(*command)
    wait_for_node(observer, hidden_node)
    code, output = interrupt(process)
    assert code == 130, output
    assert "Traceback" not in output


def test_sigterm_ends_a_client_command_with_143(observer: Node) -> None:
    process = start("list", "--spin-time", "60")
    wait_for_node(observer, "_container_cli_")
    code, output = interrupt(process, signal.SIGTERM)
    assert code == 143, output


def test_manager_stops_cleanly_and_never_reads_p_as_a_remap_rule(observer: Node) -> None:
    process = start("manager", "--name", "session_manager", "-p", "node_names:=[/nobody]", "-p", "autostart:=false")
    wait_for_node(observer, "session_manager")
    code, output = interrupt(process)
    assert code == 0, output
    assert "remap" not in output.lower(), output


def test_command_line_arguments_are_not_ros_arguments(monkeypatch: pytest.MonkeyPatch) -> None:
    """rcl would apply the remap rule in sys.argv to every node of the context."""
    monkeypatch.setattr(sys, "argv", ["container", "load", "-p", "x:=1", "--ros-args", "-r", "chatter:=elsewhere"])
    topics: list[str] = []

    async def main(session: Session) -> int:
        with session.client_node("_argv_probe") as node:
            topics.append(node.create_publisher(type(node.get_clock().now().to_msg()), "chatter", 1).topic_name)
        return 7

    assert run_session(main) == 7
    assert topics == ["/chatter"]


#: A session whose main makes a node (left to the garbage collector, as a
#: node's own references make it) and returns 3, then the names of the
#: process's Fast DDS threads (``dds.*``), each its participant's but the shared
#: memory watchdog, which the library keeps for the process.
SESSION_THEN_THREADS = """
import os, sys
from container import _session
from rclpy.node import Node

{patch}

class Probe(Node):
    def __init__(self, context):
        super().__init__("_teardown_probe", context=context)
        # As most nodes do: a bound method as a callback, node and timer in a cycle.
        self.timer = self.create_timer(60.0, self.tick)

    def tick(self):
        pass

async def main(session):
    session.executor.add_node(Probe(session.context))
    return 3

code = _session.run_session(main)
names = []
for task in os.listdir("/proc/self/task"):
    try:
        with open(f"/proc/self/task/{{task}}/comm") as comm:
            names.append(comm.read().strip())
    except OSError:
        pass
print("dds threads:", sorted(n for n in names if n.startswith("dds.") and n != "dds.shm.wdog"), flush=True)
sys.exit(code)
"""


def run_script(script: str, *, timeout: float = 30.0) -> tuple[int, str, float]:
    began = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=timeout, cwd=REPO, check=False
    )
    return done.returncode, done.stdout + done.stderr, time.monotonic() - began


def test_a_session_ends_with_its_participant_destroyed_not_left_to_the_interpreters_exit() -> None:
    code, output, _ = run_script(SESSION_THEN_THREADS.format(patch=""))
    assert code == 3, output
    assert "dds threads: []" in output, output
    assert "Traceback" not in output, output


@pytest.mark.skipif(ENGINE == "python", reason="the pure-Python Deadline needs the GIL, which this hang keeps")
def test_a_teardown_that_never_ends_costs_its_bound_and_keeps_the_sessions_status() -> None:
    # A middleware deadlock in the participant's destruction, inside rclpy's
    # destructors, which keep the GIL: stood in for by a context whose
    # destruction sleeps for an hour in C, the GIL held (ctypes.PyDLL).
    hang = "import ctypes, rclpy.context\n_session.TEARDOWN_S = 1.0\n"
    hang += "rclpy.context.Context.destroy = lambda self: ctypes.PyDLL(None).sleep(3600)"
    code, output, took = run_script(SESSION_THEN_THREADS.format(patch=hang))
    assert code == 3, output
    said = "ROS teardown (the DDS participant's destruction) still running 1 s after the session ended"
    assert said in output, output
    assert "exiting without it (status 3)" in output, output
    assert "dds threads:" not in output, output  # the process ended there
    assert took < 20, output


#: A node that is in discovery and serves the lifecycle and container services,
#: but never answers ``change_state`` or the container's requests: a stuck
#: process, or one that is gone and not yet dropped from discovery.
STUCK_NODE = """
import threading
import rclpy
from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from lifecycle_msgs.msg import State, Transition, TransitionDescription
from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor

rclpy.init()
node = rclpy.create_node("stuck")
group = ReentrantCallbackGroup()

def never(request, response):
    threading.Event().wait()

def state(request, response):
    response.current_state = State(id=State.PRIMARY_STATE_UNCONFIGURED, label="unconfigured")
    return response

def transitions(request, response):
    response.available_transitions = [TransitionDescription(
        transition=Transition(id=Transition.TRANSITION_CONFIGURE, label="configure"),
        start_state=State(id=State.PRIMARY_STATE_UNCONFIGURED, label="unconfigured"),
        goal_state=State(id=State.PRIMARY_STATE_INACTIVE, label="inactive"))]
    return response

for srv_type, name, callback in [
    (GetState, "stuck/get_state", state),
    (GetAvailableTransitions, "stuck/get_available_transitions", transitions),
    (GetAvailableTransitions, "stuck/get_transition_graph", transitions),
    (ChangeState, "stuck/change_state", never),
    (LoadNode, "stuck/_container/load_node", never),
    (UnloadNode, "stuck/_container/unload_node", never),
    (ListNodes, "stuck/_container/list_nodes", never),
]:
    node.create_service(srv_type, name, callback, callback_group=group)
executor = MultiThreadedExecutor(num_threads=8)
executor.add_node(node)
print("stuck node up", flush=True)
executor.spin()
"""


@pytest.fixture
def stuck_node() -> Iterator[LoggedProcess]:
    process = LoggedProcess([sys.executable, "-c", STUCK_NODE], name="stuck")
    try:
        process.wait_for_line("stuck node up")
        yield process
    finally:
        process.close()


def run_command(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, float]:
    """``container ARGS`` in this process: exit code, stderr and how long it took."""
    began = time.monotonic()
    code = main(list(args))
    return code, capsys.readouterr().err, time.monotonic() - began


def test_lifecycle_get_of_a_missing_node_gives_up(capsys: pytest.CaptureFixture[str]) -> None:
    code, err, took = run_command(capsys, "lifecycle", "get", "/nonexistent", "--timeout", "1")
    assert (code, err) == (1, "Node not found\n")
    assert took < 8


def test_client_commands_give_up_on_a_node_that_never_answers(
    stuck_node: LoggedProcess, capsys: pytest.CaptureFixture[str]
) -> None:
    code, err, took = run_command(capsys, "lifecycle", "set", "/stuck", "configure", "--timeout", "1")
    assert (code, err) == (
        1, "/stuck: transition 'configure': /stuck/change_state did not answer within 1.0 s\n"
    )
    assert took < 8  # discovery (up to --spin-time, 2 s), a query, then 1 s
    code, err, took = run_command(capsys, "unload", "/stuck", "1", "--timeout", "1")
    assert (code, err) == (1, "No response from '/stuck/_container/unload_node' within 1 s\n")
    assert took < 8
