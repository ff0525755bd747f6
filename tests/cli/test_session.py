"""Every command starts ROS and ends alike: one session runner (``container._session``)."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator

import pytest
from rclpy.context import Context
from rclpy.node import Node

from container._session import Session, run_session
from tests.container_support import REPO
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
