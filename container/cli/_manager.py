"""``container manager [FILE] [-p name:=value]... [--ros-args ...]``: a lifecycle manager process.

``FILE`` may be a container file (its ``manager:`` section is used), a Nav2
parameter file (``lifecycle_manager: {ros__parameters: {...}}``), or a plain
mapping of the manager's settings. ``-p`` overrides single parameters, with
YAML values: ``-p node_names:=[/talker,/listener] -p autostart:=true``.
ROS arguments apply to the manager node with rcl's semantics, as to Nav2's
``lifecycle_manager``: ``--ros-args -r __node:=NAME --params-file nav2.yaml``
(what launch_ros passes to the registered ``lifecycle_manager`` executable);
the file and ``-p`` above win over them.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

import yaml

from .._config import read_yaml
from .._errors import ConfigError
from .._runtime import configure_logging
from ._types import name_value

if TYPE_CHECKING:
    from .._compat import SubParsers

__all__ = ["add_parser"]


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "manager",
        help="run a lifecycle manager (Nav2-compatible) as its own process",
        description="Run a lifecycle manager until SIGINT or SIGTERM.",
    )
    parser.add_argument("file", nargs="?", help="container file, Nav2 parameter file or settings")
    parser.add_argument("--name", help="the manager node's name (default: lifecycle_manager)")
    parser.add_argument("--namespace", help="the manager node's namespace (default: /)")
    parser.add_argument(
        "-p",
        "--param",
        action="append",
        default=[],
        metavar="NAME:=VALUE",
        type=name_value,
        help="set a parameter (YAML value); repeatable",
    )
    parser.set_defaults(handler=_run, finish_without_output=True)


def _settings_mapping(path: str) -> dict[str, Any]:
    document = read_yaml(path)
    if document is None:
        return {}
    if not isinstance(document, dict):
        raise ConfigError("expected a mapping", source=path)
    if "manager" in document:
        section = document["manager"]
        if not isinstance(section, dict):
            raise ConfigError("expected a mapping", source=f"{path}: manager")
        return dict(section)
    if len(document) == 1:
        (name, body), = document.items()
        if isinstance(body, dict) and "ros__parameters" in body:
            parameters = body["ros__parameters"]
            if not isinstance(parameters, dict):
                raise ConfigError("expected a mapping", source=f"{path}: {name}.ros__parameters")
            settings = dict(parameters)
            if name not in ("/**", "**"):
                settings.setdefault("name", str(name).rsplit("/", 1)[-1])
            return settings
    return dict(document)


def _run(args: argparse.Namespace) -> int:
    configure_logging()
    from .._app import run_manager
    from ..lifecycle import ManagerSettings

    try:
        mapping = _settings_mapping(args.file) if args.file else {}
        for name, value in args.param:
            mapping[name] = yaml.safe_load(value)
        if args.name:
            mapping["name"] = args.name
        if args.namespace:
            mapping["namespace"] = args.namespace
        settings = ManagerSettings.from_mapping(mapping, source=args.file or "manager")
    except ConfigError as exc:
        print(f"container manager: {exc}", file=sys.stderr)
        return 2
    return run_manager(settings, ros_args=getattr(args, "ros_args", ()))
