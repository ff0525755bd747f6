"""A plugin's ``rclcpp_components`` lines, listed at build time by importing it.

The build backend (a wheel) and colcon's builds (:mod:`container.colcon`,
``find_package(lifecycle_container)``) write a plugin's component types into
the ament index when it is built, before it is installed: the plugin is
imported in a separate interpreter, from where the build put it, and
registered the way the container registers it. Standard library only at
import: it runs inside builds.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

from ._errors import PluginError

__all__ = ["list_node_types", "parse_entry_points"]

_LIST_TYPES = """
import json, sys
from container._registry import PluginRegistry
import importlib
registry = PluginRegistry(group="container.build.none")
distribution, plugins = sys.argv[1], json.loads(sys.argv[2])
for name, value in plugins.items():
    module, _, attribute = value.partition(":")
    plugin = importlib.import_module(module.strip())
    for part in filter(None, attribute.strip().split(".")):
        plugin = getattr(plugin, part)
    registry.add_plugin(plugin, distribution=distribution)
for t in sorted(registry.types.values(), key=lambda t: t.full_name):
    print(f"{t.full_name};{t.node_class.__module__}:{t.node_class.__qualname__}")
"""


def list_node_types(
    distribution: str,
    plugins: Mapping[str, str],
    *,
    paths: Sequence[str | Path],
    libraries: Sequence[str | Path] = (),
    cwd: str | Path | None = None,
) -> list[str]:
    """The ``<package>::<Type>;<module>:<class>`` lines of the node types ``plugins`` register.

    :param plugins: the distribution's ``container.plugins`` entry points, name to ``module[:attribute]``.
    :param paths: put first on the interpreter's ``PYTHONPATH`` (where the build put the plugin).
    :param libraries: put first on ``LD_LIBRARY_PATH`` (interface packages built with it).
    :raises PluginError: the plugin could not be imported or registered; the
        interpreter's error output is the reason.
    """
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([*map(str, paths), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env["LD_LIBRARY_PATH"] = os.pathsep.join([*map(str, libraries), env.get("LD_LIBRARY_PATH", "")]).rstrip(
        os.pathsep
    )
    try:
        result = subprocess.run(
            [sys.executable, "-c", _LIST_TYPES, distribution, json.dumps(dict(plugins))],
            capture_output=True,
            text=True,
            env=env,
            cwd=cwd,
            timeout=300,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise PluginError(f"could not list its node types: {exc}", distribution=distribution) from exc
    if result.returncode != 0:
        raise PluginError(
            f"could not list its node types:\n{result.stderr.strip()}", distribution=distribution
        )
    return [line for line in result.stdout.splitlines() if "::" in line]


def parse_entry_points(text: str) -> dict[str, dict[str, str]]:
    """The groups of an ``entry_points.txt`` (an ini file), each entry's name to its value."""
    groups: dict[str, dict[str, str]] = {}
    current: dict[str, str] | None = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = groups.setdefault(line[1:-1].strip(), {})
        elif current is not None and "=" in line:
            name, _, value = line.partition("=")
            current[name.strip()] = value.strip()
    return groups
