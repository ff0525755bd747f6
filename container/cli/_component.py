"""``container load|unload|list|types``: the ``ros2 component`` verbs; and ``container reload``.

Same arguments, output and exit codes as ros2cli's ``ros2 component``, against
any container on the ROS domain: a node is a container if it serves the three
``composition_interfaces`` services under ``<node>/_container/``, which is
how ros2cli recognises rclcpp's containers too.

There is no ros2 daemon here, so each command discovers the graph itself,
bounded by ``--spin-time``. rclpy exposes no graph-change event (rclpy#929),
so discovery is polled at a short interval until what the command needs has
appeared, not slept through.

No verb waits forever: ros2cli waits for a container's service and for its
answer without a limit; here ``--timeout`` (default 10 s) bounds each of
those waits, so a container that is gone but still in discovery, or stuck,
costs a one-line error naming the service, exit code 1. An unload runs the
node's lifecycle down, each step bounded by the container's
``unload_timeout``: give a node with slow transitions a longer ``--timeout``.

``container reload NODE`` has no ``ros2 component`` twin: it asks the
container that holds NODE (found through ``list_nodes``, or named with
``--container``) to reload it with its plugin's code imported afresh, over
the container's ``~/_container/reload_node`` service.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time
from collections.abc import Awaitable, Callable, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

from ._types import CLIENT_TIMEOUT_S, name_value, positive_seconds

if TYPE_CHECKING:
    from rclpy.client import Client
    from rclpy.node import Node

    from .._compat import SubParsers

__all__ = ["add_parser"]

T = TypeVar("T")

#: How ros2cli spells what a container serves, relative to its full name.
_SERVICES = {
    "load_node": "composition_interfaces/srv/LoadNode",
    "unload_node": "composition_interfaces/srv/UnloadNode",
    "list_nodes": "composition_interfaces/srv/ListNodes",
}
#: Log level names ``--log-level`` takes besides numbers (rcutils severities).
_LOG_LEVELS = {"unset": 0, "debug": 10, "info": 20, "warn": 30, "warning": 30, "error": 40, "fatal": 50}
#: Interval between two looks at the discovered graph.
_POLL_S = 0.02
#: How long a named container may take to be seen (the default ``--spin-time``
#: of the verbs that name one). A node's name comes on ``ros_discovery_info``,
#: a reliable topic: a sample lost under load is sent again at its writer's
#: next heartbeat, every 3 s in Fast DDS by default (every 0.1 s under this
#: project's profile, but a container may run with a profile of its own, or
#: be rclcpp's; CI twice found no container within 2 s between two loads into
#: it that worked, before the profile set it; which sample was late is not
#: known). Found sooner, the wait ends sooner; only a name nobody serves
#: costs all of it.
_NAMED_SPIN_S = 5.0
#: How long ``list`` without a container looks at most (its default ``--spin-time``).
_LIST_SPIN_S = 2.0
#: How long a node seen in the graph may take to show its container services:
#: their endpoints come by discovery (sent again at a 1 s heartbeat) and are
#: tied to the node by ``ros_discovery_info`` (at its writer's: 3 s by default).
_ENDPOINTS_S = 4.0
#: ``list`` without a container stops once the set of containers has been
#: stable this long (it cannot know how many to expect).
_SETTLE_S = 0.5


def add_parser(subparsers: SubParsers) -> None:
    """Register ``load``, ``unload``, ``list`` and ``types``."""
    load = subparsers.add_parser(
        "load",
        help="load a component into a container node",
        description="Load a registered node type into a running container node.",
    )
    load.add_argument("container_node_name", help="container node name to load the component into")
    load.add_argument("package_name", help="name of the package where the component is to be found")
    load.add_argument("plugin_name", help="type name of the component to be loaded")
    load.add_argument("-n", "--node-name", default=None, help="component node name")
    load.add_argument("--node-namespace", default=None, help="component node namespace")
    load.add_argument(
        "--log-level", default=None, type=_log_level, help="component node log level (name or number)"
    )
    load.add_argument(
        "-r", "--remap-rule", action="append", default=[], dest="remap_rules",
        help="component node remapping rules, in the 'from:=to' form",
    )
    load.add_argument(
        "-p", "--parameter", action="append", default=[], dest="parameters", type=name_value,
        help="component node parameters, in the 'name:=value' form",
    )
    load.add_argument(
        "-e", "--extra-argument", action="append", default=[], dest="extra_arguments",
        type=name_value, help="extra arguments for the container, in the 'name:=value' form",
    )
    load.add_argument(
        "-q", "--quiet", action="store_true", help="only print the component's unique ID and node name"
    )
    _add_spin_time(load)
    load.set_defaults(handler=_run_load, finish_without_output=True)

    unload = subparsers.add_parser(
        "unload",
        help="unload a component from a container node",
        description="Unload components from a container node, through their lifecycle.",
    )
    unload.add_argument("container_node_name", help="container node name to unload components from")
    unload.add_argument("component_uid", type=int, nargs="+", help="unique ID of the component to unload")
    unload.add_argument("-q", "--quiet", action="store_true", help="only print component unique IDs")
    _add_spin_time(unload)
    unload.set_defaults(handler=_run_unload, finish_without_output=True)

    listing = subparsers.add_parser(
        "list",
        help="output a list of running containers and components",
        description="List the container nodes on the ROS domain and the components they hold.",
    )
    listing.add_argument(
        "container_node_name", nargs="?", default=None, help="container node to list components from"
    )
    listing.add_argument("--containers-only", action="store_true", help="list container nodes only")
    _add_spin_time(listing)
    listing.set_defaults(handler=_run_list)

    reload = subparsers.add_parser(
        "reload",
        help="reload a loaded node with its plugin's code imported afresh",
        description=(
            "Reload a node in a running container: its plugin distribution's modules are imported afresh, and "
            "every loaded node of that distribution is taken down, loaded again from the new code under the "
            "same name, remap rules and current parameters, and driven back to the state it was in. If the new "
            "code fails, the old code's nodes run on (docs/guide/reload.md)."
        ),
    )
    reload.add_argument("node", help="full name of the node (e.g. /ldlidar); or its unique ID, with --container")
    reload.add_argument(
        "--container", default=None, help="the container node holding it (default: looked up on the ROS domain)"
    )
    reload.add_argument("-q", "--quiet", action="store_true", help="only print the new unique IDs and node names")
    _add_spin_time(reload)
    reload.set_defaults(handler=_run_reload, finish_without_output=True)

    types = subparsers.add_parser(
        "types",
        help="output a list of the installed component types",
        description="List the node types the locally installed plugins register, by package.",
    )
    types.set_defaults(handler=_run_types)


def _add_spin_time(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--spin-time", type=float, default=None,
        help=(
            f"seconds to wait for discovery of the container (default: {_NAMED_SPIN_S:g} for a container "
            f"named, {_LIST_SPIN_S:g} to list them all)"
        ),
    )
    parser.add_argument(
        "--timeout", type=positive_seconds, default=CLIENT_TIMEOUT_S, metavar="SECONDS",
        help="seconds to wait for the container's service, and for each answer (default: %(default)s)",
    )


def _log_level(text: str) -> int:
    if text.lower() in _LOG_LEVELS:
        return _LOG_LEVELS[text.lower()]
    try:
        return int(text)
    except ValueError:
        names = ", ".join(name.upper() for name in _LOG_LEVELS)
        raise argparse.ArgumentTypeError(f"expected one of {names} or a number, not {text!r}") from None


def _full_name(name: str) -> str:
    return name if name.startswith("/") else f"/{name}"


# -- verbs ------------------------------------------------------------------------
def _run_load(args: argparse.Namespace) -> int:
    from composition_interfaces.srv import LoadNode
    from rcl_interfaces.msg import Parameter as ParameterMsg
    from rclpy.parameter import get_parameter_value

    request = LoadNode.Request(
        package_name=args.package_name,
        plugin_name=args.plugin_name,
        node_name=args.node_name or "",
        node_namespace=args.node_namespace or "",
        log_level=args.log_level or 0,
        remap_rules=list(args.remap_rules),
        parameters=[
            ParameterMsg(name=name, value=get_parameter_value(string_value=value))
            for name, value in args.parameters
        ],
        extra_arguments=[
            ParameterMsg(name=name, value=get_parameter_value(string_value=value))
            for name, value in args.extra_arguments
        ],
    )

    async def load(node: Node) -> int:
        container = args.container_node_name
        client = await _container_client(node, container, "load_node", LoadNode, args)
        if client is None:
            return _fail(f"Unable to find container node '{container}'")
        response = await _call(client, request, timeout=args.timeout)
        if not response.success:
            return _fail(f"Failed to load component: {response.error_message}")
        _warn(response.error_message, container=container)
        if args.quiet:
            print(f"{response.unique_id}  {response.full_node_name}")
        else:
            print(
                f"Loaded component {response.unique_id} into '{container}' "
                f"container node as '{response.full_node_name}'"
            )
        return 0

    return _with_node(load, ros_args=getattr(args, "ros_args", ()))


def _run_unload(args: argparse.Namespace) -> int:
    from composition_interfaces.srv import UnloadNode

    async def unload(node: Node) -> int:
        container = args.container_node_name
        client = await _container_client(node, container, "unload_node", UnloadNode, args)
        if client is None:
            return _fail(f"Unable to find container node '{container}'")
        for uid in args.component_uid:
            response = await _call(client, UnloadNode.Request(unique_id=uid), timeout=args.timeout)
            if not response.success:
                return _fail(
                    f"Failed to unload component {uid} from '{container}' container node\n"
                    f"    {response.error_message}"
                )
            print(uid if args.quiet else f"Unloaded component {uid} from '{container}' container node")
        return 0

    return _with_node(unload, ros_args=getattr(args, "ros_args", ()))


def _run_list(args: argparse.Namespace) -> int:
    from composition_interfaces.srv import ListNodes

    async def components(node: Node, container: str) -> list[str]:
        client: Client[Any, Any] = node.create_client(ListNodes, f"{_full_name(container)}/_container/list_nodes")
        try:
            response = await _call(client, ListNodes.Request(), timeout=args.timeout)
        finally:
            node.destroy_client(client)
        return [f"{uid}  {name}" for uid, name in zip(response.unique_ids, response.full_node_names, strict=True)]

    async def listing(node: Node) -> int:
        wanted = args.container_node_name
        if wanted is not None:
            client = await _container_client(node, wanted, "list_nodes", ListNodes, args)
            if client is None:
                return _fail(f"Unable to find container node '{wanted}'")
            node.destroy_client(client)
            if not args.containers_only:
                for line in await components(node, wanted):
                    print(line)
            return 0
        for container in await _settled_containers(node, _spin_time(args, named=False)):
            print(container)
            if not args.containers_only:
                for line in await components(node, container):
                    print(f"  {line}")
        return 0

    return _with_node(listing, ros_args=getattr(args, "ros_args", ()))


def _run_reload(args: argparse.Namespace) -> int:
    from composition_interfaces.srv import ListNodes
    from lifecycle_container_interfaces.srv import ReloadNode

    target: str = args.node
    by_id = target.isdigit()
    if by_id and args.container is None:
        print("container reload: a unique ID needs --container (or give the node's full name)", file=sys.stderr)
        return 2
    request = ReloadNode.Request(unique_id=int(target)) if by_id else ReloadNode.Request(node_name=_full_name(target))

    async def holder(node: Node) -> str | None:
        """The container whose list_nodes names the node."""
        for container in await _settled_containers(node, _spin_time(args, named=False)):
            client: Client[Any, Any] = node.create_client(ListNodes, f"{container}/_container/list_nodes")
            try:
                listed = await _call(client, ListNodes.Request(), timeout=args.timeout)
            finally:
                node.destroy_client(client)
            if request.node_name in listed.full_node_names:
                return container
        return None

    async def reload(node: Node) -> int:
        container = args.container if args.container is not None else await holder(node)
        if container is None:
            return _fail(f"No container on the ROS domain holds a node named '{request.node_name}'")
        client = await _container_client(node, container, "reload_node", ReloadNode, args)
        if client is None:
            return _fail(f"Unable to find container node '{container}' serving reload_node")
        response = await _call(client, request, timeout=args.timeout)
        if not response.success:
            return _fail(f"Failed to reload '{target}': {response.error_message}")
        for uid, name in zip(response.unique_ids, response.full_node_names, strict=True):
            said = f"Reloaded '{name}' in '{container}' container node as component {uid}"
            print(f"{uid}  {name}" if args.quiet else said)
        if response.error_message:
            print(response.error_message, file=sys.stderr)
        return 0

    return _with_node(reload, ros_args=getattr(args, "ros_args", ()))


def _run_types(args: argparse.Namespace) -> int:
    from .._registry import PluginRegistry

    for package, type_names in PluginRegistry().packages().items():
        print(package)
        for type_name in type_names:
            print(f"  {type_name}")
    return 0


# -- talking to containers ------------------------------------------------------------
def _warn(error_message: str, *, container: str) -> None:
    """Log the warnings a successful load answer carries, one line each, under the logger that logged them.

    Through ROS logging like any warning (stderr, as ``[WARN] [time]
    [talker]: ...``, and this command's log file), so the person who typed
    the load reads them without the container's log; the load still
    succeeded. A container that leaves ``error_message`` empty on success
    (rclcpp's) prints nothing here.
    """
    from rclpy.logging import get_logger

    from .._warnings import decode

    for warning in decode(error_message, default_logger=container.strip("/").replace("/", ".")):
        get_logger(warning.logger).warning(warning.message)


def _fail(message: str) -> int:
    print(message, file=sys.stderr)
    return 1


def _with_node(main: Callable[[Node], Awaitable[int]], *, ros_args: Sequence[str] = ()) -> int:
    """Run ``main`` with a hidden client node; return its exit code."""
    from .._session import Session, run_session

    async def run(session: Session) -> int:
        with session.client_node(f"_container_cli_{os.getpid()}") as node:
            try:
                return await main(node)
            except _Failure as exc:
                return _fail(str(exc))

    return run_session(run, ros_args=ros_args)


async def _poll(condition: Callable[[], T | None], *, timeout: float) -> T | None:
    """Return ``condition()``'s first non-``None`` value, or ``None`` after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value is not None or time.monotonic() >= deadline:
            return value
        await asyncio.sleep(_POLL_S)


def _is_container(node: Node, name: str, namespace: str, *, also: str | None = None) -> bool:
    """Whether the node serves the three container services (and ``also``, another under ``_container/``)."""
    from rclpy.node import NodeNameNonExistentError

    try:
        served = dict(node.get_service_names_and_types_by_node(name, namespace))
    except NodeNameNonExistentError:
        return False  # gone between listing and asking
    base = f"{namespace.rstrip('/')}/{name}/_container/"
    if also is not None and base + also not in served:
        return False
    return all(type_name in served.get(base + service, []) for service, type_name in _SERVICES.items())


def _containers(node: Node) -> list[str]:
    return sorted(
        f"{namespace.rstrip('/')}/{name}"
        for name, namespace in node.get_node_names_and_namespaces()
        if _is_container(node, name, namespace)
    )


async def _container_client(
    node: Node, container: str, service: str, srv_type: Any, args: argparse.Namespace
) -> Client[Any, Any] | None:
    """Wait for ``container`` to show up as a container and its ``service`` to be ready.

    Discovery has three steps, bounded apart. The node's name, within
    ``--spin-time`` (:data:`_NAMED_SPIN_S`): not seen by then, there is no
    such node. Then, the name seen, its services in the graph, within
    :data:`_ENDPOINTS_S`: a node's name and its endpoints are discovered
    apart, and what is lost under load is sent again only at the next
    heartbeat, so a container whose name came first is not called missing
    for that (a node that is no container costs those seconds). Last,
    ``service`` matched with our client, within ``args.timeout``, as any
    service the verbs wait for (:func:`_matched`).

    :return: a client of the service, or ``None`` if ``container`` is no
        container node serving ``service``.
    :raises _Failure: ``service`` in the graph, not matched within ``args.timeout``.
    """
    full_name = _full_name(container)
    if await _poll(lambda: True if full_name in _node_names(node) else None, timeout=_spin_time(args)) is None:
        return None
    namespace, _, name = full_name.rpartition("/")
    also = None if service in _SERVICES else service

    def serves() -> bool | None:
        return True if _is_container(node, name, namespace or "/", also=also) else None

    if await _poll(serves, timeout=min(args.timeout, _ENDPOINTS_S)) is None:
        return None
    client: Client[Any, Any] = node.create_client(srv_type, f"{full_name}/_container/{service}")
    # Seen in the graph is not yet matched with our client's endpoints.
    try:
        await _matched(client, timeout=args.timeout)
    except _Failure:
        node.destroy_client(client)
        raise
    return client


def _spin_time(args: argparse.Namespace, *, named: bool = True) -> float:
    """``--spin-time``, or its default for looking for one named container or for all of them."""
    if args.spin_time is not None:
        return float(args.spin_time)
    return _NAMED_SPIN_S if named else _LIST_SPIN_S


def _node_names(node: Node) -> list[str]:
    return [f"{namespace.rstrip('/')}/{name}" for name, namespace in node.get_node_names_and_namespaces()]


async def _settled_containers(node: Node, spin_time: float) -> list[str]:
    """The containers on the domain, once discovery has stopped finding new ones."""
    deadline = time.monotonic() + spin_time
    seen: list[str] = []
    stable_since = time.monotonic()
    while time.monotonic() < deadline:
        now = _containers(node)
        if now != seen:
            seen, stable_since = now, time.monotonic()
        elif seen and time.monotonic() - stable_since >= _SETTLE_S:
            break
        await asyncio.sleep(_POLL_S)
    return seen


async def _call(client: Client[Any, Any], request: Any, *, timeout: float) -> Any:
    """Send ``request`` once the server is matched; wait for its response.

    :param timeout: seconds to wait for the server, then for the response.
    :raises _Failure: no server, or no response in time.
    """
    await _matched(client, timeout=timeout)
    from ..executor import result as future_result

    future = client.call_async(request)
    try:
        return await future_result(future, timeout=timeout)
    except TimeoutError:
        client.remove_pending_request(future)
        raise _Failure(f"No response from '{client.srv_name}' within {timeout:g} s") from None


async def _matched(client: Client[Any, Any], *, timeout: float) -> None:
    """Wait until ``client``'s service is matched with it.

    :raises _Failure: not within ``timeout`` seconds.
    """
    if await _poll(lambda: True if client.service_is_ready() else None, timeout=timeout) is None:
        raise _Failure(f"No '{client.srv_name}' service found within {timeout:g} s")


class _Failure(Exception):
    """A verb cannot go on; the message is what the user reads."""
