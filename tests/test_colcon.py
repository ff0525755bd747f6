"""The repository in a colcon workspace, built over the PyPI wheels' ROS prefix.

A fresh virtualenv with only the ROS wheels (and colcon, from PyPI) is the
underlay, as ``source /opt/ros/jazzy/setup.bash`` would be on a ROS install;
the repository is copied into ``src/`` and built with ``colcon build``. The
result must be a ROS prefix ROS tools read, and a working container.
"""

from __future__ import annotations

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
from tests.install_support import installed_ros_distro

# Builds: a virtualenv of the ROS wheels and colcon (about 2 minutes, the first
# test's set-up), then the workspace.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]


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
    tracked = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO, check=True, capture_output=True,
    ).stdout.decode().split("\0")
    for name in filter(None, tracked):
        if (REPO / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, source / name)
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


def test_the_installed_container_executable_serves_load_requests(workspace: tuple[Path, dict[str, str]]) -> None:
    root, env = workspace
    env = {**env, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        ["bash", "-c", "source install/setup.bash && exec install/lifecycle_container/lib/lifecycle_container/"
         "component_container --ros-args -r __node:=colcon_container"],
        cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        assert proc.stdout is not None
        lines: list[str] = []
        deadline = time.monotonic() + 60
        while not any("ready with" in line for line in lines):
            assert time.monotonic() < deadline and proc.poll() is None, "".join(lines)
            lines.append(proc.stdout.readline())
        loaded = _in_workspace(root, env, "container load /colcon_container lifecycle_container Talker")
        assert loaded == "Loaded component 1 into '/colcon_container' container node as '/talker'\n"
    finally:
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, rest
    assert "Unloaded '/talker'" in rest


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
