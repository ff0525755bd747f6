"""The project's wheels, installed with pip into a fresh virtualenv and nothing else run.

The container, the LiDAR plugin and the third-party example are each built
into a wheel (as ``pip wheel`` or ``python -m build`` would, without build
isolation: lifecycle-container is not on PyPI for an isolated build of the
plugins to fetch), installed into a new virtualenv with their dependencies
from PyPI, used, and uninstalled: what pip installed, pip removes.

Cost: the four wheels, built side by side, the project and the beacon example
in the build directories ``.ci/setup`` keeps (nothing compiled again): 13 to
19 s where one after another, the beacon example compiled anew, took 51 s
(back to back, beside other builds); then pip and the tests, about 40 s.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from container._ament import EXECUTABLES
from container._registry import PluginRegistry
from tests.container_support import REPO
from tests.install_support import greeter_package, installed_ros_distro

# Builds: the wheels (under 20 s, the first test's set-up), a virtualenv to install them into.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

INDEX = Path("share") / "ament_index" / "resource_index"
SITE = Path("lib") / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages"
#: Holds the command's signals from site's first .pth file on (container/_entry.py).
PTH = REPO / "container" / "interfaces" / "00_lifecycle_container.pth"


def _run(*args: str | Path, env: dict[str, str] | None = None, timeout: float = 600) -> str:
    result = subprocess.run([str(a) for a in args], capture_output=True, text=True, env=env, timeout=timeout)
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout


@pytest.fixture(scope="module")
def wheels(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("wheels")
    build = [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-build-isolation", "--no-deps", "--wheel-dir", out]
    # The project and the beacon example in the build directories .ci/setup
    # left in the environment, if there are: their compiled parts are up to
    # date there. The four builds run side by side (separate directories).
    sources = [REPO, REPO / "plugins" / "ldlidar", REPO / "examples" / "thirdparty_plugin",
               REPO / "examples" / "beacon_plugin"]
    kept = {REPO: Path(sys.prefix) / "skbuild", sources[3]: Path(sys.prefix) / "skbuild-beacon_plugin"}
    # No ROS_DISTRO, as in a virtualenv of the wheels not activated: the
    # build is for the distribution installed here (container/interfaces/ros_distro.py).
    env = {k: v for k, v in os.environ.items() if k != "ROS_DISTRO"}
    builds = [
        subprocess.Popen(
            [str(a) for a in (*build, source)]
            + ([f"--config-settings=build-dir={kept[source]}"] if source in kept and kept[source].is_dir() else []),
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
        )
        for source in sources
    ]
    try:
        for proc in builds:
            output, _ = proc.communicate(timeout=600)
            assert proc.returncode == 0, output
    finally:
        for proc in builds:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    found = {path.name.split("-")[0]: path for path in out.glob("*.whl")}
    assert sorted(found) == ["beacon_nodes", "greeter_nodes", "ldlidar", "lifecycle_container"]
    return found


@pytest.fixture(scope="module")
def venv(wheels: dict[str, Path], underlay: Path) -> Iterator[Path]:
    """A virtualenv of ROS wheels (nothing of this project, nothing run) with the
    container and LiDAR wheels then installed by pip; all of them uninstalled again."""
    python = underlay / "bin" / "python"
    _run(python, "-m", "pip", "install", "--quiet", wheels["lifecycle_container"], wheels["ldlidar"])
    yield underlay
    # The session's other users of the environment get it back as it was.
    subprocess.run(
        [str(python), "-m", "pip", "uninstall", "--yes", "--quiet", *(name.replace("_", "-") for name in wheels)],
        capture_output=True, timeout=300,
    )


def _plain_env() -> dict[str, str]:
    # Nothing activated: no AMENT_PREFIX_PATH, no ROS_DISTRO, no PYTHONPATH. And
    # not this process's ROS libraries: the wheels' bootstrapper (a .pth that
    # re-executes Python with LD_LIBRARY_PATH set) skips itself when its guard
    # variable is inherited, so a child in another environment would run on
    # this environment's libraries.
    drop = {
        "VIRTUAL_ENV", "PYTHONPATH", "AMENT_PREFIX_PATH", "ROS_DISTRO", "LD_LIBRARY_PATH",
        "_ROS_WHEELS_BOOTSTRAP_COMPLETE",
    }
    return {k: v for k, v in os.environ.items() if k not in drop}


def _index_files(prefix: Path, package: str) -> list[Path]:
    return [
        path
        for path in (
            prefix / INDEX / "packages" / package,
            prefix / INDEX / "rclcpp_components" / package,
            *(prefix / "lib" / package / name for name in EXECUTABLES),
        )
        if path.exists()
    ]


def test_a_wheel_built_without_ros_distro_depends_on_the_distribution_it_was_built_against(
    wheels: dict[str, Path], venv: Path
) -> None:
    distro = installed_ros_distro()
    with zipfile.ZipFile(wheels["lifecycle_container"]) as wheel:
        [metadata] = [name for name in wheel.namelist() if name.endswith(".dist-info/METADATA")]
        requires = [line.split(":", 1)[1].strip() for line in wheel.read(metadata).decode().splitlines()
                    if line.startswith("Requires-Dist:")]
    assert f"ros-{distro}-rclpy[fastrtps]" in requires, requires
    assert not [r for r in requires if r.startswith("ros-") and not r.startswith(f"ros-{distro}-")], requires
    # So pip put no other distribution's wheels beside this one's (they share names such as ros-fastcdr).
    listed = json.loads(_run(venv / "bin" / "python", "-m", "pip", "list", "--format", "json", env=_plain_env()))
    distros = {p["name"].split("-")[1] for p in listed if p["name"].startswith("ros-")} & {"jazzy", "kilted"}
    assert distros == {distro}


def test_the_wheels_carry_the_ament_index_and_executables(venv: Path) -> None:
    components = {
        package: (venv / INDEX / "rclcpp_components" / package).read_text().splitlines()
        for package in ("lifecycle_container", "ldlidar")
    }
    # As the container's own registry lists them (the container wheel's list is written at build).
    registry = PluginRegistry()
    for package, lines in components.items():
        assert lines == sorted(
            f"{t.full_name};{t.node_class.__module__}:{t.node_class.__qualname__}"
            for t in registry.types.values()
            if t.package == package
        )
    for package in ("lifecycle_container", "ldlidar"):
        assert (venv / INDEX / "packages" / package).is_file()
    # Both Fast DDS profiles: container._runtime.dds_profile() picks the one its Fast DDS reads.
    for profile in ("fastdds_profile.xml", "fastdds2_profile.xml"):
        assert (venv / SITE / "container" / profile).is_file()
    for name in EXECUTABLES:
        assert os.access(venv / "lib" / "lifecycle_container" / name, os.X_OK)
    # The command: the wheel's launcher (sh, which starts the virtualenv's Python with the
    # signals held; container/_entry.py), not a console script of pip's, which the kernel starts.
    command = (venv / "bin" / "container").read_text()
    assert command.startswith("#!/bin/sh\n") and "exec env --block-signal=INT,TERM" in command, command
    assert os.access(venv / "bin" / "container", os.X_OK)
    # Where site reads it, before the ROS wheels' bootstrapper's.
    assert (venv / SITE / PTH.name).read_text() == PTH.read_text()
    assert sorted(path.name for path in (venv / SITE).glob("*.pth"))[0] == PTH.name
    found = _run(
        venv / "bin" / "python", "-c",
        "from ament_index_python import get_resources; import json;"
        "print(json.dumps(sorted(get_resources('rclcpp_components'))))",
        env={**_plain_env(), "AMENT_PREFIX_PATH": str(venv)},
    )
    assert json.loads(found) == ["ldlidar", "lifecycle_container"]
    # `container index` is for what was installed some other way: it leaves pip's entries alone.
    indexed = _run(venv / "bin" / "container", "index", env=_plain_env())
    assert indexed.splitlines() == [
        f"ament index of {venv}: up to date",
        "  ldlidar: installed with its wheel",
        "  lifecycle_container: installed with its wheel",
    ]


def test_the_lidar_example_runs_from_the_wheels(venv: Path) -> None:
    env = {**_plain_env(), "PYTHONUNBUFFERED": "1"}
    config = venv / "share" / "lifecycle_container" / "examples" / "lidar.yaml"
    proc = subprocess.Popen(
        [str(venv / "bin" / "container"), "run", str(config), "--ros-args", "-r", "__node:=wheel_container"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        assert proc.stdout is not None
        lines: list[str] = []
        deadline = time.monotonic() + 60
        while not any("ready with 1 node(s)" in line for line in lines):
            assert time.monotonic() < deadline and proc.poll() is None, "".join(lines)
            lines.append(proc.stdout.readline())
        scan = _run(
            venv / "bin" / "python", "-c",
            "import rclpy; from rclpy.node import Node; from sensor_msgs.msg import LaserScan\n"
            "rclpy.init(); node = Node('scan_reader'); got = []\n"
            "node.create_subscription(LaserScan, '/ldlidar/scan', got.append, 10)\n"
            "while not got: rclpy.spin_once(node, timeout_sec=1.0)\n"
            "print(len(got[0].ranges))",
            env=env, timeout=60,
        )
        assert int(scan) == 455
    finally:
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, rest
    assert "Unloaded '/ldlidar'" in rest
    # The project's Fast DDS profile was found and read whole.
    assert not [line for line in [*lines, *rest.splitlines()] if "XMLPARSER" in line], rest


def test_a_plugin_with_its_own_interfaces_installs_and_uninstalls_them(wheels: dict[str, Path], venv: Path) -> None:
    python = venv / "bin" / "python"
    _run(python, "-m", "pip", "install", "--quiet", "--no-deps", wheels["beacon_nodes"])
    assert len(_index_files(venv, "beacon_nodes")) == 2
    made = _run(
        python, "-c",
        "from beacon_interfaces.msg import Beacon; from beacon_interfaces.action import Sweep;"
        "print(Beacon(name='x').name, Sweep.Goal(steps=3).steps)",
        env=_plain_env(),
    )
    assert made.split() == ["x", "3"]
    site = venv / SITE
    generated = [venv / "share" / "beacon_interfaces", site]
    assert (generated[0] / "msg" / "Beacon.msg").is_file()

    _run(python, "-m", "pip", "uninstall", "--yes", "--quiet", "beacon-nodes")

    assert _index_files(venv, "beacon_nodes") == []
    assert not any(path.is_file() for path in generated[0].rglob("*"))
    assert not any((venv / "lib").glob("libbeacon_interfaces__*.so"))
    assert not any(path.is_file() for path in (site / "beacon_interfaces").rglob("*"))


def test_colcon_builds_a_plugin_against_the_containers_wheel(venv: Path, tmp_path: Path) -> None:
    # docs/guide/colcon.md over a plain virtualenv: the ROS wheels, colcon and
    # the container's wheel, with AMENT_PREFIX_PATH and ROS_DISTRO exported.
    workspace = tmp_path / "ws"
    greeter_package(workspace / "src" / "greeter_nodes")
    env = {
        **_plain_env(), "PATH": f"{venv / 'bin'}{os.pathsep}{os.environ['PATH']}",
        "AMENT_PREFIX_PATH": str(venv), "ROS_DISTRO": installed_ros_distro(),
    }
    built = subprocess.run(
        ["colcon", "build", "--event-handlers", "console_cohesion-"],
        cwd=workspace, env=env, capture_output=True, text=True, timeout=300,
    )
    assert built.returncode == 0, built.stdout + built.stderr
    prefix = workspace / "install" / "greeter_nodes"
    assert (prefix / INDEX / "rclcpp_components" / "greeter_nodes").read_text() == (
        "greeter_nodes::Greeter;greeter_nodes:Greeter\n"
    )
    listed = subprocess.run(
        ["bash", "-c", "source install/setup.bash && container types && python -c "
         "'from ament_index_python import get_package_prefix as p; print(p(\"greeter_nodes\"))'"],
        cwd=workspace, env=env, capture_output=True, text=True, timeout=120,
    )
    assert "greeter_nodes\n  greeter_nodes::Greeter\n" in listed.stdout, listed.stdout + listed.stderr
    assert listed.stdout.splitlines()[-1] == str(prefix)
    # The pip layout finds the CMake files the container's wheel installed (configured only).
    shutil.copytree(REPO / "examples" / "beacon_plugin", tmp_path / "beacon", ignore=shutil.ignore_patterns("tests"))
    configured = subprocess.run(
        ["cmake", "-S", tmp_path / "beacon", "-B", tmp_path / "beacon-build", f"-DCMAKE_INSTALL_PREFIX={tmp_path}"],
        env=env, capture_output=True, text=True, timeout=120,
    )
    assert configured.returncode == 0, configured.stdout + configured.stderr
    found = "lifecycle_container: plugin beacon-nodes (ROS package beacon_nodes; Python: beacon_nodes)"
    assert found in configured.stdout
    cache = (tmp_path / "beacon-build" / "CMakeCache.txt").read_text()
    assert f"lifecycle_container_DIR:PATH={venv / 'share' / 'lifecycle_container' / 'cmake'}\n" in cache


def test_pip_uninstall_takes_everything_the_wheels_installed(wheels: dict[str, Path], venv: Path) -> None:
    python = venv / "bin" / "python"
    _run(python, "-m", "pip", "install", "--quiet", "--no-deps", wheels["greeter_nodes"])
    assert len(_index_files(venv, "greeter_nodes")) == 2  # a third-party plugin: marker and component types
    listed = _run(python, "-m", "pip", "show", "--files", "lifecycle-container", "ldlidar")
    assert "share/composition_interfaces/package.xml" in listed
    assert "lifecycle_container/component_container\n" in listed

    _run(python, "-m", "pip", "uninstall", "--yes", "--quiet", "greeter-nodes", "ldlidar", "lifecycle-container")

    for package in ("lifecycle_container", "ldlidar", "greeter_nodes"):
        assert _index_files(venv, package) == []
    for leftover in ("share/composition_interfaces", "share/lifecycle_container", "lib/lifecycle_container"):
        assert not any(path.is_file() for path in (venv / leftover).rglob("*")), leftover
    assert not (venv / "bin" / "container").exists()
    assert not (venv / SITE / PTH.name).exists()
