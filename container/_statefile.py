"""The state file: what a container hosts, kept on disk so that a respawned container restores it.

A container given the ``state_file`` parameter records there every node it
hosts, the way each was loaded (type, name, namespace, remap rules,
parameters, extra arguments, log level), the parameters set on it since and
its lifecycle state, and the next unique id it would hand out.
:mod:`container._statekeeper` keeps the file in step with the container;
this module is the file alone: its format, read and written whole.

The format is JSON (a person can read it, Python writes it without a
dependency), versioned: a file of another format or version is refused
whole, never half read. Parameters keep their ROS type (``double`` ``5.0``
is not ``integer`` ``5``)::

    {"format": "lifecycle_container.state", "version": 1,
     "container": "/robot/my_container", "next_unique_id": 3,
     "written": "2025-01-01T12:00:00Z", "pid": 4242,
     "nodes": [{"unique_id": 1, "package": "lifecycle_container",
                "plugin": "lifecycle_container::Talker", "name": "talker",
                "namespace": "/demo", "full_name": "/demo/talker",
                "remap_rules": ["chatter:=/demo/chatter"],
                "parameters": [{"name": "rate", "type": "double", "value": 5.0}],
                "changed_parameters": [], "extra_arguments": [],
                "log_level": 0, "state": "active"}]}

A write replaces the file atomically: a temporary file in the same
directory, written, flushed to the disk (``fsync``), renamed over the old
one, and the directory flushed too; a reader (the next container) finds the
old file or the new one, whole, even after a crash or a power cut
mid-write.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rclpy.parameter import Parameter

from ._errors import StateFileError

__all__ = [
    "FORMAT",
    "LIFECYCLE_STATES",
    "MAX_BYTES",
    "VERSION",
    "ContainerState",
    "NodeRecord",
    "decode",
    "encode",
    "read_state",
    "same_parameters",
    "set_aside",
    "temporary_files",
    "write_atomically",
]

#: What the file says it is, and the one version of it this container reads.
FORMAT = "lifecycle_container.state"
VERSION = 1

#: A larger file is not one a container wrote (100 nodes take about 50 kB).
MAX_BYTES = 16 * 1024 * 1024

#: The primary states a lifecycle node is recorded in.
LIFECYCLE_STATES = ("unconfigured", "inactive", "active", "finalized")

#: The ROS names of the parameter types (``ros2 param describe``), and rclpy's.
_TYPES: dict[str, Parameter.Type] = {
    "bool": Parameter.Type.BOOL,
    "integer": Parameter.Type.INTEGER,
    "double": Parameter.Type.DOUBLE,
    "string": Parameter.Type.STRING,
    "byte_array": Parameter.Type.BYTE_ARRAY,
    "bool_array": Parameter.Type.BOOL_ARRAY,
    "integer_array": Parameter.Type.INTEGER_ARRAY,
    "double_array": Parameter.Type.DOUBLE_ARRAY,
    "string_array": Parameter.Type.STRING_ARRAY,
}
_TYPE_NAMES = {kind: name for name, kind in _TYPES.items()}


@dataclass(frozen=True, slots=True)
class NodeRecord:
    """One hosted node, as it was loaded and as it stands.

    :param name: the name the load asked for (``None``: the type's default).
    :param namespace: the namespace the load asked for (``None``: ``/``).
    :param parameters: the overrides the node was constructed with, parameter
        files already read: what a load of the same node resolves to.
    :param changed_parameters: parameters set on the node since it was
        loaded (``ros2 param set``, the node itself), latest value each.
    :param state: its lifecycle state; ``None`` for a node without one.
    """

    unique_id: int
    package: str
    plugin: str
    name: str | None
    namespace: str | None
    full_name: str
    remap_rules: tuple[str, ...] = ()
    parameters: tuple[Parameter[Any], ...] = ()
    changed_parameters: tuple[Parameter[Any], ...] = ()
    extra_arguments: tuple[Parameter[Any], ...] = ()
    log_level: int = 0
    state: str | None = None

    @property
    def type_label(self) -> str:
        return self.plugin if "::" in self.plugin else f"{self.package}::{self.plugin}"


@dataclass(frozen=True, slots=True)
class ContainerState:
    """A container's whole state: its full name, its next unique id, its nodes in load order.

    :param written: when the file was written (UTC, ISO 8601), as read; for the logs.
    :param pid: which process wrote it, as read; for the logs.
    """

    container: str
    next_unique_id: int
    nodes: tuple[NodeRecord, ...] = ()
    written: str | None = None
    pid: int | None = None


def encode(state: ContainerState, *, pid: int | None = None, now: float | None = None) -> bytes:
    """The file's bytes for ``state`` (written by process ``pid`` at ``now``, for whoever reads it)."""
    written = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(time.time() if now is None else now))
    document = {
        "format": FORMAT,
        "version": VERSION,
        "container": state.container,
        "next_unique_id": state.next_unique_id,
        "written": written,
        "pid": os.getpid() if pid is None else pid,
        "nodes": [_encode_node(record) for record in state.nodes],
    }
    return (json.dumps(document, indent=1, ensure_ascii=False) + "\n").encode("utf-8")


