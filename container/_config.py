"""The container's YAML file, with the field names launch_ros users write.

::

    container:                      # all optional
      name: ComponentManager
      namespace: /
      parameters: [params.yaml]     # for the container node itself
      plugins: {allow: [...], block: [...], trace: false}
      devices:                      # what port parameters may name (container.devices)
        serial: ["/dev/ttyUSB*", "/dev/ttyACM*", "/dev/serial/by-id/*", "/dev/serial/by-path/*", "/dev/ldlidar"]
        replay_dirs: [captures]     # file:// replays only below these (default: none)
        replay_max_bytes: 67108864
        network: false              # socket:// and rfc2217:// ports
      reentrant_limit: 8
      unload_timeout: 5.0           # seconds each step of taking a node down may take
      load_timeout: 10.0            # seconds a node's constructor may take
      shutdown_timeout: 5.0         # seconds a stuck event loop may hold up SIGINT/SIGTERM
      watchdog_threshold: 1.0       # seconds a plugin may hold the event loop before it is reported
      on_failure: continue          # a listed node that fails to load or start: continue | exit
      use_intra_process_comms: false  # the default of the nodes' extra argument
    nodes:
      - package: lifecycle_container
        plugin: lifecycle_container::Talker
        name: talker
        namespace: /demo
        parameters: [{rate: 2.0}, params.yaml]
        remappings: [[chatter, /demo/chatter]]     # or {from:, to:} or "a:=b"
        extra_arguments: [{use_intra_process_comms: true}]
        autostart: true
    manager:                        # optional: a lifecycle manager in-process
      node_names: [/demo/talker]
      autostart: true

Every mistake is reported with its place (``nodes[1].remappings[0]``) and
unknown keys are refused, so a typo never silently drops a setting.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.exceptions import InvalidNamespaceException, InvalidNodeNameException
from rclpy.validate_namespace import validate_namespace
from rclpy.validate_node_name import validate_node_name

from . import checks
from ._errors import ConfigError
from ._params import ParameterSource
from ._yaml import read_yaml
from .devices import DevicePolicy

__all__ = ["ON_FAILURE", "ContainerConfig", "NodeSpec", "load_config", "parse_config", "read_yaml"]


@dataclass(frozen=True, slots=True)
class NodeSpec:
    """One node to load, as a launch_ros ``ComposableNode`` describes it."""

    package: str
    plugin: str
    name: str | None = None
    namespace: str | None = None
    parameters: tuple[ParameterSource, ...] = ()
    remap_rules: tuple[str, ...] = ()
    extra_arguments: Mapping[str, Any] = field(default_factory=dict)
    autostart: bool = False
    base_dir: Path | None = None


@dataclass(frozen=True, slots=True)
class ContainerConfig:
    """Everything ``container run`` needs from its file."""

    name: str = "ComponentManager"
    namespace: str = "/"
    parameters: tuple[ParameterSource, ...] = ()
    plugins_allow: tuple[str, ...] | None = None
    plugins_block: tuple[str, ...] = ()
    trace_hooks: bool = False
    devices: DevicePolicy = field(default_factory=DevicePolicy)
    reentrant_limit: int = 8
    unload_timeout: float = 5.0
    load_timeout: float = 10.0
    shutdown_timeout: float = 5.0
    watchdog_threshold: float = 1.0
    on_failure: str = "continue"
    use_intra_process_comms: bool = False
    nodes: tuple[NodeSpec, ...] = ()
    manager: Mapping[str, Any] | None = None
    base_dir: Path | None = None

    @property
    def full_name(self) -> str:
        """The container node's full name (``/ns/name``)."""
        namespace = self.namespace if self.namespace.startswith("/") else f"/{self.namespace}"
        return f"{namespace.rstrip('/')}/{self.name}"


_CONTAINER_KEYS = {
    "name",
    "namespace",
    "parameters",
    "plugins",
    "devices",
    "reentrant_limit",
    "unload_timeout",
    "load_timeout",
    "shutdown_timeout",
    "watchdog_threshold",
    "on_failure",
    "use_intra_process_comms",
}

