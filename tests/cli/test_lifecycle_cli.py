"""``container lifecycle``: the ros2 lifecycle verbs against a running container."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable

import pytest

from container.cli import main
from tests.container_support import REPO, ContainerProcess

DEMO = """
nodes:
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: talker
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: broken
    parameters: [{rate: -1.0}]
  - package: lifecycle_container
    plugin: lifecycle_container::Listener
    name: listener
"""


@pytest.fixture(autouse=True)
def own_domain(monkeypatch: pytest.MonkeyPatch) -> None:
    """A ROS domain of its own: nodes of earlier in-process tests linger in the
    graph until garbage-collected, and ``nodes`` lists the whole graph."""
    session = int(os.environ["ROS_DOMAIN_ID"])
    monkeypatch.setenv("ROS_DOMAIN_ID", str((session + 50) % 101 + 1))


def lifecycle(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(["lifecycle", *args])
    out, err = capsys.readouterr()
    return code, out, err


# A container process and a command-line call per verb.
@pytest.mark.slow
def test_lifecycle_verbs_match_ros2_lifecycle(
    run_container: Callable[..., ContainerProcess], capsys: pytest.CaptureFixture[str]
) -> None:
    run_container(DEMO)
    assert lifecycle(capsys, "nodes") == (0, "/broken\n/listener\n/talker\n", "")
    assert lifecycle(capsys, "get", "/talker") == (0, "unconfigured [1]\n", "")
    assert lifecycle(capsys, "list", "/talker") == (
        0,
        "- configure [1]\n\tStart: unconfigured\n\tGoal: configuring\n"
        "- shutdown [5]\n\tStart: unconfigured\n\tGoal: shuttingdown\n",
        "",
    )
    assert lifecycle(capsys, "set", "/talker", "configure") == (0, "Transitioning successful\n", "")
    assert lifecycle(capsys, "set", "talker", "3") == (0, "Transitioning successful\n", "")
    assert lifecycle(capsys, "get") == (
        0,
        "/broken: unconfigured [1]\n/listener: unconfigured [1]\n/talker: active [3]\n",
        "",
    )
    assert lifecycle(capsys, "set", "/talker", "configure") == (
        1,
        "",
        "Unknown transition requested, available ones are:\n"
        "- deactivate [4]\n- shutdown [7]\n",
    )


# A container process and command-line processes.
@pytest.mark.slow
def test_failed_transition_and_unknown_node_exit_non_zero(
    run_container: Callable[..., ContainerProcess], capsys: pytest.CaptureFixture[str]
) -> None:
    run_container(DEMO)
    assert lifecycle(capsys, "set", "/broken", "configure") == (1, "", "Transitioning failed\n")
    assert lifecycle(capsys, "get", "/broken") == (0, "unconfigured [1]\n", "")
    assert lifecycle(capsys, "get", "/nobody", "--spin-time", "0.5") == (1, "", "Node not found\n")
    assert lifecycle(capsys, "set", "/nobody", "configure", "--spin-time", "0.5")[0] == 1


def test_command_line_entry_point(run_container: Callable[..., ContainerProcess]) -> None:
    run_container(DEMO)
    result = subprocess.run(
        [sys.executable, "-m", "container", "lifecycle", "set", "/listener", "configure"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert (result.returncode, result.stdout) == (0, "Transitioning successful\n"), result.stderr