def _encode_node(record: NodeRecord) -> dict[str, Any]:
    return {
        "unique_id": record.unique_id,
        "package": record.package,
        "plugin": record.plugin,
        "name": record.name,
        "namespace": record.namespace,
        "full_name": record.full_name,
        "remap_rules": list(record.remap_rules),
        "parameters": encode_parameters(record.parameters),
        "changed_parameters": encode_parameters(record.changed_parameters),
        "extra_arguments": encode_parameters(record.extra_arguments),
        "log_level": record.log_level,
        "state": record.state,
    }


def encode_parameters(parameters: Iterable[Parameter[Any]]) -> list[dict[str, Any]]:
    """Parameters as the file holds them: ``{"name", "type", "value"}`` each, in order."""
    encoded = []
    for parameter in parameters:
        kind = _TYPE_NAMES.get(parameter.type_)
        if kind is None:  # NOT_SET: nothing to restore
            continue
        value: Any = parameter.value
        if parameter.type_ == Parameter.Type.BYTE_ARRAY:
            value = [byte[0] if isinstance(byte, bytes) else int(byte) for byte in value]
        elif parameter.type_ == Parameter.Type.DOUBLE_ARRAY:
            value = [float(item) for item in value]
        elif kind.endswith("_array"):
            value = list(value)
        encoded.append({"name": parameter.name, "type": kind, "value": value})
    return encoded


def decode(data: bytes, *, source: str) -> ContainerState:
    """Read a state file's bytes.

    :param source: the file, for the messages.
    :raises StateFileError: not JSON, not a state file, another version, or
        a field of the wrong type; nothing of it is used then.
    """
    try:
        document = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise StateFileError(f"not UTF-8 text ({exc.reason} at byte {exc.start})", path=source) from exc
    except json.JSONDecodeError as exc:
        raise StateFileError(f"not JSON ({exc.msg} at line {exc.lineno} column {exc.colno})", path=source) from exc
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise StateFileError(f"not a container state file (no \"format\": \"{FORMAT}\")", path=source)
    version = document.get("version")
    if version != VERSION:
        raise StateFileError(
            f"state file version {version!r}: this container reads version {VERSION} only "
            "(written by another release of lifecycle-container?)",
            path=source,
        )
    reader = _Reader(source)
    container = reader.string(document, "container")
    next_id = reader.integer(document, "next_unique_id", minimum=1)
    nodes = tuple(
        reader.node(entry, f"nodes[{index}]") for index, entry in enumerate(reader.array(document, "nodes"))
    )
    seen: set[int] = set()
    for record in nodes:
        if record.unique_id in seen:
            raise StateFileError(f"unique_id {record.unique_id} is recorded twice", path=source)
        if record.unique_id >= next_id:
            raise StateFileError(
                f"unique_id {record.unique_id} is not below next_unique_id {next_id}", path=source
            )
        seen.add(record.unique_id)
    written = document.get("written")
    pid = document.get("pid")
    return ContainerState(
        container,
        next_id,
        nodes,
        written=written if isinstance(written, str) else None,
        pid=pid if isinstance(pid, int) and not isinstance(pid, bool) else None,
    )


