"""The ``container`` command: ``run`` a container, and drive one from outside.

Each sub-command lives in its own module with an ``add_parser(subparsers)``
function that registers it and sets ``handler`` on its parser. Handlers
return the process exit code.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from . import _component, _lifecycle, _manager, _run

if TYPE_CHECKING:
    from .._compat import SubParsers

__all__ = ["main"]

#: Modules contributing sub-commands, in the order ``--help`` lists them.
_COMMANDS: list[Callable[[SubParsers], None]] = [
    _run.add_parser,
    _component.add_parser,
    _lifecycle.add_parser,
    _manager.add_parser,
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="container",
        description="A component container for ROS 2 lifecycle nodes, on one asyncio executor.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in _COMMANDS:
        add(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else list(argv))
    handler = getattr(args, "handler", None)
    if handler is None:
        parser.print_help(sys.stderr)
        return 2
    code: int = handler(args)
    return code
