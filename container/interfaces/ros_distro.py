"""The ROS 2 distribution a build is for, and what each one needs.

The generated interface packages and the executor's compiled path are built
against one distribution's rosidl and rcl: a build is for Jazzy or for
Kilted, never both, so the distribution is chosen when building (the
``ROS_DISTRO`` variable; unset, the one whose rclpy the build's environment
holds, as a build without isolation has; else ``jazzy``) and pins what the
result depends on. The requirements live in one table,
``[tool.lifecycle-container]`` in ``pyproject.toml``; this module reads it
for its two users:

* scikit-build-core, as an in-tree dynamic-metadata provider: the
  distribution's packages become the build's requirements and the
  distribution's run-time packages the wheel's dependencies;
* ``.ci/setup``, which runs this file (``python ros_distro.py
  build-requires``) to install the build requirements itself before an
  install without build isolation.

Standard library only: it runs inside pip's isolated build environments and
before the virtualenv has anything installed.
"""

from __future__ import annotations

import importlib.metadata
import os
import sys
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "UnsupportedDistroError",
    "build_requires",
    "chosen",
    "dynamic_metadata",
    "get_requires_for_dynamic_metadata",
    "run_requires",
    "supported",
]

#: The project's pyproject.toml (this file is container/interfaces/ros_distro.py).
PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"

#: The variable that chooses the distribution, as ROS's own setup files set it.
VARIABLE = "ROS_DISTRO"


class UnsupportedDistroError(ValueError):
    """``ROS_DISTRO`` names a distribution the project has no table for."""

    def __init__(self, name: str, known: list[str]) -> None:
        super().__init__(f"ROS_DISTRO={name} is not supported (supported: {', '.join(known)})")
        self.name = name
        self.known = known


def _table() -> dict[str, Any]:
    with PYPROJECT.open("rb") as file:
        table: dict[str, Any] = tomllib.load(file)["tool"]["lifecycle-container"]
    return table


def supported() -> list[str]:
    """The distributions the project builds for, the default first."""
    table = _table()
    default: str = table["default-distro"]
    return [default, *(name for name in table["distros"] if name != default)]


def chosen(environ: Mapping[str, str] = os.environ) -> str:
    """The distribution ``environ`` asks for (``ROS_DISTRO``), else the one installed, else the default.

    Without ``ROS_DISTRO`` (a virtualenv of PyPI wheels sets none until its
    activate script runs), a build without isolation (``pip wheel
    --no-build-isolation``, ``pip install -e``) compiles against whichever
    distribution's wheels the environment holds: the wheel's dependencies
    must name that one. A wheel built in a Kilted environment that asked for
    Jazzy's rclpy made pip put Jazzy's ``ros-fastcdr`` under Kilted's
    generated libraries, which then failed to load.

    :raises UnsupportedDistroError: it asks for one without a table.
    """
    known = supported()
    name = environ.get(VARIABLE) or _installed(known) or known[0]
    if name not in known:
        raise UnsupportedDistroError(name, known)
    return name


def _installed(known: list[str]) -> str | None:
    """The one distribution of ``known`` whose rclpy wheel this environment holds (``None``: none, or several)."""
    found = [name for name in known if _has_distribution(f"ros-{name}-rclpy")]
    return found[0] if len(found) == 1 else None


def _has_distribution(name: str) -> bool:
    try:
        importlib.metadata.distribution(name)
    except importlib.metadata.PackageNotFoundError:
        return False
    return True


def build_requires(distro: str) -> list[str]:
    """What building the interfaces and the compiled path needs for ``distro``."""
    requires: list[str] = _table()["distros"][distro]["build-requires"]
    return list(requires)


def run_requires(distro: str) -> list[str]:
    """What the installed project needs at run time on ``distro``."""
    table = _table()
    return [*table["dependencies"], *table["distros"][distro]["dependencies"]]


# -- scikit-build-core's dynamic-metadata hooks --------------------------------


def dynamic_metadata(settings: Mapping[str, Any], project: Mapping[str, Any]) -> dict[str, Any]:
    """``[project]`` fields that depend on the distribution built for."""
    return {"dependencies": run_requires(chosen())}


def get_requires_for_dynamic_metadata(settings: Mapping[str, Any]) -> list[str]:
    """The distribution's build requirements, for pip's isolated build environment."""
    return build_requires(chosen())


def _main(argv: list[str]) -> int:
    """``ros_distro.py {chosen|build-requires|run-requires}``: one line or one requirement per line."""
    try:
        distro = chosen()
    except UnsupportedDistroError as error:
        print(error, file=sys.stderr)
        return 2
    if argv == ["chosen"]:
        print(distro)
    elif argv == ["build-requires"]:
        print("\n".join(build_requires(distro)))
    elif argv == ["run-requires"]:
        print("\n".join(run_requires(distro)))
    else:
        print("usage: ros_distro.py {chosen|build-requires|run-requires}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
