"""A plugin built by colcon as an ``ament_python`` package: its component types in the ament index.

colcon builds an ``ament_python`` package with setuptools and installs its
data files, the package marker among them, but nothing lists its node
types: ``ros2 component types`` would not see the plugin. :func:`cmdclass`
gives the plugin's ``setup.py`` the commands colcon installs data files
with (``install_data``, and ``symlink_data`` under ``--symlink-install``),
which also write ``share/ament_index/resource_index/rclcpp_components/<package>``
into the install prefix: one ``<package>::<Type>;<module>:<class>`` line per
node type the plugin registers, listed by importing it from the build in a
separate interpreter. colcon's record of the install lists the file::

    from setuptools import setup

    from container.colcon import cmdclass

    setup(cmdclass=cmdclass())      # name, packages, entry points, data files: setup.cfg

A plugin that fails to import, or registers nothing, fails the build with
the reason. A plugin built with CMake (``ament_cmake``, plain CMake) gets
the same from ``find_package(lifecycle_container)``; a wheel from
:mod:`container.build_backend`.

Standard library and setuptools only at import: it runs inside colcon's
``setup.py`` calls.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from ._errors import PluginError
from ._hookspecs import ros_package_name
from ._plugin_types import list_node_types, parse_entry_points

__all__ = ["cmdclass"]

_GROUP = "container.plugins"
_PACKAGES = "share/ament_index/resource_index/packages"
_COMPONENTS = "share/ament_index/resource_index/rclcpp_components"


def cmdclass() -> dict[str, type]:
    """The ``cmdclass`` of an ``ament_python`` plugin's ``setup()``: data files with its component types."""
    # setuptools first: its distutils (Python 3.12 has none of its own).
    importlib.import_module("setuptools")
    install_data: type = importlib.import_module("distutils.command.install_data").install_data
    commands = {"install_data": _with_components(install_data)}
    try:
        # colcon's own command for --symlink-install, importable where colcon runs setup.py.
        symlink_data: type = importlib.import_module("colcon_core.distutils.commands.symlink_data").symlink_data
    except ImportError:
        pass
    else:
        commands["symlink_data"] = _with_components(symlink_data)
    return commands


def _with_components(base: type) -> type:
    """``base`` (a data files command) that also installs the plugin's ``rclcpp_components`` entry."""

    class Command(base):  # type: ignore[misc]
        def run(self) -> None:
            super().run()
            path = write_components(self.distribution, Path(self.install_dir), build=self._build_lib())
            self.outfiles.append(str(path))

        def _build_lib(self) -> str | None:
            if not self.distribution.have_run.get("build"):
                return None  # develop (--symlink-install): the sources are imported in place
            build_lib: str = self.get_finalized_command("build").build_lib
            return build_lib

    Command.__name__ = Command.__qualname__ = base.__name__
    return Command


def write_components(distribution: Any, prefix: Path, *, build: str | None) -> Path:
    """Write the ``rclcpp_components`` entry of the plugin setuptools' ``distribution`` describes.

    :param prefix: the install prefix (the data files' root).
    :param build: where ``build`` put the modules; ``None`` imports them from the sources.
    :raises PluginError: the distribution declares no plugin, installs no
        package marker of that name, or its plugin cannot be listed.
    """
    name: str = distribution.get_name()
    package = ros_package_name(name)
    plugins = _plugins(distribution.entry_points or {})
    if not plugins:
        raise PluginError(f"no {_GROUP!r} entry points in setup.cfg or setup.py", distribution=name)
    markers = {
        os.path.basename(file)
        for directory, files in _data_files(distribution)
        if directory.strip("/") == _PACKAGES
        for file in files
    }
    if package not in markers:
        raise PluginError(
            f"its node types are {package}::<Type>, but its data files install no package marker "
            f"{_PACKAGES}/{package} (resource/{package}; package.xml's <name> must be {package} too)",
            distribution=name,
        )
    sources = Path.cwd() / (distribution.package_dir or {}).get("", "")
    lines = list_node_types(name, plugins, paths=[p for p in (build, sources) if p is not None])
    if not lines:
        raise PluginError("its plugin registers no node types", distribution=name)
    path = prefix / _COMPONENTS / package
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{line}\n" for line in lines), encoding="utf-8")
    return path


def _plugins(entry_points: Mapping[str, Any] | str) -> dict[str, str]:
    """The ``container.plugins`` group of setuptools' ``entry_points``, name to value."""
    if isinstance(entry_points, str):
        return parse_entry_points(entry_points).get(_GROUP, {})
    group = entry_points.get(_GROUP) or []
    lines = group.splitlines() if isinstance(group, str) else list(group)
    return parse_entry_points(f"[{_GROUP}]\n" + "\n".join(lines)).get(_GROUP, {})


def _data_files(distribution: Any) -> Iterable[tuple[str, list[str]]]:
    for item in distribution.data_files or []:
        if isinstance(item, tuple | list) and len(item) == 2:
            yield str(item[0]), [str(f) for f in item[1]]
