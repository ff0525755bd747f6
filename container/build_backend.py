"""A PEP 517 build backend for plugin distributions: their wheels carry their ament index entries.

ROS tools (``ros2 pkg list``, ``ros2 component types``, launch_ros) find
packages and component types in the ament index, files under
``<prefix>/share/ament_index``. A plugin built with this backend gets them as
data files of its wheel, so ``pip install`` puts them in the environment and
``pip uninstall`` removes them: no ``container index`` to run. In the
plugin's ``pyproject.toml``::

    [build-system]
    requires = ["setuptools>=68", "lifecycle-container"]
    build-backend = "container.build_backend"

It builds with setuptools (or with scikit-build-core when the project has a
``[tool.scikit-build]`` table: a plugin with interface packages of its own),
then, if the wheel declares ``container.plugins`` entry points, imports the
plugin from the built wheel in a separate interpreter to list its node types
and adds

* ``share/ament_index/resource_index/packages/<package>`` (an empty marker) and
* ``share/ament_index/resource_index/rclcpp_components/<package>`` (one
  ``<package>::<Type>;<module>:<class>`` line per type)

where ``<package>`` is the distribution's name as a ROS package name. A
plugin whose import fails at build time still gets its marker; the failure
is printed and the build goes on (the container reports the same failure
when it loads).

``build-backend = "scikit_build_core.build"`` would build such a plugin's
wheel without these entries, silently; ``find_package(lifecycle_container)``
refuses that (it sees ``LIFECYCLE_CONTAINER_BUILD_BACKEND``, which this
backend sets while scikit-build-core builds). colcon builds of a plugin get
the same entries from :mod:`container.colcon` (``ament_python``) or from
``find_package(lifecycle_container)`` (CMake).

Standard library only at import (plus the chosen backend): it runs inside
pip's build, before anything of ROS needs to load.
"""

from __future__ import annotations

import base64
import contextlib
import csv
import hashlib
import importlib
import io
import os
import sys
import tempfile
import tomllib
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ._errors import PluginError
from ._hookspecs import ros_package_name
from ._plugin_types import list_node_types, parse_entry_points

__all__ = [
    "build_editable",
    "build_sdist",
    "build_wheel",
    "get_requires_for_build_editable",
    "get_requires_for_build_sdist",
    "get_requires_for_build_wheel",
    "prepare_metadata_for_build_editable",
    "prepare_metadata_for_build_wheel",
]

_GROUP = "container.plugins"
_INDEX = "share/ament_index/resource_index"
#: Set while the inner backend builds (lifecycle_container-config.cmake reads it).
_MARK = "LIFECYCLE_CONTAINER_BUILD_BACKEND"


def _inner() -> Any:
    """The backend that builds the project: scikit-build-core's if configured, else setuptools'."""
    try:
        with open("pyproject.toml", "rb") as file:
            tool = tomllib.load(file).get("tool", {})
    except FileNotFoundError:
        tool = {}
    name = "scikit_build_core.build" if "scikit-build" in tool else "setuptools.build_meta"
    return importlib.import_module(name)


@contextlib.contextmanager
def _through_this_backend() -> Iterator[None]:
    """Tell ``find_package(lifecycle_container)`` in the build that this backend adds the index entries.

    (It refuses a plugin built by scikit-build-core's backend alone, whose
    wheel would silently lack them.)
    """
    previous = os.environ.get(_MARK)
    os.environ[_MARK] = "1"
    try:
        yield
    finally:
        if previous is None:
            del os.environ[_MARK]
        else:
            os.environ[_MARK] = previous


def get_requires_for_build_wheel(config_settings: dict[str, Any] | None = None) -> list[str]:
    requires: list[str] = _inner().get_requires_for_build_wheel(config_settings)
    return requires


def get_requires_for_build_editable(config_settings: dict[str, Any] | None = None) -> list[str]:
    requires: list[str] = _inner().get_requires_for_build_editable(config_settings)
    return requires


def get_requires_for_build_sdist(config_settings: dict[str, Any] | None = None) -> list[str]:
    requires: list[str] = _inner().get_requires_for_build_sdist(config_settings)
    return requires