#: What ``container run`` does when a node its file lists fails to load or
#: start: serve on with the others (rclcpp's container never exits for a
#: failed load), or take everything down and exit 1 (for a launch file or a
#: systemd unit that must notice).
ON_FAILURE = ("continue", "exit")
_NODE_KEYS = {
    "package",
    "plugin",
    "name",
    "namespace",
    "parameters",
    "remappings",
    "extra_arguments",
    "autostart",
}


def load_config(path: str | Path) -> ContainerConfig:
    """Read and check a container file."""
    path = Path(path)
    return parse_config(read_yaml(path), base_dir=path.parent, source=str(path))


def parse_config(
    document: Any, *, base_dir: Path | None = None, source: str = "config"
) -> ContainerConfig:
    """Check a parsed container document; paths resolve against ``base_dir``."""
    if document is None:
        document = {}
    top = _mapping(document, f"{source}")
    _no_unknown(top, {"container", "nodes", "manager"}, source)
    container = _mapping(top.get("container") or {}, f"{source}: container")
    _no_unknown(container, _CONTAINER_KEYS, f"{source}: container")
    plugins = _mapping(container.get("plugins") or {}, f"{source}: container.plugins")
    _no_unknown(plugins, {"allow", "block", "trace"}, f"{source}: container.plugins")
    allow = plugins.get("allow")
    nodes_value = top.get("nodes") or []
    if not isinstance(nodes_value, list):
        raise ConfigError("must be a list of nodes", source=f"{source}: nodes")
    manager = top.get("manager")
    if manager is not None:
        manager = _mapping(manager, f"{source}: manager")
    return ContainerConfig(
        name=_node_name(container.get("name", "ComponentManager"), f"{source}: container.name"),
        namespace=_namespace(container.get("namespace", "/"), f"{source}: container.namespace"),
        parameters=_parameter_sources(container.get("parameters"), f"{source}: container.parameters"),
        plugins_allow=None if allow is None else _strings(allow, f"{source}: container.plugins.allow"),
        plugins_block=_strings(plugins.get("block") or [], f"{source}: container.plugins.block"),
        trace_hooks=_bool(plugins.get("trace", False), f"{source}: container.plugins.trace"),
        devices=DevicePolicy.from_mapping(
            _mapping(container["devices"] or {}, f"{source}: container.devices"),
            source=f"{source}: container.devices",
            base_dir=base_dir,
        )
        if "devices" in container
        else DevicePolicy(),
        reentrant_limit=_positive_int(
            container.get("reentrant_limit", 8), f"{source}: container.reentrant_limit"
        ),
        unload_timeout=_positive_float(
            container.get("unload_timeout", 5.0), f"{source}: container.unload_timeout"
        ),
        load_timeout=_positive_float(container.get("load_timeout", 10.0), f"{source}: container.load_timeout"),
        shutdown_timeout=_positive_float(
            container.get("shutdown_timeout", 5.0), f"{source}: container.shutdown_timeout"
        ),
        watchdog_threshold=_positive_float(
            container.get("watchdog_threshold", 1.0), f"{source}: container.watchdog_threshold"
        ),
        on_failure=_choice(container.get("on_failure", "continue"), ON_FAILURE, f"{source}: container.on_failure"),
        use_intra_process_comms=_bool(
            container.get("use_intra_process_comms", False), f"{source}: container.use_intra_process_comms"
        ),
        nodes=tuple(
            _node(entry, base_dir=base_dir, where=f"{source}: nodes[{index}]")
            for index, entry in enumerate(nodes_value)
        ),
        manager=manager,
        base_dir=base_dir,
    )


def _node(value: Any, *, base_dir: Path | None, where: str) -> NodeSpec:
    node = _mapping(value, where)
    _no_unknown(node, _NODE_KEYS, where)
    for key in ("package", "plugin"):
        if key not in node:
            raise ConfigError(f"missing {key!r}", source=where)
    name = node.get("name")
    namespace = node.get("namespace")
    return NodeSpec(
        package=_string(node["package"], f"{where}.package"),
        plugin=_string(node["plugin"], f"{where}.plugin"),
        name=None if name is None else _string(name, f"{where}.name"),
        namespace=None if namespace is None else _string(namespace, f"{where}.namespace"),
        parameters=_parameter_sources(node.get("parameters"), f"{where}.parameters"),
        remap_rules=_remappings(node.get("remappings") or [], f"{where}.remappings"),
        extra_arguments=_extra_arguments(node.get("extra_arguments") or [], f"{where}.extra_arguments"),
        autostart=_bool(node.get("autostart", False), f"{where}.autostart"),
        base_dir=base_dir,
    )


