"""Distribution metadata for a CMake install (colcon) of a Python distribution.

pip gives every installed distribution a ``<name>-<version>.dist-info``
directory, and the container finds its plugins (and pytest its fixtures,
scikit-build-core the CMake files) through the entry points listed there.
colcon installs files, not distributions, so CMake writes it:

* the repository's ``CMakeLists.txt``, at configure time, for each
  distribution it installs (the project and each plugin under ``plugins/``)::

      python dist_info.py OUT_DIR PYPROJECT [PYPROJECT ...]

* ``find_package(lifecycle_container)`` in a plugin's ``CMakeLists.txt``
  (``lifecycle_container-config.cmake``), which first asks what the plugin
  is: its distribution, its ROS package and its Python packages' directories
  (a CMake list; nothing when the project declares no ``container.plugins``
  entry points)::

      python dist_info.py --plugin PYPROJECT

Then ``OUT_DIR`` goes into the prefix's site-packages. ``Requires-Dist``
lists the distribution's requirements on every ROS distribution (the ROS
packages come from the underlay, as ``package.xml`` declares them).

Standard library only: it runs before anything of the project is installed,
from the directory of the CMake files (``share/lifecycle_container/cmake``).
"""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path
from typing import Any

__all__ = ["plugin_info", "write_dist_info"]

#: The entry point group plugins are found by (container._registry.ENTRY_POINT_GROUP).
PLUGIN_GROUP = "container.plugins"


def _normalized(name: str) -> str:
    # The directory name pip writes (PEP 427's escaping of the project name),
    # and the ROS package name of a distribution (container._hookspecs.ros_package_name).
    return re.sub(r"[-_.]+", "_", name).lower()


def _project(pyproject: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """The ``[project]`` table of ``pyproject`` and the whole file.

    :raises ValueError: there is no ``[project]`` table, or its name or version is dynamic.
    """
    with pyproject.open("rb") as file:
        data: dict[str, Any] = tomllib.load(file)
    project = data.get("project")
    if not isinstance(project, dict):
        raise ValueError(f"{pyproject}: no [project] table")
    for key in ("name", "version"):
        if not isinstance(project.get(key), str):
            raise ValueError(f"{pyproject}: [project] {key} must be written out (not dynamic) for a CMake install")
    return project, data


def write_dist_info(out: Path, pyproject: Path) -> Path:
    """Write ``<name>-<version>.dist-info`` for the project of ``pyproject`` into ``out``."""
    project, data = _project(pyproject)
    name, version = project["name"], project["version"]
    requires = [] if "dependencies" in project.get("dynamic", []) else list(project.get("dependencies", []))
    requires += data.get("tool", {}).get("lifecycle-container", {}).get("dependencies", [])
    info = out / f"{_normalized(name)}-{version}.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    metadata = [
        "Metadata-Version: 2.1",
        f"Name: {name}",
        f"Version: {version}",
        f"Summary: {project.get('description', '')}",
        f"Requires-Python: {project.get('requires-python', '')}",
        *(f"Requires-Dist: {requirement}" for requirement in requires),
    ]
    (info / "METADATA").write_text("\n".join(metadata) + "\n", encoding="utf-8")
    (info / "INSTALLER").write_text("colcon\n", encoding="utf-8")
    groups: dict[str, dict[str, str]] = {}
    if project.get("scripts"):
        groups["console_scripts"] = project["scripts"]
    groups.update(project.get("entry-points", {}))
    lines = []
    for group, entries in groups.items():
        lines.append(f"[{group}]")
        lines += [f"{entry} = {target}" for entry, target in entries.items()]
        lines.append("")
    (info / "entry_points.txt").write_text("\n".join(lines), encoding="utf-8")
    return info


def plugin_info(pyproject: Path) -> list[str]:
    """What a CMake build of the plugin ``pyproject`` describes installs, or nothing if it is no plugin.

    :return: its distribution name, its ROS package name, then the directory
        of each of its Python packages (relative to the project), as
        scikit-build-core finds them: ``[tool.scikit-build] wheel.packages``,
        else the first of ``src/<name>``, ``python/<name>``, ``<name>``.
    :raises ValueError: the project cannot be installed this way (and why).
    """
    project, data = _project(pyproject)
    if not project.get("entry-points", {}).get(PLUGIN_GROUP):
        return []
    name: str = project["name"]
    root = pyproject.parent
    packages = data.get("tool", {}).get("scikit-build", {}).get("wheel", {}).get("packages")
    if packages is None:
        module = re.sub(r"[-.]+", "_", name)
        found = [p for p in (f"src/{module}", f"python/{module}", module) if (root / p / "__init__.py").is_file()]
        packages = found[:1]
    if not packages or not all((root / p).is_dir() for p in packages):
        raise ValueError(
            f"{pyproject}: no Python package to install (set [tool.scikit-build] wheel.packages): "
            f"{', '.join(packages) or 'none found'}"
        )
    return [name, _normalized(name), *packages]


def main(argv: list[str]) -> int:
    try:
        if len(argv) == 2 and argv[0] == "--plugin":
            print(";".join(plugin_info(Path(argv[1]))), end="")
            return 0
        if len(argv) < 2 or argv[0].startswith("-"):
            print("usage: dist_info.py OUT_DIR PYPROJECT [PYPROJECT ...] | --plugin PYPROJECT", file=sys.stderr)
            return 2
        for pyproject in argv[1:]:
            write_dist_info(Path(argv[0]), Path(pyproject))
    except (OSError, ValueError, tomllib.TOMLDecodeError) as exc:
        print(f"dist_info.py: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
