"""The repository in a colcon workspace, built over the PyPI wheels' ROS prefix.

A fresh virtualenv with only the ROS wheels (and colcon, from PyPI) is the
underlay, as ``source /opt/ros/jazzy/setup.bash`` would be on a ROS install;
the repository is copied into ``src/`` and built with ``colcon build``. The
result must be a ROS prefix ROS tools read, and a working container. Three
plugin layouts are built beside it by the same ``colcon build``, and the
beacon example's interface package alone in a workspace of its own, at the
same time (``builds``; tests/colcon_support.py).

Cost: the underlay (30 to 40 s, most of it downloads), then the two builds
side by side: about 230 s on two quiet CPUs, 450 s on one. They start with
the session, at idle priority, and these tests run last (tests/conftest.py):
what the other tests leave idle goes to the builds.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.colcon_support import PLUGIN_TYPES, Builds, Prebuild

# What is left of the builds is the first test's set-up.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

INDEX = Path("share") / "ament_index" / "resource_index"


def _in_workspace(workspace: Path, env: dict[str, str], script: str, *, timeout: float = 120) -> str:
    """Run ``script`` in bash after ``source install/setup.bash``; return its output."""
    result = subprocess.run(
        ["bash", "-c", f"source install/setup.bash && {script}"],
        cwd=workspace,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout


@pytest.fixture(scope="module")
def builds(colcon_prebuild: Prebuild | None) -> Builds:
    """What the session's prebuild made (tests/colcon_support.py): the workspace with the repository and the
    three plugins, and the beacon example's interface package in a workspace of its own."""
    assert colcon_prebuild is not None, "tests/conftest.py starts the builds when test_colcon is collected"
    # What is left of the builds: started with the session at idle priority, they had the time the
    # tests before these left idle.
    builds = colcon_prebuild.result()
    # colcon writes build/, install/ and log/; nothing else may change.
    assert builds.sources_untouched
    assert builds.workspace_entries == ["build", "install", "log", "src"]
    assert not Path("/container").exists()
    return builds


@pytest.fixture(scope="module")
def workspace(builds: Builds) -> tuple[Path, dict[str, str]]:
    """The workspace, with the repository built and installed by colcon."""
    assert builds.finished("lifecycle_container"), builds.output
    return builds.workspace, builds.env


def test_the_install_is_a_ros_prefix_with_the_packages_types_and_executables(
    workspace: tuple[Path, dict[str, str]],
) -> None:
    root, env = workspace
    prefix = root / "install" / "lifecycle_container"
    out = _in_workspace(
        root,
        env,
        'echo "$AMENT_PREFIX_PATH"; python -c "'
        "import json, container, ldlidar, composition_interfaces.srv, container.executor._fastpath as fast;"
        "from ament_index_python import get_resource, get_package_prefix;"
        "print(json.dumps({"
        "'modules': [container.__file__, ldlidar.__file__, composition_interfaces.__file__, fast.__file__],"
        "'components': {p: get_resource('rclcpp_components', p)[0] for p in ('lifecycle_container', 'ldlidar')},"
        "'prefix': get_package_prefix('lifecycle_container')}))\"",
    )
    ament_prefix_path, report = out.splitlines()[-2:]
    # The container's prefix before the underlay's; the plugins' prefixes beside it come first too.
    install = f"{root / 'install'}{os.sep}"
    prefixes = ament_prefix_path.split(":")
    assert [p for p in prefixes if not p.startswith(install) or p == str(prefix)][:2] == [
        str(prefix), env["AMENT_PREFIX_PATH"]
    ]
    assert all(p.startswith(install) for p in prefixes[: prefixes.index(str(prefix))])
    found = json.loads(report)
    assert all(module.startswith(str(prefix)) for module in found["modules"]), found["modules"]
    assert found["prefix"] == str(prefix)
    assert found["components"]["lifecycle_container"].splitlines() == [
        "lifecycle_container::Counter;container.demo:Counter",
        "lifecycle_container::Listener;container.demo:Listener",
        "lifecycle_container::Talker;container.demo:Talker",
    ]
    assert found["components"]["ldlidar"].splitlines() == ["ldlidar::LdLidarNode;ldlidar._node:LdLidarNode"]
    for executable in ("component_container", "component_container_mt", "component_container_isolated",
                       "lifecycle_manager"):
        assert os.access(prefix / "lib" / "lifecycle_container" / executable, os.X_OK)
    # The command and the executables: sh, which starts Python with the signals held (container/_entry.py).
    for script in (prefix / "bin" / "container", prefix / "lib" / "lifecycle_container" / "component_container"):
        text = script.read_text()
        assert text.startswith("#!/bin/sh\n") and "exec env --block-signal=INT,TERM" in text, text
    types = _in_workspace(root, env, "container types")
    assert "ldlidar\n  ldlidar::LdLidarNode\n" in types
    assert "lifecycle_container\n  lifecycle_container::Counter\n" in types


