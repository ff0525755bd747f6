"""For the tests that start the container the way ROS tools do.

An executable found through the ament index, launch_ros's argument list, a
network namespace, rather than ``python -m container run FILE``: any command
as a :class:`LoggedProcess` (shared with ``container_support``), and the times
its log lines carry.

ros2cli and launch_ros are not on PyPI; what they do is reproduced here
step by step: ``ExecutableInPackage`` (:func:`executable_in_package`), the
parameters file a ``Node`` or ``ComposableNodeContainer`` writes for
``parameters=[{...}]`` (:func:`launch_params_file`), the command line it
starts (:func:`container_command`) and the LoadNode request
``get_composable_node_load_request`` makes of a ``ComposableNode``
(:func:`composable_node_request`).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import yaml
from ament_index_python import get_package_prefix
from composition_interfaces.srv import LoadNode
from rcl_interfaces.msg import Parameter as ParameterMsg
from rclpy.parameter import Parameter

from tests.container_support import LoggedProcess

__all__ = [
    "LoggedProcess",
    "composable_node_request",
    "container_command",
    "executable_in_package",
    "flattened",
    "launch_params_file",
    "log_time",
    "venv_ament_prefix_path",
]

#: rcutils' console format: ``[INFO] [1795457363.349322609] [logger]: message``.
_STAMP = re.compile(r"^\[\w+\] \[(\d+\.\d+)\]")

VENV_ACTIVATE = Path(sys.prefix) / "bin" / "activate"


def log_time(line: str) -> float:
    """The wall-clock time an rcutils log line carries."""
    match = _STAMP.match(line)
    if match is None:
        raise AssertionError(f"not an rcutils log line with a time stamp: {line!r}")
    return float(match.group(1))


def venv_ament_prefix_path() -> str:
    """AMENT_PREFIX_PATH as the virtualenv's activation sets it."""
    result = subprocess.run(
        ["bash", "-c", f'unset AMENT_PREFIX_PATH; . "{VENV_ACTIVATE}"; printf %s "$AMENT_PREFIX_PATH"'],
        capture_output=True, text=True, timeout=30, check=True,
    )
    return result.stdout


def executable_in_package(package: str, executable: str) -> str:
    """launch_ros's ExecutableInPackage: the prefix from the index, then lib/<package>, searched like which."""
    libexec = os.path.join(get_package_prefix(package), "lib", package)
    assert os.path.isdir(libexec), f"package {package!r} has no libexec directory {libexec}"
    found = shutil.which(executable, path=libexec)
    assert found is not None, f"executable {executable!r} not found in {libexec}"
    return found


def launch_params_file(directory: Path, node_name: str, parameters: dict[str, Any]) -> Path:
    """What launch_ros's Node writes for ``parameters=[{...}]`` of a fully named node."""
    path = directory / f"launch_params_{node_name.strip('/').replace('/', '_')}"
    path.write_text(yaml.dump({node_name: {"ros__parameters": parameters}}, default_flow_style=False))
    return path


def container_command(executable: str, *, name: str, namespace: str, params_file: Path) -> list[str]:
    """The command line launch_ros starts for a ComposableNodeContainer(name=, namespace=, parameters=[{...}])."""
    return [
        executable, "--ros-args", "-r", f"__node:={name}", "-r", f"__ns:={namespace}", "--params-file", str(params_file)
    ]


def flattened(parameters: dict[str, Any], prefix: str = "") -> list[ParameterMsg]:
    """launch_ros's to_parameters_list for a dict: nested keys joined with '.', one message each."""
    messages = []
    for key, value in parameters.items():
        if isinstance(value, dict):
            messages.extend(flattened(value, f"{prefix}{key}."))
        else:
            messages.append(Parameter(f"{prefix}{key}", value=value).to_parameter_msg())
    return messages


def composable_node_request(
    *,
    package: str,
    plugin: str,
    name: str,
    namespace: str,
    remappings: list[tuple[str, str]] = [],  # noqa: B006 (never mutated)
    parameters: dict[str, Any] | None = None,
    extra_arguments: dict[str, Any] | None = None,
) -> LoadNode.Request:
    """What get_composable_node_load_request sends for one ComposableNode (no ros_namespace pushed)."""
    request = LoadNode.Request()
    request.package_name = package
    request.plugin_name = plugin
    request.node_name = name
    request.node_namespace = namespace if namespace.startswith("/") else f"/{namespace}"
    request.remap_rules = [f"{source}:={target}" for source, target in remappings]
    request.parameters = flattened(parameters or {})
    request.extra_arguments = flattened(extra_arguments or {})
    return request
