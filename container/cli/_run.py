"""``container run CONFIG``: one container process hosting the configured nodes."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from .._config import load_config
from .._errors import ConfigError
from .._params import node_parameters
from .._runtime import configure_logging

if TYPE_CHECKING:
    from .._compat import SubParsers

__all__ = ["add_parser"]


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "run",
        help="run a container with the nodes of a YAML file",
        description="Run a container hosting the nodes a YAML file lists, until SIGINT or SIGTERM.",
    )
    parser.add_argument("config", help="the container's YAML file (see examples/)")
    parser.add_argument("--verbose", action="store_true", help="log plugin loading in detail")
    parser.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    configure_logging(verbose=args.verbose)
    try:
        config = load_config(args.config)
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
    from .._app import run_container

    if settings is None:
        return run_container(config)
    from .._app import manager_extension

    return run_container(config, extensions=(manager_extension(settings),))
