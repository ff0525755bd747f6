"""Fresh virtualenvs of ROS wheels, for the tests of how users install (colcon, wheels)."""

from __future__ import annotations

import importlib.metadata
import os
import shutil
import subprocess
import sys
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from tests.container_support import REPO


def installed_ros_distro() -> str:
    """The ROS distribution whose rclpy wheel this test environment has."""
    for distro in ("jazzy", "kilted"):
        try:
            importlib.metadata.distribution(f"ros-{distro}-rclpy")
        except importlib.metadata.PackageNotFoundError:
            continue
        return distro
    raise AssertionError("no ros-<distro>-rclpy installed in the test environment")


def _installed_closure(requirements: list[str]) -> list[str]:
    """``name==version`` of every distribution in this environment that ``requirements`` need, theirs
    included: the versions installed here, read from their metadata."""
    extras: dict[str, set[str]] = {}
    todo = [Requirement(line) for line in requirements]
    while todo:
        requirement = todo.pop()
        name = canonicalize_name(requirement.name)
        if name in extras and set(requirement.extras) <= extras[name]:
            continue
        extras[name] = extras.get(name, set()) | set(requirement.extras)
        try:
            distribution = importlib.metadata.distribution(name)
        except importlib.metadata.PackageNotFoundError:
            raise AssertionError(f"{requirement}: needed for the ROS wheels' virtualenv, not installed here") from None
        for line in distribution.requires or []:
            dependency = Requirement(line)
            wanted = extras[name] or {""}
            if dependency.marker is None or any(dependency.marker.evaluate({"extra": e}) for e in wanted):
                todo.append(dependency)
    return sorted(f"{name}=={importlib.metadata.version(name)}" for name in extras)


def make_ros_wheels_venv(prefix: Path) -> Path:
    """A new virtualenv at ``prefix`` with the ROS wheels, the ROS build tools and colcon: nothing of this project.

    The ROS wheels and the build tools are the ones this environment has, at the versions it has
    (``.ci/setup`` resolved them), installed by name and version without resolving again; colcon, which
    this environment lacks, is then resolved and installed beside them. pip comes in the first install
    (``venv`` would install its own copy, slower)."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(prefix)], check=True, timeout=120)
    python = prefix / "bin" / "python"
    ros_distro = REPO / "container" / "interfaces" / "ros_distro.py"
    env = {**os.environ, "ROS_DISTRO": installed_ros_distro()}
    requirements = [
        line
        for kind in ("run-requires", "build-requires")
        for line in subprocess.run(
            [sys.executable, str(ros_distro), kind], env=env, check=True, capture_output=True, text=True
        ).stdout.split()
    ]
    pinned = _installed_closure([*requirements, "numpy", "cmake>=3.21", "pip"])
    for args in (
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", *pinned],
        [str(python), "-m", "pip", "install", "colcon-common-extensions"],
    ):
        result = subprocess.run([*args, "--quiet", "--no-compile"], capture_output=True, text=True, timeout=600)
        assert result.returncode == 0, result.stdout + result.stderr
    return prefix


def greeter_package(destination: Path) -> Path:
    """A colcon plugin without messages of its own at ``destination``: examples/colcon/radar_nodes' files
    without its interface package, around the third-party example's module (docs/guide/colcon.md)."""
    radar = REPO / "examples" / "colcon" / "radar_nodes"
    for name in ("package.xml", "setup.cfg", "setup.py"):
        text = (radar / name).read_text(encoding="utf-8")
        text = text.replace("  <depend>radar_interfaces</depend>\n", "").replace("radar_nodes", "greeter_nodes")
        assert "radar" not in text.replace("radar_nodes", ""), name
        (destination / name).parent.mkdir(parents=True, exist_ok=True)
        (destination / name).write_text(text, encoding="utf-8")
    (destination / "resource").mkdir()
    (destination / "resource" / "greeter_nodes").touch()
    shutil.copytree(
        REPO / "examples" / "thirdparty_plugin" / "greeter_nodes", destination / "greeter_nodes",
        ignore=shutil.ignore_patterns("__pycache__"),
    )
    return destination


#: The reload tests' and benchmark's plugin project (tests/test_reload.py, tests/benchmarks/bench_reload.py).
RELOAD_PROBE_PYPROJECT = """\
[build-system]
requires = ["setuptools>=64"]
build-backend = "setuptools.build_meta"

[project]
name = "reload-probe"
version = "0.1"

[project.entry-points."container.plugins"]
reload_probe = "reload_probe.plugin"
"""


def install_reload_probe(directory: Path, plugin: str, *, editable: bool = True) -> tuple[Path, list[str]]:
    """The ``reload-probe`` plugin (its module ``reload_probe.plugin`` is ``plugin``) installed with pip into a
    prefix under ``directory``: ``--editable`` (setuptools' compat mode, a path in a ``.pth``) or plainly.

    :return: the plugin module's file to edit (the project's in editable mode, the installed one else), and the
        PYTHONPATH entries that see the install as site.py would (the prefix's site-packages, then what its
        ``.pth`` adds): the test environment stays as set up.
    """
    project = directory / "reload-probe"
    (project / "src" / "reload_probe").mkdir(parents=True)
    (project / "pyproject.toml").write_text(RELOAD_PROBE_PYPROJECT, encoding="utf-8")
    (project / "src" / "reload_probe" / "__init__.py").write_text("", encoding="utf-8")
    (project / "src" / "reload_probe" / "plugin.py").write_text(plugin, encoding="utf-8")
    prefix = directory / "prefix"
    how = ["--config-settings", "editable_mode=compat", "--editable", str(project)] if editable else [str(project)]
    result = subprocess.run(
        [
            sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
            "--no-compile", "--prefix", str(prefix), *how,
        ],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    site = prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    source = (project / "src" if editable else site) / "reload_probe" / "plugin.py"
    assert source.is_file()
    paths = [
        line.strip()
        for pth in site.glob("*.pth")
        for line in pth.read_text(encoding="utf-8").splitlines()
        if line.strip() and not line.startswith(("#", "import"))
    ]
    assert paths == ([str(project / "src")] if editable else []), paths
    return source, [str(site), *paths]
