"""The container node: loads registered node types, tracks and unloads them.

``load`` is the one code path for every way a node enters the container: the
YAML file of ``container run`` and the ``load_node`` service both call it.
Error messages follow rclcpp's ComponentManager where it has one, since
that is what ``ros2 component`` users read.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import weakref
from collections.abc import Callable, Coroutine, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.exceptions import (
    InvalidNamespaceException,
    InvalidNodeNameException,
)
from rclpy.lifecycle import LifecycleNodeMixin
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.validate_namespace import validate_namespace
from rclpy.validate_node_name import validate_node_name

from . import checks
from ._compat import (
    InvalidROSArgsError,
    finish_type_description_service,
    is_built,
    state_machine,
    state_machine_if_built,
)
from ._errors import ConfigError, LoadError, TransitionError
from ._logger import FastLogging
from ._memory import MemoryReturn
from ._params import ParameterSource, node_parameters
from ._registry import NodeType, PluginRegistry
from ._statefile import same_parameters
from ._text import clip
from ._warnings import LoadWarning
from .executor import Escaped, format_plugin_frames, in_thread
from .intra import intra_process_class
from .lifecycle import LifecycleNode, bring_down, bring_up, is_lifecycle, transition

if TYPE_CHECKING:
    from rclpy.context import Context

    from .executor import AsyncioExecutor

__all__ = [
    "RELOAD_STATE",
    "Carry",
    "ComponentManager",
    "LoadRequest",
    "LoadWatcher",
    "LoadedNode",
    "Restore",
    "entry_label",
    "type_label",
]

#: The rclpy parameter that starts a node's ~/get_type_description service.
TYPE_DESCRIPTION_SERVICE = "start_type_description_service"

#: The attribute a reloaded node's dict of kept state is handed over in
#: (``LifecycleNode.reload_state``; any node class may read it).
RELOAD_STATE = "reload_state"

#: Extra arguments accepted, with their expected type: rclcpp's container's
#: (``use_intra_process_comms``, see :mod:`container.intra`;
#: ``forward_global_arguments``), and ``autostart``, which brings a lifecycle
#: node to active after loading.
_EXTRA_ARGUMENTS: dict[str, type] = {
    "use_intra_process_comms": bool,
    "forward_global_arguments": bool,
    "autostart": bool,
}

#: What ``thread_num`` means here (``ros2 param describe``; docs/guide/launch.md).
THREAD_NUM_DESCRIPTION = (
    "Accepted as rclcpp's component_container_mt reads it (default: the number of CPUs). "
    "Here every node's plain callbacks run on worker threads of their own lanes, started when "
    "needed and ended when idle, so no callback waits for a thread another node holds; "
    "thread_num does not cap them."
)

#: How rclcpp names the types in its refusals.
_TYPE_WORDS: dict[type, str] = {bool: "boolean"}

#: rcl log severities a LoadNode request may carry (0 leaves the level alone).
_LOG_LEVELS = {0, 10, 20, 30, 40, 50}


def type_label(package: str, plugin: str) -> str:
    """How logs name a requested type: ``package::Type``, whether or not ``plugin`` has the package."""
    return plugin if "::" in plugin else f"{package}::{plugin}"


@dataclass(frozen=True, slots=True)
class LoadRequest:
    """What to load: the fields of composition_interfaces/LoadNode, plus ``autostart``.

    ``parameters`` holds rclpy parameters, inline mappings or parameter files
    (resolved against ``base_dir``), later entries winning. ``autostart`` is
    also read from ``extra_arguments`` (``-e autostart:=true``), so a LoadNode
    request can ask for it.
    """

    package: str
    plugin: str
    name: str | None = None
    namespace: str | None = None
    remap_rules: Sequence[str] = ()
    parameters: Sequence[Parameter[Any] | ParameterSource] = ()
    extra_arguments: Mapping[str, Any] = field(default_factory=dict)
    log_level: int = 0
    autostart: bool = False
    base_dir: Path | None = None

    @property
    def wants_autostart(self) -> bool:
        """``autostart``, from the field or the extra argument."""
        return self.autostart or self.extra_arguments.get("autostart") is True

    def wants_intra_process(self, default: bool) -> bool:
        """``use_intra_process_comms`` from the extra arguments, else ``default``."""
        value = self.extra_arguments.get("use_intra_process_comms")
        return default if value is None else value is True


@dataclass(frozen=True, slots=True)
class Restore:
    """What a node restored from a state file keeps of its previous life (:mod:`container._statekeeper`).

    :param unique_id: the id it had, so ``ros2 component list`` shows the same.
    :param changed_parameters: parameters set on it after it was loaded; they
        override the request's for its construction, and are not part of
        what it was loaded with.
    """

    unique_id: int
    changed_parameters: Sequence[Parameter[Any]] = ()


@dataclass(frozen=True, slots=True)
class Carry:
    """What a node reloaded in place of another takes over from it (:mod:`container._reload`).

    :param changed_parameters: the parameters set on the old node since it
        was loaded, at their current values; they override the request's,
        as a restored node's do.
    :param state: the old node's ``reload_state`` dict, handed to the new
        node before its constructor runs.
    """

    changed_parameters: Sequence[Parameter[Any]] = ()
    state: dict[str, Any] = field(default_factory=dict)


class _SetSince:
    """An on-set-parameters callback that notes which declared parameters are set after construction.

    A name set on a node that already has it is a change (a ``set_parameters``
    call, from a peer or from the node); a declaration is not. What the
    value became is read when it is wanted, so a set another callback
    rejects costs nothing but a read of the unchanged value.
    """

    __slots__ = ("_node", "names")

    def __init__(self, node: Node) -> None:
        # Weakly: the node holds this callback, and a cycle would keep an
        # unloaded node's memory until the garbage collector runs.
        self._node = weakref.ref(node)
        self.names: dict[str, None] = {}

    def __call__(self, parameters: list[Parameter[Any]]) -> SetParametersResult:
        node = self._node()
        if node is not None:
            for parameter in parameters:
                if node.has_parameter(parameter.name):
                    self.names[parameter.name] = None
        return SetParametersResult(successful=True)

    def current(self) -> list[Parameter[Any]]:
        node = self._node()
        if node is None:
            return []
        return [node.get_parameter(name) for name in self.names if node.has_parameter(name)]


@dataclass(eq=False, slots=True)
class LoadedNode:
    """A node living in the container."""

    unique_id: int
    node: Node
    node_type: NodeType
    request: LoadRequest
    full_name: str
    #: Whether the executor runs its callbacks yet (see ``ComponentManager.load``).
    served: bool = True
    #: What its load (and autostart) warned of, in order, for whoever asked
    #: for it: the LoadNode answer, ``container run``'s summary. Logged too.
    warnings: list[LoadWarning] = field(default_factory=list)
    #: The parameter overrides its request resolved to (parameter files read),
    #: in order: what it was loaded with.
    parameters: tuple[Parameter[Any], ...] = ()
    #: Restored from a state file, and no load has asked for it since (see
    #: ``ComponentManager.load``).
    restored: bool = False
    #: Which of its parameters were set since it was constructed.
    _set_since: _SetSince | None = None

    def changed_parameters(self) -> list[Parameter[Any]]:
        """The parameters set on the node since it was loaded, at their current values."""
        return [] if self._set_since is None else self._set_since.current()


class LoadWatcher(Protocol):
    """Told of every node that enters or leaves the container (the state file's keeper)."""

    def loaded(self, loaded: LoadedNode) -> None:
        """Handle a node just loaded (not necessarily served yet)."""

    def unloaded(self, loaded: LoadedNode) -> None:
        """Handle a node just taken off the container's list, before it goes down its lifecycle."""


class ComponentManager(FastLogging, Node):
    """The container's own node (``ComponentManager`` by default, like rclcpp's).

    :param registry: the node types that may be loaded.
    :param executor: where loaded nodes run.
    :param unload_timeout: seconds each lifecycle step of an unload may take.
    :param use_intra_process_comms: whether a loaded node joins intra-process
        communication when its request does not say.
    """

    def __init__(
        self,
        *,
        registry: PluginRegistry,
        executor: AsyncioExecutor,
        name: str = "ComponentManager",
        namespace: str = "/",
        context: Context | None = None,
        parameter_overrides: Sequence[Parameter[Any]] = (),
        unload_timeout: float = 5.0,
        load_timeout: float = 10.0,
        use_intra_process_comms: bool = False,
    ) -> None:
        super().__init__(
            name,
            namespace=namespace,
            context=context,
            parameter_overrides=list(parameter_overrides),
            # The command line's ROS arguments are the container node's (as
            # rclcpp's): launch_ros names it with -r __node:= and -r __ns:=.
            use_global_arguments=True,
        )
        self.registry = registry
        self._host = executor
        # rclcpp's containers declare it (component_container_mt reads it), so
        # launch files pass it and `ros2 param get` expects it.
        self.declare_parameter(
            "thread_num",
            os.cpu_count() or 1,
            ParameterDescriptor(description=THREAD_NUM_DESCRIPTION, read_only=True),
        )
        self.unload_timeout = unload_timeout
        self.load_timeout = load_timeout
        self.use_intra_process_comms = use_intra_process_comms
        self._background: set[asyncio.Task[None]] = set()
        self._next_id = 1
        self._loaded: dict[int, LoadedNode] = {}
        self._ignored_arguments: set[str] = set()
        #: Told of every load and unload, if set.
        self.watcher: LoadWatcher | None = None
        #: Held by whatever changes the set of loaded nodes from outside
        #: (the container services, a reload), so that they apply one at a time.
        self.changing = asyncio.Lock()
        #: Set by :meth:`unload_all`: nothing is loaded after it.
        self.closed = False
        #: What unloaded nodes freed, given back to the system once unloads settle.
        self.memory = MemoryReturn(log=lambda trimmed: self.get_logger().info(trimmed.describe()))

    # -- queries ------------------------------------------------------------------
    def loaded(self) -> list[LoadedNode]:
        """Loaded nodes in load order."""
        return list(self._loaded.values())

    def holds(self, loaded: LoadedNode) -> bool:
        """Whether ``loaded`` is still loaded (not unloaded since)."""
        return self._loaded.get(loaded.unique_id) is loaded

    def find(self, unique_id: int) -> LoadedNode:
        try:
            return self._loaded[unique_id]
        except KeyError:
            raise LoadError(f"No node found with unique_id: {unique_id}") from None

    def find_named(self, full_name: str) -> LoadedNode:
        """The loaded node whose full name is ``full_name``."""
        for loaded in self._loaded.values():
            if loaded.full_name == full_name:
                return loaded
        raise LoadError(f"No node found named {clip(full_name, quote=True)}")

    @property
    def next_unique_id(self) -> int:
        """The unique id the next load gets: ids count from 1 and are never reused, as rclcpp's."""
        return self._next_id

    def reserve_unique_ids(self, next_id: int) -> None:
        """Never hand out an id below ``next_id`` (those a previous life of the container used)."""
        self._next_id = max(self._next_id, next_id)

    # -- load -------------------------------------------------------------------
    async def load(
        self,
        request: LoadRequest,
        *,
        serve: bool = True,
        restore: Restore | None = None,
        carry: Carry | None = None,
    ) -> LoadedNode:
        """Construct a registered node type and start running it.

        The constructor runs on a thread of its own, bounded by
        ``load_timeout``: one that blocks stalls neither the event loop nor
        any other node. A constructor that fails (raises, exits, times out)
        leaves nothing behind: whatever of the node it built is destroyed
        before the refusal is raised. Autostart, if asked, is left to
        :meth:`load_and_start`, which awaits it.

        :param serve: hand the node to the executor now; with ``False`` it
            waits for :meth:`serve_loaded`. A container file's nodes are all
            constructed first: Fast DDS creates an endpoint more slowly while
            a wait set holds other endpoints, so constructing each node while
            the previous ones are served made 100 constructors 2-3 times as
            slow (measured with plain rclpy and a spinning executor too).
            rclcpp's container never overlaps the two either: its executor
            runs the constructor.
        :param restore: the node comes back from a state file, with its unique
            id and the parameters set on it since. Until a load asks for it,
            a load of the same full name is answered with it when it asks
            for the same (type, remap rules, parameters, extra arguments,
            log level), as a launch file started again would; a load that
            asks for something else replaces it. Any other node of the same
            name is a duplicate, refused.
        :raises LoadError: with a message fit for a LoadNode response.
        """
        if self.closed:
            raise LoadError("the container is shutting down: it loads nothing more")
        if restore is not None and restore.unique_id in self._loaded:
            raise LoadError(f"unique_id {restore.unique_id} is in use")
        node_type = self.registry.resolve(request.package, request.plugin)
        forward_global_arguments = _check_extra_arguments(request.extra_arguments)
        own = self.get_logger().name
        warnings: list[LoadWarning] = []
        for key in _ignored_extra_arguments(request.extra_arguments):
            ignored = (
                f"Extra component argument {clip(key, quote=True)} is not used by this container: ignored "
                "(as rclcpp's container does)"
            )
            # Every load that passes it hears of it; the log, once.
            warnings.append(LoadWarning(own, ignored))
            if key not in self._ignored_arguments:
                self._ignored_arguments.add(key)
                self.get_logger().warning(f"{ignored}; logged once")
        if request.log_level not in _LOG_LEVELS:
            raise LoadError(f"Invalid log_level {request.log_level}: expected one of 0, 10, 20, 30, 40, 50")
        remaps = [_check_remap(rule) for rule in request.remap_rules]
        name = request.name or _default_name(node_type)
        namespace = _absolute(request.namespace or "/")
        _check_name("node name", name, validate_node_name)
        _check_name("namespace", namespace, validate_namespace)
        # The name the node will have: rcl applies the request's remap rules
        # (__node:=, __ns:=) over the name it is constructed with.
        full_name = _remapped_name(name, namespace, remaps)
        try:
            loaded_with = _overrides(request, full_name)
        except ConfigError as exc:
            raise LoadError(f"Invalid parameters: {exc}") from exc
        restored = self._restored_as(full_name)
        if restored is not None:
            if _same_load(restored, node_type, request, loaded_with):
                restored.restored = False
                self.get_logger().info(
                    f"Load of {clip(full_name, quote=True)} answered with the node restored from the state file "
                    f"(unique_id {restored.unique_id}), loaded with the same settings"
                )
                return restored
            self.get_logger().warning(
                f"Load of {clip(full_name, quote=True)} asks for other settings than the node restored from the "
                f"state file (unique_id {restored.unique_id}): that node is unloaded, this one loaded"
            )
            await self.unload(restored.unique_id)
        self._refuse_duplicate(full_name)
        if forward_global_arguments:
            forwarded = (
                f"Loading {clip(full_name)} with forward_global_arguments: the container's own ROS "
                "arguments (its name, namespace, parameters, remaps) apply to that node too"
            )
            self.get_logger().warning(forwarded)
            warnings.append(LoadWarning(own, forwarded))
        overrides = [*loaded_with]
        set_since_load = [
            *(restore.changed_parameters if restore is not None else ()),
            *(carry.changed_parameters if carry is not None else ()),
        ]
        if set_since_load:
            changed = {parameter.name: parameter for parameter in set_since_load}
            overrides = [*(p for p in overrides if p.name not in changed), *changed.values()]
        if not any(parameter.name == TYPE_DESCRIPTION_SERVICE for parameter in overrides):
            # A node's ~/get_type_description service is a DDS reader and
            # writer (about 100 kB) that next to no tool asks; loaded nodes
            # start without it unless asked (-p
            # start_type_description_service:=true). rclpy 7-9 never
            # finalise it; an unload does (see _destroy).
            overrides.append(Parameter(TYPE_DESCRIPTION_SERVICE, value=False))
        cli_args = ["--ros-args", *(part for rule in remaps for part in ("-r", rule))] if remaps else None
        intra_process = request.wants_intra_process(self.use_intra_process_comms)
        # A node joins intra-process from its constructor on, so that what
        # the constructor creates joins too; its class (or its intra-process
        # subclass) takes the keyword.
        node_class = intra_process_class(node_type.node_class) if intra_process else node_type.node_class
        options = {"use_intra_process_comms": True} if intra_process else {}
        built: list[Node] = []

        def construct() -> Node:
            # __new__ apart from __init__, so that a constructor failing half
            # way still leaves us the object to destroy.
            node = node_class.__new__(node_class)
            built.append(node)
            if carry is not None:
                # Before the constructor, so that it reads what the old node kept.
                setattr(node, RELOAD_STATE, carry.state)
            node.__init__(  # type: ignore[misc]
                name,
                namespace=namespace,
                context=self.context,
                cli_args=cli_args,
                # rclcpp's default: the container's command line is the container's.
                use_global_arguments=forward_global_arguments,
                parameter_overrides=overrides,
                **options,
            )
            return node

        accounting = self._host.accounting
        # The constructor, and the threads it starts, are the new node's (by the name it is loaded as).
        with accounting.working_as(full_name) if accounting is not None else contextlib.nullcontext():
            construction = asyncio.ensure_future(in_thread(construct, name=f"construct:{clip(full_name)}"))
        try:
            node = await asyncio.wait_for(asyncio.shield(construction), self.load_timeout)
            # Remap rules (__node:=, __ns:=) or the class may have renamed it.
            self._refuse_duplicate(node.get_fully_qualified_name())
            if request.log_level:
                node.get_logger().set_level(request.log_level)
        except TimeoutError:
            # It may return yet: whatever it built is destroyed then.
            construction.add_done_callback(lambda _: _discard(built))
            raise LoadError(f"Component constructor did not return within {self.load_timeout:g} s") from None
        except (InvalidNodeNameException, InvalidNamespaceException) as exc:
            _discard(built)
            raise LoadError(f"Invalid node name or namespace: {_one_line(exc)}") from exc
        except InvalidROSArgsError as exc:
            _discard(built)
            raise LoadError(f"Invalid remap rules: {_one_line(exc)}") from exc
        except LoadError:
            _discard(built)
            raise
        except (KeyboardInterrupt, asyncio.CancelledError):
            _discard(built)
            raise
        except BaseException as exc:  # sys.exit() in a constructor ends only that load
            _discard(built)
            error = exc.error if isinstance(exc, Escaped) else exc
            # The answer carries one line; the log, where it came from.
            self.get_logger().error(
                f"Component constructor of {node_type.full_name} ({clip(full_name, quote=True)}) raised "
                f"{_one_line(error)}\n{format_plugin_frames(error.__traceback__, innermost_first=False)}"
            )
            raise LoadError(f"Component constructor threw an exception: {_one_line(error)}") from exc
        unique_id = self._next_id if restore is None else restore.unique_id
        self._next_id = max(self._next_id, unique_id + 1)
        set_since = _SetSince(node)
        # What a previous life of the node had set counts as set on this one.
        set_since.names.update(dict.fromkeys(parameter.name for parameter in set_since_load))
        node.add_on_set_parameters_callback(set_since)
        loaded = LoadedNode(
            unique_id, node, node_type, request, node.get_fully_qualified_name(), served=serve,
            warnings=warnings, parameters=tuple(loaded_with), restored=restore is not None,
            _set_since=set_since,
        )
        self._loaded[loaded.unique_id] = loaded
        if serve:
            self._host.add_node(node)
        self.get_logger().info(
            f"Loaded {node_type.full_name} as '{loaded.full_name}' (unique_id {loaded.unique_id})"
        )
        logger = node.get_logger()
        if isinstance(node, LifecycleNode):
            # Ours check after their first configure, when all is declared;
            # a typo of what the constructor declared is told now.
            parameter_warnings = node.warn_likely_typos()
        else:
            parameter_warnings = checks.unread_parameters(node, [parameter.name for parameter in overrides])
            for warning in parameter_warnings:
                logger.warning(warning)
        warnings.extend(LoadWarning(logger.name, warning) for warning in parameter_warnings)
        if self.watcher is not None:
            self.watcher.loaded(loaded)
        return loaded

    def serve_loaded(self, nodes: Iterable[LoadedNode]) -> None:
        """Hand nodes loaded with ``serve=False`` to the executor; skip those unloaded since."""
        for loaded in nodes:
            if not loaded.served and self.holds(loaded):
                loaded.served = True
                self._host.add_node(loaded.node)

    def _restored_as(self, full_name: str) -> LoadedNode | None:
        """The node restored from a state file under ``full_name`` that no load has asked for yet."""
        for other in self._loaded.values():
            if other.restored and other.full_name == full_name:
                return other
        return None

    def _refuse_duplicate(self, full_name: str) -> None:
        if full_name == self.get_fully_qualified_name():
            raise LoadError(f"A node named '{full_name}' is the container itself")
        for other in self._loaded.values():
            if other.full_name == full_name:
                raise LoadError(
                    f"A node named '{full_name}' is already loaded (unique_id {other.unique_id})"
                )

    async def load_and_start(self, request: LoadRequest, *, timeout: float) -> LoadedNode:
        """:meth:`load`, then bring a lifecycle node up when ``autostart`` asks.

        A node that fails to come up stays loaded, in the state it reached,
        so that it can be inspected; the failure is raised.
        """
        loaded = await self.load(request)
        if request.wants_autostart:
            await self.start(loaded, timeout=timeout)
        return loaded

    async def start(self, loaded: LoadedNode, *, timeout: float, until: str = "active") -> None:
        """Configure and activate a loaded lifecycle node (a plain node has nothing to do).

        :param timeout: seconds each transition may take.
        :param until: ``inactive`` to configure only.
        :raises TransitionError: a transition failed; the node stays where it stopped.
        """
        if is_lifecycle(loaded.node):
            try:
                await bring_up(self._host, loaded.node, timeout=timeout, until=until)
            finally:
                self._collect_configure_warnings(loaded)

    async def shut_down(self, loaded: LoadedNode, *, timeout: float) -> None:
        """Shut a loaded lifecycle node down for good (``finalized``), from the state it is in.

        :raises TransitionError: the shutdown failed.
        """
        if is_lifecycle(loaded.node):
            await transition(self._host, loaded.node, "shutdown", timeout=timeout)

    @staticmethod
    def _collect_configure_warnings(loaded: LoadedNode) -> None:
        """Add what the node's configure warned of (its unread parameters) to its load's warnings."""
        node = loaded.node
        if not isinstance(node, LifecycleNode):
            return
        logger = node.get_logger().name
        known = {warning.message for warning in loaded.warnings if warning.logger == logger}
        loaded.warnings.extend(
            LoadWarning(logger, message) for message in node.parameter_warnings if message not in known
        )

    # -- unload -------------------------------------------------------------------
    async def unload(self, unique_id: int, *, off_graph: bool = True) -> tuple[LoadedNode, list[str]]:
        """Take the node down its lifecycle, stop what still runs, then destroy it.

        rclcpp destroys a component without running its shutdown; here a
        lifecycle node is deactivated, cleaned up and shut down first, each
        step bounded by ``unload_timeout``. A transition already in progress
        (a ``change_state`` from a peer) is waited for, and cancelled past
        ``unload_timeout``; callbacks still running are cancelled or waited
        for, as long again, and the answers they gave sent (a caller still
        being discovered has up to a second). Nothing is destroyed while one
        of its callbacks still uses it: a plain callback blocked for good keeps its node's
        state machine (and so its lifecycle services) until it returns. An
        unload always removes the node.

        :param off_graph: return once the node is off the ROS graph, as
            rclcpp's unload does (a node of the same name may be loaded next);
            ``False`` where nobody looks any more (a shutdown's unloads: each
            such wait costs a rebuild of the wait sets, half a second for a
            hundred demo nodes), and the node leaves the graph a moment later.
        :return: the node, and notes on what had to be cut short.
        :raises LoadError: no node has ``unique_id``.
        """
        loaded = self.find(unique_id)
        # Down its lifecycle on the executor like any other (a file's node
        # unloaded while the file still loads was not served yet).
        self.serve_loaded([loaded])
        del self._loaded[unique_id]
        if self.watcher is not None:
            self.watcher.unloaded(loaded)
        node = loaded.node
        notes: list[str] = []
        if isinstance(node, LifecycleNode):
            cut = await node.end_transition(timeout=self.unload_timeout)
            if cut is not None:
                notes.append(cut)
        if is_lifecycle(node):
            try:
                await bring_down(self._host, node, timeout=self.unload_timeout)
            except TransitionError as exc:
                notes.append(f"taken down incompletely: {exc.reason}")
        stuck = await self._host.retire(node, timeout=self.unload_timeout, released=off_graph)
        if stuck:
            notes.append(
                f"still running after {self.unload_timeout:g} s, left to finish: {', '.join(stuck)}"
            )
            self._spawn(self._destroy_when_idle(node))
        else:
            _destroy(node, held=not off_graph)
            self.memory.unloaded()
        log = self.get_logger()
        for note in notes:
            log.warning(f"Unloading '{loaded.full_name}': {note}")
        log.info(f"Unloaded '{loaded.full_name}' (unique_id {unique_id})")
        return loaded, notes

    async def _destroy_when_idle(self, node: Node) -> None:
        """Destroy ``node`` once its last blocked callback has returned."""
        while await self._host.retire(node, timeout=1.0):
            pass
        _destroy(node, held=False)
        self.memory.unloaded()
        self.get_logger().info(f"Released '{node.get_fully_qualified_name()}': its last callback returned")

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.ensure_future(coro)
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    async def unload_all(self) -> None:
        """Unload every node, the last loaded first; load nothing after.

        A load or a reload under way (they hold :attr:`changing`) ends first:
        a reload's new nodes, loaded after this began, would otherwise
        outlive it (each bounded by ``load_timeout``).
        """
        async with self.changing:
            self.closed = True
            for unique_id in reversed(list(self._loaded)):
                await self.unload(unique_id, off_graph=False)
        for task in list(self._background):
            task.cancel()
        self.memory.close()


def _same_load(
    loaded: LoadedNode, node_type: NodeType, request: LoadRequest, parameters: Sequence[Parameter[Any]]
) -> bool:
    """Whether ``request`` (resolving to ``parameters``) asks for what ``loaded`` was loaded with."""
    return (
        node_type.full_name == loaded.node_type.full_name
        and tuple(request.remap_rules) == tuple(loaded.request.remap_rules)
        and same_parameters(parameters, loaded.parameters)
        and dict(request.extra_arguments) == dict(loaded.request.extra_arguments)
        and request.log_level == loaded.request.log_level
    )


def _discard(built: list[Node]) -> None:
    """Destroy what a failed constructor built, so it leaves nothing on the graph."""
    for node in built:
        if is_built(node):
            # The base class's: an override may rely on attributes the
            # failed constructor never set.
            with contextlib.suppress(Exception):
                finish_type_description_service(node)  # never served: nothing holds it
            with contextlib.suppress(Exception):
                Node.destroy_node(node)
        machine = state_machine_if_built(node)
        if machine is not None:
            machine.destroy_when_not_in_use()
    built.clear()


def _destroy(node: Node, *, held: bool) -> None:
    """Destroy ``node`` now, not whenever the garbage collector gets to it.

    :param held: whether a wait set may still hold the node's entities (a
        shutdown's unloads do not wait for them to let go). Else its type
        description service, which rclpy leaves on the graph and in Fast
        DDS for good, is finalised first: a shutdown ends the process anyway.
    """
    if not held:
        try:
            finish_type_description_service(node)
        except Exception as exc:  # rcl's failure: the node is destroyed all the same
            node.get_logger().warning(f"its type description service stays on the graph: {exc}")
    node.destroy_node()
    # rclpy's LifecycleNode keeps a C++ state machine that holds the rcl node
    # (and its transition_event publisher); destroy_node leaves it, so the node
    # would stay on the ROS graph until the Python object is collected.
    if isinstance(node, LifecycleNodeMixin):
        state_machine(node).destroy_when_not_in_use()


def _check_extra_arguments(arguments: Mapping[str, Any]) -> bool:
    """Check the extra arguments this container reads; return ``forward_global_arguments`` (rclcpp's default: false).

    Others are not refused: rclcpp's container ignores extra arguments it
    does not know, and launch files written for it pass some
    (``enable_rosout``); the manager logs each such name once.
    """
    for key, value in arguments.items():
        expected = _EXTRA_ARGUMENTS.get(key)
        if expected is not None and not isinstance(value, expected):
            raise LoadError(
                f"Extra component argument '{key}' must be a {_TYPE_WORDS[expected]}"
            )
    return arguments.get("forward_global_arguments") is True


def _ignored_extra_arguments(arguments: Mapping[str, Any]) -> list[str]:
    return [key for key in arguments if key not in _EXTRA_ARGUMENTS]


def _remapped_name(name: str, namespace: str, rules: Sequence[str]) -> str:
    """The full name rcl gives a node constructed as ``namespace``/``name`` with ``rules``.

    rcl uses the first rule that matches, a rule prefixed ``node:`` only for
    the node constructed as ``node``. The constructed node's own name is
    checked again: a class may pick another name, and global arguments may
    apply too.
    """
    found: dict[str, str] = {}
    for rule in rules:
        source, _, target = rule.partition(":=")
        node, _, source = source.rpartition(":")
        if source in ("__node", "__ns") and node in ("", name):
            found.setdefault(source, target)
    namespace = found.get("__ns", namespace)
    return f"{namespace.rstrip('/')}/{found.get('__node', name)}"


#: ``from:=to``, optionally node-specific (``node:from:=to``); rcl checks the rest.
_REMAP = re.compile(r"^(?:[^:=\s]+:)?[^:=\s]+:=[^:=\s]+$")


def _check_name(what: str, value: str, validate: Callable[[str], object]) -> None:
    """Refuse a node name or namespace rcl would refuse, or would cut short.

    A NUL passes rcl's validation (it reads C strings) and would name the
    node after what comes before it: ``a\x00b`` would load as ``/a``.
    """
    if "\x00" in value:
        raise LoadError(f"Invalid {what} {clip(value, quote=True)}: must not contain a NUL character")
    try:
        validate(value)
    except (InvalidNodeNameException, InvalidNamespaceException) as exc:
        # rclpy's message spans lines (the name, a caret under the fault).
        reason = str(exc).splitlines()[0].split(": ", 1)[-1].rstrip(":")
        raise LoadError(f"Invalid {what} {clip(value, quote=True)}: {reason}") from None


#: A parameter name as rcl's ``-p`` parser takes one: tokens of letters,
#: digits and underscores, separated by ``.`` or ``/`` (``qos_overrides./chatter.depth``).
_PARAMETER_NAME = re.compile(r"^[A-Za-z0-9_]+(?:(?:\.|/|\./)[A-Za-z0-9_]+)*$")


def _check_parameter_name(name: str) -> None:
    if not _PARAMETER_NAME.match(name):
        problem = "must not be empty" if not name else (
            "must be words of letters, digits and '_' joined by '.' or '/' (no '..', '//', NUL, or '.'/'/' at an end)"
        )
        raise LoadError(f"Invalid parameters: parameter name {clip(name, quote=True)} {problem}")


def _check_remap(rule: str) -> str:
    if "\x00" in rule:
        raise LoadError(f"Invalid remap rule {clip(rule, quote=True)}: must not contain a NUL character")
    if not _REMAP.match(rule):
        raise LoadError(f"Invalid remap rule {clip(rule, quote=True)}: expected 'from:=to'")
    return rule


def _absolute(namespace: str) -> str:
    return namespace if namespace.startswith("/") else f"/{namespace}"


def _default_name(node_type: NodeType) -> str:
    default = getattr(node_type.node_class, "default_node_name", None)
    if isinstance(default, str) and default:
        return default
    return re.sub(r"(?<!^)(?=[A-Z])", "_", node_type.name).lower()


def _overrides(request: LoadRequest, full_name: str) -> list[Parameter[Any]]:
    merged: dict[str, Parameter[Any]] = {}
    sources: list[ParameterSource] = []

    def flush() -> None:
        for parameter in node_parameters(sources, full_name=full_name, base_dir=request.base_dir):
            merged[parameter.name] = parameter
        sources.clear()

    for entry in request.parameters:
        if isinstance(entry, Parameter):
            flush()
            merged[entry.name] = entry
        else:
            sources.append(entry)
    flush()
    for name in merged:
        _check_parameter_name(name)
    return list(merged.values())


def _one_line(exc: BaseException) -> str:
    text = clip(" ".join(str(exc).split()))
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def entry_label(index: int, request: LoadRequest) -> str:
    """How logs name the ``index``-th node of a container file: ``nodes[3] (name: front_lidar)``.

    Two entries of one type are told apart by their name; an unnamed
    entry by its type.
    """
    what = f"name: {request.name}" if request.name else f"type: {type_label(request.package, request.plugin)}"
    return f"nodes[{index}] ({clip(what)})"


def requests_from_specs(specs: Iterable[Any]) -> list[LoadRequest]:
    """Turn the ``nodes`` of a container file into load requests."""
    return [
        LoadRequest(
            package=spec.package,
            plugin=spec.plugin,
            name=spec.name,
            namespace=spec.namespace,
            remap_rules=spec.remap_rules,
            parameters=spec.parameters,
            extra_arguments=spec.extra_arguments,
            autostart=spec.autostart,
            base_dir=spec.base_dir,
        )
        for spec in specs
    ]
