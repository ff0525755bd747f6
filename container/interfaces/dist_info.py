"""Write the distribution metadata a colcon install of the repository needs.

pip gives every installed distribution a ``<name>-<version>.dist-info``
directory, and the container finds its plugins (and pytest its fixtures,
scikit-build-core the CMake files) through the entry points listed there.
colcon installs files, not distributions, so the repository's ``CMakeLists.txt``
runs this at configure time for each distribution it installs (the project
and each plugin under ``plugins/``)::

    python dist_info.py OUT_DIR PYPROJECT [PYPROJECT ...]

and installs ``OUT_DIR`` into the prefix's site-packages. ``Requires-Dist``
lists the distribution's requirements on every ROS distribution (the ROS
packages come from the underlay, as ``package.xml`` declares them).

Standard library only: it runs before anything of the project is installed.
"""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path
from typing import Any

__all__ = ["write_dist_info"]


def _normalized(name: str) -> str:
    # The directory name pip writes (PEP 427's escaping of the project name).
    return re.sub(r"[-_.]+", "_", name).lower()


def write_dist_info(out: Path, pyproject: Path) -> Path:
    """Write ``<name>-<version>.dist-info`` for the project of ``pyproject`` into ``out``."""
    with pyproject.open("rb") as file:
        data: dict[str, Any] = tomllib.load(file)
    project = data["project"]
    name, version = project["name"], project["version"]
    requires = list(project.get("dependencies", []))
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


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print("usage: dist_info.py OUT_DIR PYPROJECT [PYPROJECT ...]", file=sys.stderr)
        return 2
    out = Path(argv[0])
    for pyproject in argv[1:]:
        write_dist_info(out, Path(pyproject))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
