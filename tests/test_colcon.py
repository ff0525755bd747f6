"""The repository in a colcon workspace, built over the PyPI wheels' ROS prefix.

A fresh virtualenv with only the ROS wheels (and colcon, from PyPI) is the
underlay, as ``source /opt/ros/jazzy/setup.bash`` would be on a ROS install;
the repository is copied into ``src/`` and built with ``colcon build``. The
result must be a ROS prefix ROS tools read, and a working container.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.container_support import REPO
from tests.install_support import greeter_package, installed_ros_distro

# Builds: a virtualenv of the ROS wheels and colcon (about 2 minutes, the first
# test's set-up), then the workspace, then the plugins in it.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

INDEX = Path("share") / "ament_index" / "resource_index"


def _snapshot(root: Path) -> dict[str, float]:
    """Every file under ``root`` (bytecode caches aside) with its modification time."""
    return {
        str(path.relative_to(root)): path.stat().st_mtime
        for path in root.rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    }


def _environment(underlay: Path) -> dict[str, str]:
    """What sourcing the underlay gives: its executables first, its prefix on AMENT_PREFIX_PATH."""
    # Not this process's ROS libraries either: the wheels' bootstrapper skips
    # itself when its guard variable is inherited (see tests/test_wheels.py).
    drop = {"VIRTUAL_ENV", "PYTHONPATH", "AMENT_PREFIX_PATH", "LD_LIBRARY_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE"}
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env["PATH"] = f"{underlay / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["AMENT_PREFIX_PATH"] = str(underlay)
    env["ROS_DISTRO"] = installed_ros_distro()
    # Both cores for the interface packages, which build one after another otherwise.
    env.setdefault("CMAKE_BUILD_PARALLEL_LEVEL", str(os.cpu_count() or 1))
    return env


def _copy_tracked(directory: Path, destination: Path) -> None:
    """The repository's files under ``directory`` (tracked, or new and not ignored), into ``destination``."""
    tracked = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard", "--", "."],
        cwd=directory, check=True, capture_output=True,
    ).stdout.decode().split("\0")
    for name in filter(None, tracked):
        if (directory / name).is_file():
            (destination / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(directory / name, destination / name)


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
def workspace(underlay: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, dict[str, str]]]:
    """``colcon build`` of the repository (its tracked files) in a fresh workspace."""
    workspace = tmp_path_factory.mktemp("colcon_ws")
    source = workspace / "src" / "lifecycle_container"
    _copy_tracked(REPO, source)
    env = _environment(underlay)
    before = {"src": _snapshot(source), "underlay": _snapshot(underlay)}
    result = subprocess.run(
        ["colcon", "build", "--event-handlers", "console_cohesion-"],
        cwd=workspace,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    after = {"src": _snapshot(source), "underlay": _snapshot(underlay)}
    # colcon writes build/, install/ and log/; nothing else may change.
    assert after == before
    assert sorted(p.name for p in workspace.iterdir()) == ["build", "install", "log", "src"]
    assert not Path("/container").exists()
    yield workspace, env


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
    assert ament_prefix_path.split(":")[:2] == [str(prefix), env["AMENT_PREFIX_PATH"]]
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


# -- third-party plugins in the workspace, as docs/guide/install.md lays them out ---------------------

#: What ``ros2 component types`` lists for each plugin package the workspace builds.
PLUGIN_TYPES = {
    "beacon_nodes": ["beacon_nodes::Beacon;beacon_nodes:Beacon"],
    "greeter_nodes": ["greeter_nodes::Greeter;greeter_nodes:Greeter"],
    "radar_nodes": ["radar_nodes::Radar;radar_nodes:Radar"],
}


@pytest.fixture(scope="module")
def plugins(workspace: tuple[Path, dict[str, str]]) -> tuple[Path, dict[str, str]]:
    """Three plugins built by colcon beside the container: radar_nodes (ament_python) with its interface
    package radar_interfaces, greeter_nodes (ament_python, no messages) and beacon_nodes (the pip layout:
    pyproject.toml and CMakeLists.txt, plus a package.xml)."""
    root, env = workspace
    src = root / "src"
    _copy_tracked(REPO / "examples" / "colcon", src)
    _copy_tracked(REPO / "examples" / "beacon_plugin", src / "beacon_plugin")
    greeter_package(src / "greeter_nodes")
    before = _snapshot(src)
    fix = src / "lifecycle_container" / "container" / "cmake" / "ros_wheels.cmake"
    result = subprocess.run(
        ["colcon", "build", "--event-handlers", "console_cohesion-", "--packages-skip", "lifecycle_container",
         "--cmake-args", f"-DCMAKE_PROJECT_INCLUDE={fix}"],
        cwd=root, env=env, capture_output=True, text=True, timeout=900,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert _snapshot(src) == before  # builds in build/, installs in install/, nothing in the sources
    return root, env


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


def test_an_interface_package_built_by_colcon_hashes_as_the_one_pip_built(
    underlay: Path, tmp_path: Path
) -> None:
    # The example plugin's interface package, built as an ordinary colcon
    # package over the wheels (the one CMake argument works around their
    # targets), against what `pip install ./examples/beacon_plugin` built into
    # the test environment: the same RIHS01 type hashes.
    source = REPO / "examples" / "beacon_plugin" / "beacon_interfaces"
    (tmp_path / "src").mkdir()
    shutil.copytree(source, tmp_path / "src" / "beacon_interfaces")
    fix = REPO / "container" / "cmake" / "ros_wheels.cmake"
    result = subprocess.run(
        ["colcon", "build", "--event-handlers", "console_cohesion-",
         "--cmake-args", f"-DCMAKE_PROJECT_INCLUDE={fix}", "-DBUILD_TESTING=OFF"],
        cwd=tmp_path, env=_environment(underlay), capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    for kind, name in (("msg", "Beacon"), ("action", "Sweep")):
        by_colcon = tmp_path / "install" / "beacon_interfaces" / "share" / "beacon_interfaces" / kind / f"{name}.json"
        by_pip = Path(sys.prefix) / "share" / "beacon_interfaces" / kind / f"{name}.json"
        hashes = [
            {entry["type_name"]: entry["hash_string"] for entry in json.loads(path.read_text())["type_hashes"]}
            for path in (by_colcon, by_pip)
        ]
        assert hashes[0] == hashes[1]
        assert hashes[0][f"beacon_interfaces/{kind}/{name}"].startswith("RIHS01_")