def prepare_metadata_for_build_wheel(metadata_directory: str, config_settings: dict[str, Any] | None = None) -> str:
    name: str = _inner().prepare_metadata_for_build_wheel(metadata_directory, config_settings)
    return name


def prepare_metadata_for_build_editable(metadata_directory: str, config_settings: dict[str, Any] | None = None) -> str:
    name: str = _inner().prepare_metadata_for_build_editable(metadata_directory, config_settings)
    return name


def build_sdist(sdist_directory: str, config_settings: dict[str, Any] | None = None) -> str:
    name: str = _inner().build_sdist(sdist_directory, config_settings)
    return name


def build_wheel(
    wheel_directory: str, config_settings: dict[str, Any] | None = None, metadata_directory: str | None = None
) -> str:
    with _through_this_backend():
        name: str = _inner().build_wheel(wheel_directory, config_settings, metadata_directory)
    add_index_entries(Path(wheel_directory) / name, source=Path.cwd())
    return name


def build_editable(
    wheel_directory: str, config_settings: dict[str, Any] | None = None, metadata_directory: str | None = None
) -> str:
    with _through_this_backend():
        name: str = _inner().build_editable(wheel_directory, config_settings, metadata_directory)
    add_index_entries(Path(wheel_directory) / name, source=Path.cwd())
    return name


def add_index_entries(wheel: Path, *, source: Path) -> None:
    """Add the ament index entries of the plugin ``wheel`` holds to it, in place.

    :param source: the project's source directory, importable in place of
        the wheel's contents for an editable wheel.
    """
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
        info = next(n.split("/")[0] for n in names if n.endswith(".dist-info/METADATA"))
        entry_points = archive.read(f"{info}/entry_points.txt").decode() if f"{info}/entry_points.txt" in names else ""
        metadata = archive.read(f"{info}/METADATA").decode()
    plugins = parse_entry_points(entry_points).get(_GROUP, {})
    if not plugins:
        return
    distribution = next(line.split(":", 1)[1].strip() for line in metadata.splitlines() if line.startswith("Name:"))
    package = ros_package_name(distribution)
    lines = _node_types(wheel, distribution=distribution, plugins=plugins, source=source)
    data = info.replace(".dist-info", ".data") + "/data"
    files = {f"{data}/{_INDEX}/packages/{package}": b""}
    if lines:
        files[f"{data}/{_INDEX}/rclcpp_components/{package}"] = "".join(f"{line}\n" for line in lines).encode()
    _append(wheel, info, files)


def _node_types(wheel: Path, *, distribution: str, plugins: dict[str, str], source: Path) -> list[str]:
    """The ``rclcpp_components`` lines of the plugin, listed by importing it from the wheel."""
    with tempfile.TemporaryDirectory(prefix="container-index-") as directory:
        root = Path(directory)
        with zipfile.ZipFile(wheel) as archive:
            archive.extractall(root)
        paths = [root, source]
        libraries = []
        for data in root.glob("*.data/data"):
            paths += data.glob("lib/python*/site-packages")
            libraries.append(data / "lib")
        try:
            return list_node_types(distribution, plugins, paths=paths, libraries=libraries, cwd=root)
        except PluginError as exc:
            print(
                f"container.build_backend: {exc.reason} (the wheel of {distribution} gets no rclcpp_components entry)",
                file=sys.stderr,
            )
            return []


def _append(wheel: Path, info: str, files: dict[str, bytes]) -> None:
    """Add ``files`` to ``wheel`` and to its RECORD."""
    record_name = f"{info}/RECORD"
    with zipfile.ZipFile(wheel) as archive:
        record = archive.read(record_name).decode()
        members = [(item, archive.read(item.filename)) for item in archive.infolist() if item.filename != record_name]
    rows = [row for row in csv.reader(io.StringIO(record)) if row and row[0] != record_name]
    for name, content in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(content).digest()).rstrip(b"=").decode()
        rows.append([name, f"sha256={digest}", str(len(content))])
    rows.append([record_name, "", ""])
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(rows)
    temporary = wheel.with_suffix(".tmp")
    with zipfile.ZipFile(temporary, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for item, content in members:
            archive.writestr(item, content)
        for name, content in files.items():
            archive.writestr(name, content)
        archive.writestr(record_name, out.getvalue())
    temporary.replace(wheel)