def _remappings(value: Any, where: str) -> tuple[str, ...]:
    if not isinstance(value, list):
        raise ConfigError("must be a list of [from, to] pairs", source=where)
    rules = []
    for index, item in enumerate(value):
        place = f"{where}[{index}]"
        if isinstance(item, str) and ":=" in item:
            source, target = item.split(":=", 1)
        elif isinstance(item, Mapping) and set(item) == {"from", "to"}:
            source, target = item["from"], item["to"]
        elif isinstance(item, Sequence) and not isinstance(item, str) and len(item) == 2:
            source, target = item
        else:
            raise ConfigError("expected [from, to], {from: ..., to: ...} or 'from:=to'", source=place)
        source, target = _string(source, place), _string(target, place)
        if not source or not target:
            raise ConfigError("both sides of a remapping must be non-empty", source=place)
        rules.append(f"{source}:={target}")
    return tuple(rules)


def _extra_arguments(value: Any, where: str) -> dict[str, Any]:
    if isinstance(value, Mapping):
        return dict(value)
    if not isinstance(value, list):
        raise ConfigError("must be a list of {name: value} mappings", source=where)
    merged: dict[str, Any] = {}
    for index, item in enumerate(value):
        merged.update(_mapping(item, f"{where}[{index}]"))
    return merged


def _parameter_sources(value: Any, where: str) -> tuple[ParameterSource, ...]:
    if value is None:
        return ()
    if isinstance(value, Mapping):
        return (dict(value),)
    if not isinstance(value, list):
        raise ConfigError("must be a list of mappings and parameter file paths", source=where)
    sources: list[ParameterSource] = []
    for index, item in enumerate(value):
        if isinstance(item, Mapping):
            sources.append(dict(item))
        elif isinstance(item, str):
            sources.append(item)
        else:
            raise ConfigError("expected a mapping or a file path", source=f"{where}[{index}]")
    return tuple(sources)


def _mapping(value: Any, where: str) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"expected a mapping, not {type(value).__name__}", source=where)
    for key in value:
        if not isinstance(key, str):
            raise ConfigError(f"keys must be strings, not {key!r}", source=where)
    return dict(value)


def _no_unknown(value: Mapping[str, Any], known: set[str], where: str) -> None:
    unknown = sorted(set(value) - known)
    if unknown:
        raise ConfigError(
            f"unknown key(s) {', '.join(map(repr, unknown))}; expected {', '.join(sorted(known))}",
            source=where,
        )


def _node_name(value: Any, where: str) -> str:
    name = checks.string(value, where=where)
    try:
        validate_node_name(name)
    except InvalidNodeNameException as exc:
        raise ConfigError(f"not a valid node name: {' '.join(str(exc).split())}", source=where) from None
    return name


def _namespace(value: Any, where: str) -> str:
    namespace = checks.string(value, where=where)
    try:
        validate_namespace(namespace if namespace.startswith("/") else f"/{namespace}")
    except InvalidNamespaceException as exc:
        raise ConfigError(f"not a valid namespace: {' '.join(str(exc).split())}", source=where) from None
    return namespace


def _string(value: Any, where: str) -> str:
    return checks.string(value, where=where, empty=True)


def _strings(value: Any, where: str) -> tuple[str, ...]:
    return checks.strings(value, where=where)


def _bool(value: Any, where: str) -> bool:
    return checks.boolean(value, where=where)


def _positive_int(value: Any, where: str) -> int:
    return checks.integer(value, where=where, minimum=1)


def _choice(value: Any, choices: Sequence[str], where: str) -> str:
    text = checks.string(value, where=where)
    if text not in choices:
        raise ConfigError(f"expected one of {', '.join(choices)}, not {text!r}", source=where)
    return text


def _positive_float(value: Any, where: str) -> float:
    return checks.number(value, where=where, positive=True)
