"""The colcon workspace tests/test_colcon.py reads, built in a process of its own from the session's start.

The workspace holds the repository (its tracked files) and three plugins:
radar_nodes (ament_python) with its interface package radar_interfaces,
greeter_nodes (ament_python, no messages) and beacon_nodes (the pip layout:
pyproject.toml and CMakeLists.txt, plus a package.xml). Beside it, in a
workspace of its own, the beacon example's interface package as an ordinary
colcon package. Both are built by ``colcon build`` over a virtualenv of the
ROS wheels (the underlay, as ``source /opt/ros/jazzy/setup.bash`` would be on
a ROS install).

The builds are most of a test leg's CPU time (about 450 s on one CPU), and
most of the other tests wait (discovery, timeouts, windows of seconds). So
:class:`Prebuild` starts them when the session starts, in a process of its
own at the lowest CPU priority (``SCHED_IDLE``: it runs only while nothing
else wants the CPU, and gives it up the moment a test's process wakes), and
test_colcon's tests, moved to the end of the session (tests/conftest.py),
read what it built. A process, not a thread: tests count the test process's
threads. Its output is a JSON file; run as ``python -m tests.colcon_support
ROOT PARENT_PID``.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import FrameType
from typing import Any

from tests.container_support import REPO
from tests.install_support import greeter_package, installed_ros_distro, make_ros_wheels_venv

__all__ = ["PLUGIN_TYPES", "Builds", "Prebuild", "environment"]

#: What ``ros2 component types`` lists for each plugin package the workspace builds.
PLUGIN_TYPES = {
    "beacon_nodes": ["beacon_nodes::Beacon;beacon_nodes:Beacon"],
    "greeter_nodes": ["greeter_nodes::Greeter;greeter_nodes:Greeter"],
    "radar_nodes": ["radar_nodes::Radar;radar_nodes:Radar"],
}

#: Set by .ci/run: the CPUs the builds may use at idle priority (the legs' test processes are each pinned
#: to one of them; the builds then fill what every leg leaves idle).
IDLE_CPUS = "CI_IDLE_CPUS"

#: How long one ``colcon build`` may take at idle priority, starved while tests run.
BUILD_TIMEOUT_S = 3600

#: How long a test waits for what is left of the builds once it needs them (within test_colcon's 900 s).
WAIT_S = 840


@dataclasses.dataclass(frozen=True)
class Builds:
    """The two ``colcon build`` runs, made side by side."""

    #: The underlay: the ROS wheels, the ROS build tools and colcon, nothing of this project.
    underlay: Path
    #: The workspace: the repository (``src/lifecycle_container``) and three plugins beside it.
    workspace: Path
    #: The environment both ran in (the underlay's, as sourced).
    env: dict[str, str]
    #: colcon's output for the workspace, and its exit status.
    output: str
    returncode: int
    #: The workspace of the beacon example's interface package alone, and its colcon's result.
    interfaces: Path
    interfaces_returncode: int
    interfaces_output: str
    #: Whether the builds left the sources and the underlay as they were (colcon writes build/,
    #: install/ and log/ only), and what the workspace holds after them.
    sources_untouched: bool
    workspace_entries: list[str]

    def finished(self, package: str) -> bool:
        """Whether colcon built and installed ``package`` (the workspace's build goes on past a failure)."""
        return re.search(rf"^Finished <<< {package} \[", self.output, flags=re.MULTILINE) is not None

    def to_json(self) -> str:
        return json.dumps({k: str(v) if isinstance(v, Path) else v for k, v in dataclasses.asdict(self).items()})

    @classmethod
    def from_json(cls, text: str) -> Builds:
        fields: dict[str, Any] = json.loads(text)
        for name in ("underlay", "workspace", "interfaces"):
            fields[name] = Path(fields[name])
        return cls(**fields)


def environment(underlay: Path) -> dict[str, str]:
    """What sourcing the underlay gives: its executables first, its prefix on AMENT_PREFIX_PATH."""
    # Not this process's ROS libraries either: the wheels' bootstrapper skips
    # itself when its guard variable is inherited (see tests/test_wheels.py).
    drop = {"VIRTUAL_ENV", "PYTHONPATH", "AMENT_PREFIX_PATH", "LD_LIBRARY_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE"}
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env["PATH"] = f"{underlay / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["AMENT_PREFIX_PATH"] = str(underlay)
    env["ROS_DISTRO"] = installed_ros_distro()
    # Every CPU this process may use, whatever the load. Each interface
    # package's build (an ExternalProject's `cmake --build`) reads
    # CMAKE_BUILD_PARALLEL_LEVEL. And colcon gives make `-j<cores> -l<cores>`
    # unless MAKEFLAGS has a -j: with -l, make starts no second job while the
    # load average is at the core count, which these builds keep it at;
    # measured here, the container's interface packages then built one at a
    # time, one compiler at a time.
    cores = str(len(os.sched_getaffinity(0)))
    env.setdefault("CMAKE_BUILD_PARALLEL_LEVEL", cores)
    env.setdefault("MAKEFLAGS", f"-j{cores}")
    return env


def _snapshot(root: Path) -> dict[str, float]:
    """Every file under ``root`` (bytecode caches aside) with its modification time."""
    return {
        str(path.relative_to(root)): path.stat().st_mtime
        for path in root.rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    }


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


def build(root: Path) -> Builds:
    """The underlay, then both builds, in directories under ``root``.

    One build of the workspace, so that colcon (a worker per core) builds radar_interfaces while the
    container builds, and the plugins that need the container side by side after it; the interface
    package apart, so that the plugins' workspace holds one beacon_interfaces only (the one beacon_nodes
    installs). The container is built as a plain ``colcon build`` builds it; the plugins' packages get the
    one CMake argument that docs/guide/colcon.md gives them over PyPI's wheels, from a colcon metadata
    file outside the workspace. The build goes on past a package's failure, so that the container's
    tests say whether it built whatever became of the plugins.
    """
    underlay = make_ros_wheels_venv(root / "underlay" / "venv")
    workspace = root / "colcon_ws"
    src = workspace / "src"
    _copy_tracked(REPO, src / "lifecycle_container")
    _copy_tracked(REPO / "examples" / "colcon", src)
    _copy_tracked(REPO / "examples" / "beacon_plugin", src / "beacon_plugin")
    greeter_package(src / "greeter_nodes")
    fix = src / "lifecycle_container" / "container" / "cmake" / "ros_wheels.cmake"
    (root / "colcon_meta").mkdir()
    meta = root / "colcon_meta" / "plugins.meta"
    plugins = ["radar_interfaces", *PLUGIN_TYPES]
    meta.write_text(json.dumps({"names": {name: {"cmake-args": [f"-DCMAKE_PROJECT_INCLUDE={fix}"]}
                                          for name in plugins}}))
    # The example plugin's interface package, built as an ordinary colcon
    # package over the wheels (the one CMake argument works around their
    # targets), for test_an_interface_package_built_by_colcon_hashes_as_the_one_pip_built.
    interfaces = root / "colcon_interfaces_ws"
    shutil.copytree(REPO / "examples" / "beacon_plugin" / "beacon_interfaces", interfaces / "src" / "beacon_interfaces")
    env = environment(underlay)
    before = {"src": _snapshot(src), "underlay": _snapshot(underlay)}
    apart = subprocess.Popen(
        ["colcon", "build", "--event-handlers", "console_cohesion-",
         "--cmake-args", f"-DCMAKE_PROJECT_INCLUDE={REPO / 'container' / 'cmake' / 'ros_wheels.cmake'}",
         "-DBUILD_TESTING=OFF"],
        cwd=interfaces, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        result = subprocess.run(
            ["colcon", "build", "--event-handlers", "console_cohesion-", "--continue-on-error", "--metas", meta],
            cwd=workspace, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            timeout=BUILD_TIMEOUT_S,
        )
        apart_output, _ = apart.communicate(timeout=BUILD_TIMEOUT_S)
    finally:
        if apart.poll() is None:
            apart.kill()
            apart.communicate()
    after = {"src": _snapshot(src), "underlay": _snapshot(underlay)}
    return Builds(
        underlay=underlay, workspace=workspace, env=env, output=result.stdout, returncode=result.returncode,
        interfaces=interfaces, interfaces_returncode=apart.returncode, interfaces_output=apart_output,
        sources_untouched=after == before, workspace_entries=sorted(p.name for p in workspace.iterdir()),
    )


class Prebuild:
    """:func:`build`, run by ``python -m tests.colcon_support`` at idle priority; :meth:`result` waits for it."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self._builds: Builds | None = None
        self._log = (root / "prebuild.log").open("wb")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "tests.colcon_support", str(root), str(os.getpid())],
            cwd=REPO, stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT,
            # Its own process group: stop() ends colcon, CMake and the compilers with it.
            start_new_session=True,
        )

    def result(self, *, timeout: float = WAIT_S) -> Builds:
        """What the builds made; the process's output in the failure if it made nothing."""
        if self._builds is not None:
            return self._builds
        try:
            self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.stop()
            raise AssertionError(f"the colcon builds did not end within {timeout:g} s:\n{self._tail()}") from None
        result = self.root / "builds.json"
        if self.process.returncode != 0 or not result.is_file():
            raise AssertionError(f"the colcon builds failed (exit {self.process.returncode}):\n{self._tail()}")
        self._builds = Builds.from_json(result.read_text(encoding="utf-8"))
        return self._builds

    def stop(self) -> None:
        """End the builds if they still run."""
        if self.process.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()
        self._log.close()

    def _tail(self, lines: int = 80) -> str:
        text = (self.root / "prebuild.log").read_text(encoding="utf-8", errors="replace")
        return "\n".join(text.splitlines()[-lines:])


def _end_with_parent(parent: int) -> None:
    """This process group ends when the test process does, however that ends (a timeout's os._exit)."""
    def end(signum: int, frame: FrameType | None) -> None:
        os.killpg(0, signal.SIGKILL)

    signal.signal(signal.SIGTERM, end)
    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM, 0, 0, 0)
    if os.getppid() != parent:  # it ended before the line above
        os.killpg(0, signal.SIGKILL)


def _main(argv: list[str]) -> int:
    root, parent = Path(argv[0]), int(argv[1])
    _end_with_parent(parent)
    # This thread's policy, which the builds' processes inherit.
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    cpus = os.environ.get(IDLE_CPUS)
    if cpus:
        os.sched_setaffinity(0, {int(cpu) for cpu in cpus.split(",")})
    started = time.monotonic()
    builds = build(root)
    (root / "builds.json.part").write_text(builds.to_json(), encoding="utf-8")
    (root / "builds.json.part").rename(root / "builds.json")
    print(f"colcon builds: done in {time.monotonic() - started:.0f} s at idle priority", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