class _Reader:
    """Typed access to the decoded JSON; every mistake names its place."""

    def __init__(self, source: str) -> None:
        self._source = source

    def fail(self, where: str, problem: str) -> StateFileError:
        return StateFileError(f"{where}: {problem}", path=self._source)

    def field(self, mapping: Mapping[str, Any], key: str, where: str = "") -> Any:
        if key not in mapping:
            raise self.fail(where or key, f"missing {key!r}" if where else "missing")
        return mapping[key]

    def string(self, mapping: Mapping[str, Any], key: str, *, where: str = "", optional: bool = False) -> Any:
        value = mapping.get(key) if optional else self.field(mapping, key, where)
        if value is None and optional:
            return None
        if not isinstance(value, str):
            raise self.fail(f"{where}.{key}" if where else key, f"expected a string, not {type(value).__name__}")
        return value

    def integer(self, mapping: Mapping[str, Any], key: str, *, where: str = "", minimum: int = 0) -> int:
        value = self.field(mapping, key, where)
        if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
            raise self.fail(f"{where}.{key}" if where else key, f"expected an integer >= {minimum}, not {value!r}")
        return value

    def array(self, mapping: Mapping[str, Any], key: str, *, where: str = "") -> list[Any]:
        value = self.field(mapping, key, where) if not where else mapping.get(key, [])
        if not isinstance(value, list):
            raise self.fail(f"{where}.{key}" if where else key, f"expected a list, not {type(value).__name__}")
        return value

    def node(self, entry: Any, where: str) -> NodeRecord:
        if not isinstance(entry, dict):
            raise self.fail(where, f"expected an object, not {type(entry).__name__}")
        rules = self.array(entry, "remap_rules", where=where)
        if not all(isinstance(rule, str) for rule in rules):
            raise self.fail(f"{where}.remap_rules", "expected strings")
        state = entry.get("state")
        if state is not None and state not in LIFECYCLE_STATES:
            raise self.fail(f"{where}.state", f"expected one of {', '.join(LIFECYCLE_STATES)} or null, not {state!r}")
        return NodeRecord(
            unique_id=self.integer(entry, "unique_id", where=where, minimum=1),
            package=self.string(entry, "package", where=where),
            plugin=self.string(entry, "plugin", where=where),
            name=self.string(entry, "name", where=where, optional=True),
            namespace=self.string(entry, "namespace", where=where, optional=True),
            full_name=self.string(entry, "full_name", where=where),
            remap_rules=tuple(rules),
            parameters=self.parameters(entry, "parameters", where),
            changed_parameters=self.parameters(entry, "changed_parameters", where),
            extra_arguments=self.parameters(entry, "extra_arguments", where),
            log_level=self.integer(entry, "log_level", where=where) if "log_level" in entry else 0,
            state=state,
        )

    def parameters(self, entry: Mapping[str, Any], key: str, where: str) -> tuple[Parameter[Any], ...]:
        decoded = []
        for index, item in enumerate(self.array(entry, key, where=where)):
            place = f"{where}.{key}[{index}]"
            if not isinstance(item, dict):
                raise self.fail(place, f"expected an object, not {type(item).__name__}")
            name = self.string(item, "name", where=place)
            kind = _TYPES.get(item.get("type"))  # type: ignore[arg-type]
            if kind is None:
                raise self.fail(f"{place}.type", f"expected one of {', '.join(_TYPES)}, not {item.get('type')!r}")
            try:
                decoded.append(Parameter(name, kind, _value(kind, self.field(item, "value", place))))
            except (TypeError, ValueError) as exc:
                raise self.fail(f"{place}.value", f"does not fit the type {item['type']!r}: {exc}") from exc
        return tuple(decoded)


def _value(kind: Parameter.Type, value: Any) -> Any:
    """A JSON value as rclpy takes it for ``kind`` (a whole number is a double where one is expected)."""
    if kind == Parameter.Type.DOUBLE and _whole(value):
        return float(value)
    if kind == Parameter.Type.DOUBLE_ARRAY and isinstance(value, list):
        return [float(item) if _whole(item) else item for item in value]
    if kind == Parameter.Type.BYTE_ARRAY and isinstance(value, list):
        if not all(_whole(item) and 0 <= item <= 255 for item in value):
            raise ValueError("expected integers 0 to 255")
        return [bytes([item]) for item in value]
    return value


def _whole(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def read_state(path: Path) -> ContainerState | None:
    """The state the file at ``path`` holds; ``None`` when there is no file.

    :raises StateFileError: it cannot be read, or is not a state file this
        container reads (:func:`decode`).
    """
    try:
        with path.open("rb") as file:
            data = file.read(MAX_BYTES + 1)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise StateFileError(f"cannot be read: {exc.strerror or exc}", path=str(path)) from exc
    if len(data) > MAX_BYTES:
        raise StateFileError(f"larger than {MAX_BYTES // (1024 * 1024)} MiB: not a state file", path=str(path))
    return decode(data, source=str(path))


def write_atomically(path: Path, data: bytes) -> None:
    """Replace the file at ``path`` with ``data``, whole or not at all.

    Readable and writable by its owner only (``mkstemp``'s mode): it holds
    the nodes' parameters.

    :raises OSError: nothing was replaced (the temporary file is removed).
    """
    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(descriptor, "wb") as file:
            file.write(data)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        raise
    # The rename itself reaches the disk with the directory.
    directory = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def temporary_files(path: Path) -> list[Path]:
    """The temporary files writes to ``path`` would leave if the process died mid-write."""
    return sorted(path.parent.glob(f".{path.name}.*.tmp"))


def set_aside(path: Path, *, now: float | None = None) -> Path:
    """Rename the file at ``path`` out of the way, keeping it: ``NAME.bad-20250101T120000``.

    :return: its new path.
    :raises OSError: it could not be renamed.
    """
    stamp = time.strftime("%Y%m%dT%H%M%S", time.localtime(time.time() if now is None else now))
    target = path.with_name(f"{path.name}.bad-{stamp}")
    number = 1
    while target.exists():
        number += 1
        target = path.with_name(f"{path.name}.bad-{stamp}-{number}")
    os.rename(path, target)
    return target


def same_parameters(first: Sequence[Parameter[Any]], second: Sequence[Parameter[Any]]) -> bool:
    """Whether two lists of overrides set the same names to the same typed values (NaN equals NaN)."""
    return _comparable(first) == _comparable(second)


def _comparable(parameters: Sequence[Parameter[Any]]) -> dict[str, tuple[str, str]]:
    # By their JSON text: NaN is unequal to itself, and an array may be a list or an array.array.
    return {
        item["name"]: (item["type"], json.dumps(item["value"], allow_nan=True))
        for item in encode_parameters(parameters)
    }

