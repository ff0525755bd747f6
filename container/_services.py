"""The container services: ``~/_container/load_node``, ``unload_node``, ``list_nodes``, ``reload_node``.

They are what makes a node a component container to ``ros2 component`` and
``container load``: any client of ``composition_interfaces`` can drive this
container exactly like rclcpp's. Every request goes through
:meth:`ComponentManager.load` / :meth:`ComponentManager.unload`, the same code
paths ``container run`` uses, and a bad request only ever costs its own
``success=false`` answer: the container serves on. A request whose extra
arguments hold ``autostart: true`` also configures and activates the node
before it is answered, so that launch files bring nodes up on any launch_ros.

``reload_node`` (``lifecycle_container_interfaces/srv/ReloadNode``, this
container's own) reloads a node with its plugin distribution's code imported
afresh (:mod:`container._reload`), for ``container reload`` and any client.

Load, unload and reload are ``async def`` so they run on the executor's loop
thread, where the container's bookkeeping lives, and share one mutually
exclusive group so that requests apply in the order they arrive (and the
manager's ``changing`` lock, which a ``--reload`` watcher's reloads take too);
``list_nodes`` is plain, in a group of its own, and answers even during a
slow unload or while a plugin's callback blocks the loop.

Answers and log lines echo what a request named through
:func:`~container.clip`: each value at most 200 characters with its length,
a whole error message at most 800. A successful load's ``error_message``
holds the warnings it caused, one line each (:mod:`container._warnings`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from lifecycle_container_interfaces.srv import ReloadNode
from rcl_interfaces.msg import Parameter as ParameterMsg
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.parameter import Parameter

from ._container import LoadRequest, type_label
from ._errors import ContainerError, LoadError
from ._qos import SERVICE_QOS
from ._text import MESSAGE_LIMIT, clip
from ._warnings import encode

if TYPE_CHECKING:
    from collections.abc import Sequence

    from rclpy.service import Service

    from ._container import ComponentManager
    from ._reload import Reloader

__all__ = ["SERVICE_QOS", "ContainerServices", "load_request_from_msg"]

#: Names relative to the container node, as rclcpp serves them.
LOAD_NODE = "~/_container/load_node"
UNLOAD_NODE = "~/_container/unload_node"
LIST_NODES = "~/_container/list_nodes"
RELOAD_NODE = "~/_container/reload_node"


def load_request_from_msg(msg: LoadNode.Request) -> LoadRequest:
    """Translate a LoadNode request into the container's :class:`LoadRequest`.

    :raises LoadError: a parameter or extra argument carries an invalid type.
    """
    return LoadRequest(
        package=msg.package_name,
        plugin=msg.plugin_name,
        name=msg.node_name or None,
        namespace=msg.node_namespace or None,
        remap_rules=tuple(msg.remap_rules),
        parameters=_parameters(msg.parameters, what="parameter"),
        extra_arguments={
            p.name: p.value for p in _parameters(msg.extra_arguments, what="extra argument")
        },
        log_level=msg.log_level,
    )


def _parameters(messages: Sequence[ParameterMsg], *, what: str) -> tuple[Parameter[Any], ...]:
    parameters = []
    for message in messages:
        try:
            parameters.append(Parameter.from_parameter_msg(message))
        except (ValueError, TypeError) as exc:
            # An out-of-range type id, or a value rclpy cannot hold.
            raise LoadError(f"Invalid {what} {clip(message.name, quote=True)}: {clip(str(exc))}") from exc
    return tuple(parameters)


class ContainerServices:
    """Serve LoadNode, UnloadNode, ListNodes and ReloadNode on a :class:`ComponentManager`.

    The services live as long as the container node, or until :meth:`destroy`.

    :param reloader: what reloads nodes (by default one of its own).
    """

    def __init__(self, manager: ComponentManager, *, reloader: Reloader | None = None) -> None:
        self._manager = manager
        # Made on first use: the reload's machinery is not imported until a reload asks for it.
        self._reloader = reloader
        changes = MutuallyExclusiveCallbackGroup()
        self._services: list[Service[Any, Any]] = [
            manager.create_service(LoadNode, LOAD_NODE, self._load, callback_group=changes, qos_profile=SERVICE_QOS),
            manager.create_service(
                UnloadNode, UNLOAD_NODE, self._unload, callback_group=changes, qos_profile=SERVICE_QOS
            ),
            manager.create_service(
                ReloadNode, RELOAD_NODE, self._reload, callback_group=changes, qos_profile=SERVICE_QOS
            ),
            manager.create_service(
                ListNodes,
                LIST_NODES,
                self._list,
                callback_group=MutuallyExclusiveCallbackGroup(),
                qos_profile=SERVICE_QOS,
            ),
        ]

    @property
    def reloader(self) -> Reloader:
        """What the reload service reloads nodes with (a ``--reload`` watcher uses it too)."""
        if self._reloader is None:
            from ._reload import Reloader

            self._reloader = Reloader(self._manager)
        return self._reloader

    def destroy(self) -> None:
        """Stop serving (idempotent); the container node stays."""
        for service in self._services:
            self._manager.destroy_service(service)
        self._services.clear()

    async def _load(self, request: LoadNode.Request, response: LoadNode.Response) -> Any:
        log = self._manager.get_logger()
        what = clip(type_label(request.package_name, request.plugin_name), quote=True)
        try:
            load = load_request_from_msg(request)
            async with self._manager.changing:
                loaded = await self._manager.load(load)
        except ContainerError as exc:
            log.error(f"Refused to load {what}: {clip(str(exc), limit=MESSAGE_LIMIT)}")
            response.success = False
            response.error_message = clip(str(exc), limit=MESSAGE_LIMIT)
            return response
        response.full_node_name = loaded.full_name
        response.unique_id = loaded.unique_id
        response.success = True
        if load.wants_autostart:
            try:
                await self._manager.start(loaded, timeout=self._manager.unload_timeout)
            except ContainerError as exc:
                # Loaded, and stays so to be inspected or unloaded by its id
                # (as a container file's node that fails to come up does).
                log.error(
                    f"Loaded {what} as '{loaded.full_name}' but autostart failed: {clip(str(exc), limit=MESSAGE_LIMIT)}"
                )
                response.success = False
                failure = clip(
                    f"Loaded as unique_id {loaded.unique_id} but autostart failed: {' '.join(str(exc).split())}",
                    limit=MESSAGE_LIMIT,
                )
                # The warnings may say why (a typo left a parameter at its default).
                response.error_message = "\n".join(filter(None, [failure, encode(loaded.warnings)]))
                return response
        # rclcpp leaves it empty on success, and its clients read it only on
        # failure: here it carries the warnings the load caused (_warnings).
        response.error_message = encode(loaded.warnings)
        return response

    async def _unload(self, request: UnloadNode.Request, response: UnloadNode.Response) -> Any:
        try:
            async with self._manager.changing:
                _, notes = await self._manager.unload(request.unique_id)
        except ContainerError as exc:
            self._manager.get_logger().error(f"Refused to unload: {clip(str(exc), limit=MESSAGE_LIMIT)}")
            response.success = False
            response.error_message = clip(str(exc), limit=MESSAGE_LIMIT)
            return response
        response.success = True
        # rclcpp leaves it empty on success; here it says what was cut short.
        response.error_message = "; ".join(notes)
        return response

    async def _reload(self, request: ReloadNode.Request, response: ReloadNode.Response) -> Any:
        try:
            reloaded = await self.reloader.reload_node(request.node_name or request.unique_id)
        except ContainerError as exc:
            self._manager.get_logger().error(clip(str(exc), limit=MESSAGE_LIMIT))
            response.success = False
            response.error_message = clip(str(exc), limit=MESSAGE_LIMIT)
            return response
        response.success = True
        response.unique_ids = [loaded.unique_id for loaded in reloaded.nodes]
        response.full_node_names = [loaded.full_name for loaded in reloaded.nodes]
        response.error_message = clip("; ".join(reloaded.notes), limit=MESSAGE_LIMIT)
        return response

    def _list(self, request: ListNodes.Request, response: ListNodes.Response) -> Any:
        # Plain, so it answers from its lane's thread even while an async
        # callback holds the event loop.
        loaded = self._manager.loaded()
        response.full_node_names = [entry.full_name for entry in loaded]
        response.unique_ids = [entry.unique_id for entry in loaded]
        return response
