"""``container lifecycle nodes|get|set|list``: the ``ros2 lifecycle`` verbs.

Same arguments and output as ros2cli's, so scripts written for one work with
the other; errors go to stderr with exit code 1, as ros2cli's do. Unlike
ros2cli, a transition that fails also exits 1, and no verb waits forever:
ros2cli waits for a node's services and for their answers without a limit
(a node that is gone but still in discovery, or stuck, holds it for good),
here ``--timeout`` (default 10 s) bounds each of those waits, and the error
names the node and the service it waited for.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time
from collections.abc import Callable, Coroutine, Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .._compat import SubParsers

from ._types import CLIENT_TIMEOUT_S, positive_seconds

__all__ = ["add_parser"]

_GET_STATE_TYPE = "lifecycle_msgs/srv/GetState"
#: How long a listing must stay unchanged to count as discovered.
_SETTLE_S = 0.5


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "lifecycle",
        help="inspect and drive lifecycle nodes, like ros2 lifecycle",
        description="Inspect and drive lifecycle nodes (the ros2 lifecycle verbs).",
    )
    verbs = parser.add_subparsers(dest="verb", metavar="VERB")

    def verb(name: str, help_text: str, handler: Callable[[argparse.Namespace], int]) -> argparse.ArgumentParser:
        sub = verbs.add_parser(name, help=help_text, description=help_text)
        sub.add_argument(
            "--spin-time",
            type=float,
            default=2.0,
            help="seconds to wait for discovery (default: 2.0)",
        )
        sub.add_argument(
            "--include-hidden-nodes", action="store_true", help="consider hidden nodes as well"
        )
        sub.set_defaults(handler=handler)
        return sub

    verb("nodes", "Output a list of nodes with lifecycle", _nodes)
    get = verb("get", "Get lifecycle state for one or more nodes", _get)
    get.add_argument("node_name", nargs="?", help="name of the ROS node; all nodes if omitted")
    set_ = verb("set", "Trigger lifecycle state transition", _set)
    set_.set_defaults(finish_without_output=True)
    set_.add_argument("node_name", help="name of the ROS node")
    set_.add_argument("transition", help="the label or the id of the transition")
    list_ = verb("list", "Output a list of available transitions", _list)
    list_.add_argument("node_name", help="name of the ROS node")
    list_.add_argument(
        "-a", "--all", action="store_true", help="display all existing transitions"
    )
    for calling in (get, set_, list_):
        calling.add_argument(
            "--timeout",
            type=positive_seconds,
            default=CLIENT_TIMEOUT_S,
            metavar="SECONDS",
            help="seconds to wait for the node's services, and for each answer (default: %(default)s)",
        )
    parser.set_defaults(handler=lambda args: _usage(parser))


def _usage(parser: argparse.ArgumentParser) -> int:
    parser.print_help(sys.stderr)
    return 2


def _session(main: Callable[[Any], Coroutine[Any, Any, int]], *, ros_args: Sequence[str] = ()) -> int:
    """Run ``main(node)`` with a short-lived hidden node; return its exit code."""
    from .._session import Session, run_session

    async def run(session: Session) -> int:
        with session.client_node(f"_container_lifecycle_cli_{os.getpid()}") as node:
            return await main(node)

    return run_session(run, ros_args=ros_args)


def _lifecycle_nodes(node: Any, *, hidden: bool) -> list[str]:
    names = []
    for service, types in node.get_service_names_and_types():
        if service.endswith("/get_state") and _GET_STATE_TYPE in types:
            name = service[: -len("/get_state")]
            if hidden or not any(part.startswith("_") for part in name.split("/")):
                names.append(name)
    return sorted(names)


async def _discover(node: Any, args: argparse.Namespace) -> list[str]:
    """All lifecycle nodes, once the graph has stopped changing (or spin-time)."""
    deadline = time.monotonic() + args.spin_time
    found = _lifecycle_nodes(node, hidden=args.include_hidden_nodes)
    stable_since = time.monotonic()
    while time.monotonic() < deadline:
        await asyncio.sleep(0.05)
        now = _lifecycle_nodes(node, hidden=args.include_hidden_nodes)
        if now != found:
            found, stable_since = now, time.monotonic()
        elif found and time.monotonic() - stable_since >= _SETTLE_S:
            break
    return found


async def _find(node: Any, args: argparse.Namespace) -> str | None:
    """The full name of ``args.node_name`` once discovered, or ``None``."""
    name = args.node_name if args.node_name.startswith("/") else f"/{args.node_name}"
    deadline = time.monotonic() + args.spin_time
    while True:
        if name in _lifecycle_nodes(node, hidden=True):
            return str(name)
        if time.monotonic() >= deadline:
            return None
        await asyncio.sleep(0.05)


def _client(node: Any, name: str, args: argparse.Namespace) -> Any:
    from ..lifecycle import LifecycleClient

    return LifecycleClient(node, name, service_timeout=args.timeout)


def _error(message: str) -> int:
    print(message, file=sys.stderr)
    return 1


def _nodes(args: argparse.Namespace) -> int:
    async def main(node: Any) -> int:
        for name in await _discover(node, args):
            print(name)
        return 0

    return _session(main, ros_args=getattr(args, "ros_args", ()))


def _get(args: argparse.Namespace) -> int:
    from .._errors import TransitionError

    async def main(node: Any) -> int:
        if args.node_name:
            name = await _find(node, args)
            if name is None:
                return _error("Node not found")
            names = [name]
        else:
            names = await _discover(node, args)
        for name in names:
            try:
                state_id, label = await _client(node, name, args).get_state()
            except TransitionError as exc:
                return _error(str(exc))
            print(f"{label} [{state_id}]" if args.node_name else f"{name}: {label} [{state_id}]")
        return 0

    return _session(main, ros_args=getattr(args, "ros_args", ()))


def _describe(transition: Any) -> str:
    return f"- {transition.transition.label} [{transition.transition.id}]"


def _list(args: argparse.Namespace) -> int:
    from .._errors import TransitionError

    async def main(node: Any) -> int:
        name = await _find(node, args)
        if name is None:
            return _error("Node not found")
        try:
            transitions = await _client(node, name, args).available_transitions(graph=args.all)
        except TransitionError as exc:
            return _error(str(exc))
        for transition in transitions:
            print(_describe(transition))
            print(f"\tStart: {transition.start_state.label}")
            print(f"\tGoal: {transition.goal_state.label}")
        return 0

    return _session(main, ros_args=getattr(args, "ros_args", ()))


def _set(args: argparse.Namespace) -> int:
    from .._errors import TransitionError

    async def main(node: Any) -> int:
        name = await _find(node, args)
        if name is None:
            return _error("Node not found")
        client = _client(node, name, args)
        try:
            transitions = await client.available_transitions()
            for described in transitions:
                if args.transition in (described.transition.label, str(described.transition.id)):
                    break
            else:
                return _error(
                    "Unknown transition requested, available ones are:"
                    + "".join(f"\n{_describe(t)}" for t in transitions)
                )
            # The node bounds its transitions itself, but a node that is
            # stuck, or gone and still in discovery, never answers.
            ok = await client.change_state(described.transition, timeout=args.timeout)
        except TransitionError as exc:
            return _error(str(exc))
        if not ok:
            return _error("Transitioning failed")
        print("Transitioning successful")
        return 0

    return _session(main, ros_args=getattr(args, "ros_args", ()))
