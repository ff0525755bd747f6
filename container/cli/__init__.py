"""The ``container`` command: ``run`` a container, and drive one from outside.

Each sub-command lives in its own module with an ``add_parser(subparsers)``
function that registers it and sets ``handler`` on its parser. Handlers
return the process exit code.

ROS arguments follow rcl's rules, as for any ROS program: every
``--ros-args`` starts a section of them, which ``--`` (or the end of the
command line) ends. They are taken out before the command's own arguments
are parsed, checked by rcl, and handed to the session's context in
``args.ros_args``; nothing outside those sections ever reaches rcl.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from .._output import finish_without_output
from . import _component, _index, _lifecycle, _manager, _run, _top

if TYPE_CHECKING:
    from .._compat import SubParsers

__all__ = ["main", "split_ros_args"]

#: Modules contributing sub-commands, in the order ``--help`` lists them.
_COMMANDS: list[Callable[[SubParsers], None]] = [
    _run.add_parser,
    _component.add_parser,
    _lifecycle.add_parser,
    _manager.add_parser,
    _top.add_parser,
    _index.add_parser,
]

_ROS_ARGS = "--ros-args"
_END_OF_ROS_ARGS = "--"


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split ``argv`` into the command's own arguments and its ROS arguments.

    :return: the arguments outside every ``--ros-args ... --`` section, and
        the sections themselves (each ``--ros-args`` kept, each closing
        ``--`` too), as rcl reads them.
    """
    own: list[str] = []
    ros: list[str] = []
    inside = False
    for arg in argv:
        if arg == _ROS_ARGS:
            inside = True
            ros.append(arg)
        elif inside and arg == _END_OF_ROS_ARGS:
            inside = False
            ros.append(arg)
        elif inside:
            ros.append(arg)
        else:
            own.append(arg)
    return own, ros


def check_ros_args(ros_args: Sequence[str]) -> str | None:
    """Let rcl parse ``ros_args``; return its complaint, or ``None`` if they are valid."""
    if not ros_args:
        return None
    from rclpy.utilities import remove_ros_args

    from .._compat import InvalidROSArgsError, UnknownROSArgsError

    try:
        remove_ros_args(["container", *ros_args])
    except UnknownROSArgsError as exc:
        return f"unknown ROS arguments: {exc}"
    except InvalidROSArgsError as exc:
        # rcl appends where in its sources it failed; the first part is the reason.
        return str(exc).split(", at /", 1)[0]
    return None


def use_this_ament_prefix() -> None:
    """Put this environment's prefix on ``AMENT_PREFIX_PATH`` if it holds an ament index.

    The ROS wheels install a ROS prefix into the environment, and ``container
    index`` registers the plugins there; ament_index_python, launch_ros and
    ros2cli find neither unless the prefix is on the path, which nothing else
    puts there. Child processes inherit it.
    """
    prefix = sys.prefix
    if not os.path.isdir(os.path.join(prefix, "share", "ament_index", "resource_index")):
        return
    paths = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    if prefix not in paths:
        os.environ["AMENT_PREFIX_PATH"] = os.pathsep.join([prefix, *paths])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="container",
        description="A component container for ROS 2 lifecycle nodes, on one asyncio executor.",
        epilog="ROS arguments go after --ros-args, as for any ROS program (rcl's syntax).",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in _COMMANDS:
        add(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    use_this_ament_prefix()
    parser = build_parser()
    own, ros_args = split_ros_args(sys.argv[1:] if argv is None else list(argv))
    args = parser.parse_args(own)
    handler = getattr(args, "handler", None)
    if handler is None:
        parser.print_help(sys.stderr)
        return 2
    problem = check_ros_args(ros_args)
    if problem is not None:
        print(f"container {args.command}: invalid ROS arguments: {problem}", file=sys.stderr)
        return 2
    args.ros_args = ros_args
    if getattr(args, "finish_without_output", False):
        # A command that acts does all it was asked when its reader goes
        # away early; one that only reads stops (container._output).
        finish_without_output()
    code: int = handler(args)
    return code
