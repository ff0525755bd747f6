"""Parameters as ROS users write them: launch-style dicts and parameter files.

A node's parameters come from a list, in order, later entries winning, as in
launch_ros: inline mappings (nested keys joined with ``.``) and standard ROS
parameter files (``node_name: {ros__parameters: {...}}``, ``/**`` for every
node). rclpy reads the files; this module only picks the entries that apply
to one node and turns everything into ``rclpy.parameter.Parameter`` overrides.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import yaml
from rcl_interfaces.msg import Parameter as ParameterMsg
from rclpy.parameter import Parameter, parameter_dict_from_yaml_file

from ._errors import ConfigError
from ._text import clip
from ._yaml import read_yaml

__all__ = ["ParameterSource", "node_parameters", "parameters_from_mapping"]

#: One entry of a node's ``parameters`` list: a mapping, or a file path.
ParameterSource = Mapping[str, Any] | str | Path


def parameters_from_mapping(values: Mapping[str, Any], *, source: str) -> list[Parameter[Any]]:
    """Turn ``{"a": {"b": 1}}`` into the override ``a.b = 1``."""
    parameters: list[Parameter[Any]] = []
    for name, value in _flatten(values, prefix=""):
        try:
            parameters.append(Parameter(name, value=value))
        except (TypeError, ValueError, AttributeError) as exc:
            raise ConfigError(
                f"parameter {clip(name, quote=True)}: value {clip(value, quote=True)} is not a ROS parameter value "
                f"({clip(str(exc))})",
                source=source,
            ) from exc
    return parameters


def parameters_from_file(path: Path, *, node_names: Iterable[str]) -> list[Parameter[Any]]:
    """Read the entries of a ROS parameter file that apply to a node.

    :param node_names: the keys that name the node (full name, with and
        without the leading slash, plain name); ``/**`` always applies.
    """
    content = read_yaml(path)
    if not isinstance(content, dict):
        raise ConfigError("a ROS parameter file maps node names to ros__parameters", source=str(path))
    targets = [name for name in node_names if name in content]
    if not targets and "/**" not in content:
        return []
    try:
        messages: dict[str, ParameterMsg] = parameter_dict_from_yaml_file(
            str(path), use_wildcard=True, target_nodes=targets
        )
    except (RuntimeError, yaml.YAMLError) as exc:
        raise ConfigError(str(exc), source=str(path)) from exc
    return [Parameter.from_parameter_msg(message) for message in messages.values()]


def node_parameters(
    sources: Iterable[ParameterSource],
    *,
    full_name: str,
    base_dir: Path | None = None,
    source: str = "parameters",
) -> list[Parameter[Any]]:
    """Collect a node's overrides from its ``parameters`` list, later winning."""
    name = full_name.rsplit("/", 1)[-1]
    keys = [full_name, full_name.lstrip("/"), name]
    merged: dict[str, Parameter[Any]] = {}
    for index, entry in enumerate(sources):
        where = f"{source}[{index}]"
        if isinstance(entry, Mapping):
            found = parameters_from_mapping(entry, source=where)
        elif isinstance(entry, (str, Path)):
            path = Path(entry)
            if base_dir is not None and not path.is_absolute():
                path = base_dir / path
            found = parameters_from_file(path, node_names=keys)
        else:
            raise ConfigError(
                f"expected a mapping or a parameter file path, not {type(entry).__name__}",
                source=where,
            )
        for parameter in found:
            merged[parameter.name] = parameter
    return list(merged.values())


def _flatten(values: Mapping[str, Any], *, prefix: str) -> Iterable[tuple[str, Any]]:
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            yield from _flatten(value, prefix=f"{name}.")
        else:
            yield name, value