@contextlib.contextmanager
def _container(root: Path, env: dict[str, str], name: str) -> Iterator[list[str]]:
    """The workspace's installed ``component_container`` as ``/name``, ready; SIGINT at the end, which it
    must exit 0 on. Yields its output lines so far; the rest is appended when it has exited."""
    proc = subprocess.Popen(
        ["bash", "-c", "source install/setup.bash && exec install/lifecycle_container/lib/lifecycle_container/"
         f"component_container --ros-args -r __node:={name}"],
        cwd=root, env={**env, "PYTHONUNBUFFERED": "1"}, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 60
        while not any("ready with" in line for line in lines):
            assert time.monotonic() < deadline and proc.poll() is None, "".join(lines)
            lines.append(proc.stdout.readline())
        yield lines
    finally:
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
        lines += rest.splitlines(keepends=True)
    assert proc.returncode == 0, "".join(lines)


def test_the_installed_container_executable_serves_load_requests(workspace: tuple[Path, dict[str, str]]) -> None:
    root, env = workspace
    with _container(root, env, "colcon_container") as output:
        loaded = _in_workspace(root, env, "container load /colcon_container lifecycle_container Talker")
        assert loaded == "Loaded component 1 into '/colcon_container' container node as '/talker'\n"
    assert "Unloaded '/talker'" in "".join(output)
    # The project's Fast DDS profile was installed, found and read whole.
    assert not [line for line in output if "XMLPARSER" in line], "".join(output)


# -- third-party plugins in the workspace, as docs/guide/install.md lays them out ---------------------

@pytest.fixture(scope="module")
def plugins(builds: Builds, workspace: tuple[Path, dict[str, str]]) -> tuple[Path, dict[str, str]]:
    """The workspace, with the three plugins built by colcon beside the container (``builds``)."""
    assert builds.returncode == 0, builds.output
    for package in ["radar_interfaces", *PLUGIN_TYPES]:
        assert builds.finished(package), builds.output
    return workspace


def test_plugins_built_by_colcon_are_ros_packages_with_their_component_types(
    plugins: tuple[Path, dict[str, str]],
) -> None:
    root, env = plugins
    out = _in_workspace(
        root,
        env,
        'python -c "'
        "import json;"
        "from ament_index_python import get_packages_with_prefixes, get_resource, get_resources;"
        "print(json.dumps({'packages': get_packages_with_prefixes(), "
        "'components': {p: get_resource('rclcpp_components', p)[0] for p in get_resources('rclcpp_components')}}))\"",
    )
    found = json.loads(out.splitlines()[-1])
    install = root / "install"
    # ros2 pkg list: each plugin is the package of its own prefix, and so is the container.
    for package in [*PLUGIN_TYPES, "radar_interfaces", "lifecycle_container"]:
        assert found["packages"][package] == str(install / package), package
    # ros2 component types
    assert {p: c.splitlines() for p, c in found["components"].items() if p in PLUGIN_TYPES} == PLUGIN_TYPES
    # Nothing of the container's own package in a plugin's prefix.
    for package in PLUGIN_TYPES:
        assert not (install / package / "lib" / "lifecycle_container").exists()
        assert not (install / package / INDEX / "packages" / "lifecycle_container").exists()
    types = _in_workspace(root, env, "container types")
    for package, lines in PLUGIN_TYPES.items():
        assert f"{package}\n  {lines[0].split(';')[0]}\n" in types


def test_the_container_loads_the_plugins_colcon_built(plugins: tuple[Path, dict[str, str]]) -> None:
    root, env = plugins
    with _container(root, env, "plugin_container") as output:
        for number, (package, lines) in enumerate(sorted(PLUGIN_TYPES.items()), start=1):
            plugin = lines[0].split(";")[0]
            loaded = _in_workspace(root, env, f"container load /plugin_container {package} {plugin} "
                                              "-e autostart:=true")
            name = plugin.split("::")[1].lower()
            assert loaded == f"Loaded component {number} into '/plugin_container' container node as '/{name}'\n"
    text = "".join(output)
    for name in ("beacon", "greeter", "radar"):
        assert f"Unloaded '/{name}'" in text, text


def test_an_interface_package_built_by_colcon_hashes_as_the_one_pip_built(builds: Builds) -> None:
    # The example plugin's interface package, built as an ordinary colcon
    # package over the wheels (``builds``), against what `pip install
    # ./examples/beacon_plugin` built into the test environment: the same
    # RIHS01 type hashes.
    assert builds.interfaces_returncode == 0, builds.interfaces_output
    for kind, name in (("msg", "Beacon"), ("action", "Sweep")):
        share = builds.interfaces / "install" / "beacon_interfaces" / "share" / "beacon_interfaces"
        by_colcon = share / kind / f"{name}.json"
        by_pip = Path(sys.prefix) / "share" / "beacon_interfaces" / kind / f"{name}.json"
        hashes = [
            {entry["type_name"]: entry["hash_string"] for entry in json.loads(path.read_text())["type_hashes"]}
            for path in (by_colcon, by_pip)
        ]
        assert hashes[0] == hashes[1]
        assert hashes[0][f"beacon_interfaces/{kind}/{name}"].startswith("RIHS01_")
