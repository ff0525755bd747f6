"""``container run [CONFIG] [--ros-args ...]``: one container process hosting the configured nodes.

Without a file it starts an empty container, as rclcpp's ``component_container``
does; the executables ``container index`` registers (``ros2 run
lifecycle_container component_container``, launch_ros's
``ComposableNodeContainer``) are this command. ROS arguments apply to the
container node with rcl's semantics (``-r __node:=``, ``-r __ns:=``,
``--params-file``, ``-p``, remaps, ``--log-level``); loaded nodes get them only
when a load asks (``forward_global_arguments``), as in rclcpp.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from .._config import ContainerConfig, load_config
from .._errors import ConfigError
from .._params import node_parameters
from .._runtime import configure_logging

if TYPE_CHECKING:
    from .._compat import SubParsers

__all__ = ["add_parser"]


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "run",
        help="run a container, with the nodes of a YAML file if given",
        description=(
            "Run a container until SIGINT or SIGTERM, hosting the nodes a YAML file lists "
            "(none without a file). ROS arguments (--ros-args ...) apply to the container node."
        ),
    )
    parser.add_argument("config", nargs="?", help="the container's YAML file (see examples/); none: empty")
    parser.add_argument("--verbose", action="store_true", help="log plugin loading in detail")
    parser.add_argument(
        "--exit-on-failure", action="store_true", default=None,
        help="exit 1 right after start-up when a node the file lists fails to load or start "
        "(default: the file's container.on_failure, 'continue': serve on and exit 0)",
    )
    parser.add_argument(
        "--reload", action="store_true",
        help="for development: reload a plugin's nodes when its source files change (docs/guide/reload.md)",
    )
    parser.add_argument(
        "--use_multi_threaded_executor", action="store_true",
        help="accepted for rclcpp's component_container_isolated; no effect: every node "
        "already has its own callback lanes on the one executor",
    )
    parser.set_defaults(handler=_run, finish_without_output=True)


def _run(args: argparse.Namespace) -> int:
    configure_logging(verbose=args.verbose)
    try:
        config = load_config(args.config) if args.config else ContainerConfig()
        # The container node's own parameter files, read now so that a
        # missing or broken one is a usage error, not a failure at start-up.
        node_parameters(config.parameters, full_name=config.full_name, base_dir=config.base_dir)
        settings = None
        if config.manager is not None:
            from ..lifecycle import ManagerSettings

            settings = ManagerSettings.from_mapping(config.manager, source=f"{args.config}: manager")
    except ConfigError as exc:
        print(f"container run: {exc}", file=sys.stderr)
        return 2
    from .._app import manager_extension, reload_extension, run_container

    extensions = () if settings is None else (manager_extension(settings),)
    if args.reload:
        extensions = (*extensions, reload_extension())
    return run_container(
        config, extensions=extensions, ros_args=getattr(args, "ros_args", ()), exit_on_failure=args.exit_on_failure
    )
