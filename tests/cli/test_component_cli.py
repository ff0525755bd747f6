"""``container load|unload|list|types``: ``ros2 component``'s output and exit codes.

Each command runs as its own process against a ``container run`` process,
as a user would type it.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.container_support import REPO, ContainerProcess, LoggedProcess

EMPTY = "container:\n  name: ComponentManager\n"


def container_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "container", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
    )


# A container process and nine command-line processes.
@pytest.mark.slow
def test_load_list_unload_like_ros2_component(run_container: Callable[..., ContainerProcess]) -> None:
    run_container(EMPTY)
    result = container_cli("list")
    assert (result.returncode, result.stdout) == (0, "/ComponentManager\n"), result.stderr

    result = container_cli("load", "/ComponentManager", "lifecycle_container", "lifecycle_container::Talker")
    assert result.returncode == 0, result.stderr
    assert result.stdout == "Loaded component 1 into '/ComponentManager' container node as '/talker'\n"

    result = container_cli(
        "load", "/ComponentManager", "lifecycle_container", "Listener",
        "-n", "ear", "--node-namespace", "/demo", "--log-level", "DEBUG",
        "-r", "chatter:=/elsewhere", "-p", "unused:=3", "-e", "use_intra_process_comms:=true",
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout == "Loaded component 2 into '/ComponentManager' container node as '/demo/ear'\n"

    # ros2cli's -q: the id and the full name, two spaces apart, as `list` prints them.
    result = container_cli("load", "-q", "/ComponentManager", "lifecycle_container", "Talker", "-n", "quiet")
    assert (result.returncode, result.stdout) == (0, "3  /quiet\n"), result.stderr

    result = container_cli("list", "/ComponentManager")
    assert (result.returncode, result.stdout) == (0, "1  /talker\n2  /demo/ear\n3  /quiet\n"), result.stderr

    result = container_cli("list")
    assert result.stdout == "/ComponentManager\n  1  /talker\n  2  /demo/ear\n  3  /quiet\n", result.stderr

    result = container_cli("list", "--containers-only")
    assert (result.returncode, result.stdout) == (0, "/ComponentManager\n"), result.stderr

    result = container_cli("unload", "/ComponentManager", "1", "3")
    assert result.returncode == 0, result.stderr
    assert result.stdout == (
        "Unloaded component 1 from '/ComponentManager' container node\n"
        "Unloaded component 3 from '/ComponentManager' container node\n"
    )
    result = container_cli("list", "/ComponentManager")
    assert (result.returncode, result.stdout) == (0, "2  /demo/ear\n"), result.stderr


# A container process and six command-line processes.
@pytest.mark.slow
def test_load_names_the_node_after_its_remap_rules_and_takes_rclcpp_extras(
    run_container: Callable[..., ContainerProcess],
) -> None:
    proc = run_container(EMPTY)
    result = container_cli("load", "/ComponentManager", "lifecycle_container", "Talker")
    assert result.returncode == 0, result.stderr
    # The type's default name is taken; the remap rule gives another one, as rcl would.
    result = container_cli(
        "load", "/ComponentManager", "lifecycle_container", "Talker", "-r", "__node:=renamed",
        "-e", "forward_global_arguments:=false", "-e", "autostart:=true",
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout == "Loaded component 2 into '/ComponentManager' container node as '/renamed'\n"
    result = container_cli("lifecycle", "get", "/renamed")
    assert (result.returncode, result.stdout) == (0, "active [3]\n"), result.stderr
    # The first rule that names the node wins over -n, as in rclcpp (its -n comes last).
    result = container_cli(
        "load", "-q", "/ComponentManager", "lifecycle_container", "Talker", "-n", "ignored",
        "-r", "__node:=first_rule", "-r", "__ns:=/ns", "-r", "__node:=second_rule",
    )
    assert (result.returncode, result.stdout) == (0, "3  /ns/first_rule\n"), result.stderr
    result = container_cli("load", "/ComponentManager", "lifecycle_container", "Talker", "-r", "__node:=renamed")
    assert result.returncode == 1
    assert "'/renamed' is already loaded (unique_id 2)" in result.stderr
    result = container_cli(
        "load", "/ComponentManager", "lifecycle_container", "Talker", "-n", "x", "-e", "autostart:=3"
    )
    assert result.returncode == 1
    assert result.stderr == "Failed to load component: Extra component argument 'autostart' must be a boolean\n"
    # Log lines name a type once.
    assert not any("lifecycle_container::lifecycle_container" in line for line in proc.lines), proc.lines


# A container process and five command-line processes.
@pytest.mark.slow
def test_refusals_print_the_reason_and_exit_1(run_container: Callable[..., ContainerProcess]) -> None:
    proc = run_container(EMPTY)
    result = container_cli("load", "/ComponentManager", "no_such_package", "no_such_package::X")
    assert result.returncode == 1
    assert result.stdout == ""
    assert result.stderr == "Failed to load component: Could not find requested resource in ament index\n"

    # An extra argument rclcpp's container would ignore is ignored (and logged once).
    result = container_cli(
        "load", "-q", "/ComponentManager", "lifecycle_container", "Talker", "-n", "e1", "-e", "enable_rosout:=false"
    )
    assert (result.returncode, result.stdout) == (0, "1  /e1\n"), result.stderr

    result = container_cli("load", "/ComponentManager", "lifecycle_container", "Talker", "-p", "rate:=fast")
    assert result.returncode == 1
    assert "Failed to load component: Component constructor threw an exception" in result.stderr

    result = container_cli("unload", "/ComponentManager", "5")
    assert result.returncode == 1
    assert result.stderr == (
        "Failed to unload component 5 from '/ComponentManager' container node\n"
        "    No node found with unique_id: 5\n"
    )
    # The container served on: the next load succeeds, with the next id (refusals take none).
    result = container_cli("load", "/ComponentManager", "lifecycle_container", "Talker")
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("Loaded component 2 ")
    assert proc.process.poll() is None


# A container process and two command-line processes.
@pytest.mark.slow
def test_load_prints_the_warnings_it_caused_and_still_succeeds(
    run_container: Callable[..., ContainerProcess],
) -> None:
    proc = run_container(EMPTY)
    result = container_cli("load", "/ComponentManager", "lifecycle_container", "Talker", "-n", "typo", "-p", "rat:=5.0")
    assert result.returncode == 0, result.stderr
    assert result.stdout == "Loaded component 1 into '/ComponentManager' container node as '/typo'\n"
    # One ROS warning line on stderr, under the node's logger, as the container logged it.
    [line] = result.stderr.splitlines()
    assert line.startswith("[WARN] ["), line
    assert line.endswith(
        "[typo]: Unknown parameter 'rat' ignored: this node does not read it (did you mean 'rate'?)"
    ), line
    proc.wait_for_line("[typo]: Unknown parameter 'rat' ignored")

    # -q keeps stdout to the id and the name; the warnings still reach stderr.
    result = container_cli(
        "load", "-q", "/ComponentManager", "lifecycle_container", "Talker", "-n", "e1", "-e", "enable_rosout:=false"
    )
    assert (result.returncode, result.stdout) == (0, "2  /e1\n"), result.stderr
    assert result.stderr.rstrip("\n").endswith(
        "[ComponentManager]: Extra component argument 'enable_rosout' is not used by this container: "
        "ignored (as rclcpp's container does)"
    ), result.stderr


@pytest.mark.parametrize(
    "args",
    [
        # A second of discovery each: one of them in the fast lane.
        pytest.param(("load", "/x", "lifecycle_container", "Talker"), marks=pytest.mark.slow),
        pytest.param(("unload", "/x", "1"), marks=pytest.mark.slow),
        ("list", "/x"),
    ],
)
def test_missing_container(args: tuple[str, ...]) -> None:
    result = container_cli(*args, "--spin-time", "1")
    assert result.returncode == 1
    assert result.stdout == ""
    assert result.stderr == "Unable to find container node '/x'\n"


def test_malformed_parameter_is_a_usage_error() -> None:
    result = container_cli("load", "/c", "pkg", "Type", "-p", "no_separator")
    assert result.returncode == 2
    assert "expected 'name:=value'" in result.stderr


def test_types_lists_the_installed_plugins() -> None:
    result = container_cli("types")
    assert result.returncode == 0, result.stderr
    assert (
        "lifecycle_container\n  lifecycle_container::Counter\n  lifecycle_container::Listener\n"
        "  lifecycle_container::Talker\n"
    ) in result.stdout


# Installs the third-party example with pip.
@pytest.mark.slow
def test_pip_installed_plugin_appears_in_types_and_loads_from_the_command_line(
    thirdparty_site: Path,
    run_container: Callable[..., ContainerProcess],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv(
        "PYTHONPATH", os.pathsep.join(filter(None, [str(thirdparty_site), os.environ.get("PYTHONPATH")]))
    )
    result = container_cli("types")
    assert result.returncode == 0, result.stderr
    assert "greeter_nodes\n  greeter_nodes::Greeter\n" in result.stdout

    proc = run_container(EMPTY)
    result = container_cli(
        "load", "/ComponentManager", "greeter_nodes", "greeter_nodes::Greeter", "-p", "name:=tests"
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout == "Loaded component 1 into '/ComponentManager' container node as '/greeter'\n"
    result = container_cli("unload", "/ComponentManager", "1")
    assert result.returncode == 0, result.stderr
    proc.wait_for_line("Unloaded '/greeter'")


# Installs the third-party example with pip.
@pytest.mark.slow
def test_a_running_container_follows_installs_and_uninstalls(
    thirdparty_site: Path,
    run_container: Callable[..., ContainerProcess],
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
) -> None:
    site = tmp_path / "site"
    site.mkdir()
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])))
    proc = run_container(EMPTY)

    def load(package: str, plugin: str) -> subprocess.CompletedProcess[str]:
        return container_cli("load", "/ComponentManager", package, plugin)

    result = load("greeter_nodes", "greeter_nodes::Greeter")
    assert result.stderr == "Failed to load component: Could not find requested resource in ament index\n"

    # Installed after start (the files pip install puts there): the next request finds it.
    shutil.copytree(thirdparty_site, site, dirs_exist_ok=True)
    result = load("greeter_nodes", "greeter_nodes::Greeter")
    assert result.stdout == "Loaded component 1 into '/ComponentManager' container node as '/greeter'\n", result.stderr
    proc.wait_for_line("Plugins installed since start: greeter_nodes::Greeter")

    # Uninstalled (what pip uninstall removes): refused, though its module is still imported.
    for path in site.iterdir():
        shutil.rmtree(path)
    result = load("greeter_nodes", "greeter_nodes::Greeter")
    assert result.returncode == 1
    assert result.stderr == (
        "Failed to load component: Cannot load greeter_nodes::Greeter: distribution 'greeter-nodes' "
        "is no longer installed\n"
    )

    # A plugin that fails to import: the load answer says why, not just "not found".
    info = site / "broken_nodes-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-nodes\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[container.plugins]\nbroken = broken_nodes_module\n")
    (site / "broken_nodes_module.py").write_text("import numpy_but_misspelled\n")
    result = load("broken_nodes", "broken_nodes::Anything")
    assert result.stderr == (
        "Failed to load component: Plugin failed to load: distribution 'broken-nodes' entry point 'broken': "
        "cannot import 'broken_nodes_module': ModuleNotFoundError: No module named 'numpy_but_misspelled'\n"
    )
    # The container is still whole: the installed demo types load.
    result = load("lifecycle_container", "lifecycle_container::Talker")
    assert result.returncode == 0, result.stderr


@pytest.mark.slow
def test_a_container_whose_services_are_discovered_after_its_name_is_waited_for(spinning: Any) -> None:
    """Under load a discovery message can come a Fast DDS heartbeat (3 s) late: the command, once it
    saw the container's name, waits for its services rather than calling it missing (CI saw
    "Unable to find container node '/ComponentManager'" between two loads that worked).

    Here the services come 1.5 s after the command saw the name, past its ``--spin-time`` of 1 s
    (the command could only have seen the name after it started looking)."""
    from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
    from rclpy.node import Node

    node = Node("late_container", context=spinning.context)
    spinning.add_node(node)
    command = LoggedProcess(
        [sys.executable, "-m", "container", "load", "/late_container", "some_package", "Some",
         "--spin-time", "1"],
        name="load",
    )
    try:
        deadline = time.monotonic() + 20.0
        cli = f"_container_cli_{command.process.pid}"
        while not any(name == cli for name, _ in node.get_node_names_and_namespaces()):
            assert time.monotonic() < deadline and command.process.poll() is None, command.output()
            threading.Event().wait(0.02)
        seen = time.monotonic()

        def load(request: Any, response: Any) -> Any:
            response.success, response.unique_id, response.full_node_name = True, 7, "/some"
            return response

        threading.Event().wait(max(0.0, seen + 1.5 - time.monotonic()))
        assert command.process.poll() is None, f"gave up before the services came:\n{command.output()}"
        node.create_service(LoadNode, "~/_container/load_node", load)
        node.create_service(UnloadNode, "~/_container/unload_node", lambda request, response: response)
        node.create_service(ListNodes, "~/_container/list_nodes", lambda request, response: response)
        assert command.process.wait(20.0) == 0, command.output()
        command.wait_for_line("Loaded component 7 into '/late_container' container node as '/some'")
    finally:
        command.close()
        spinning.remove_node(node)
        node.destroy_node()
