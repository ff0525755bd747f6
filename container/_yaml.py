"""Reading the YAML files users hand the container, safely.

``yaml.safe_load`` builds no objects, but it still accepts what breaks a
process later: a file of gigabytes, bytes that are not UTF-8, a key given
twice (the second silently wins), an alias that refers to itself (a
structure that never ends), and a few hundred bytes of nested aliases that
expand to billions of values ("billion laughs": 906 bytes grew to 1.65 GB
here). Each of these is a :class:`~container.ConfigError` with its place.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from ._errors import ConfigError

__all__ = ["MAX_FILE_BYTES", "MAX_VALUES", "load_yaml", "read_yaml"]

#: Largest file read; container and parameter files are a few kilobytes.
MAX_FILE_BYTES = 1 << 20
#: Most values a document may hold once its aliases are expanded.
MAX_VALUES = 100_000


class _Loader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys."""

    def construct_mapping(self, node: MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if isinstance(key_node, ScalarNode):
                key = self.construct_object(key_node, deep=deep)
                if key in seen:
                    mark = key_node.start_mark
                    raise ConfigError(
                        f"key {key!r} appears twice (line {mark.line + 1}, column {mark.column + 1})",
                        source=str(self.name),
                    )
                seen.add(key)
        return super().construct_mapping(node, deep=deep)


def _check_size(root: Node, source: str) -> None:
    """Refuse recursive aliases and documents that expand beyond :data:`MAX_VALUES`."""
    count = 0
    # (node, ids of the collections on the path to it); aliases share nodes,
    # so walking with repetition counts what the expansion will hold.
    stack: list[tuple[Node, frozenset[int]]] = [(root, frozenset())]
    while stack:
        node, path = stack.pop()
        count += 1
        if count > MAX_VALUES:
            raise ConfigError(
                f"expands to more than {MAX_VALUES:,} values (nested YAML aliases?)", source=source
            )
        if isinstance(node, SequenceNode | MappingNode):
            if id(node) in path:
                mark = node.start_mark
                raise ConfigError(
                    f"an alias refers to itself (line {mark.line + 1}): the structure would never end",
                    source=source,
                )
            inner = path | {id(node)}
            children: list[Node] = (
                list(node.value)
                if isinstance(node, SequenceNode)
                else [part for pair in node.value for part in pair]
            )
            stack.extend((child, inner) for child in children)


def load_yaml(text: str, *, source: str) -> Any:
    """Parse one YAML document from ``text``; ``None`` when it is empty."""
    loader = _Loader(text)
    loader.name = source
    try:
        root = loader.get_single_node()
        if root is None:
            return None
        _check_size(root, source)
        return loader.construct_document(root)
    except yaml.YAMLError as exc:
        raise ConfigError(f"not valid YAML: {exc}", source=source) from exc
    finally:
        loader.dispose()


def read_yaml(path: str | Path) -> Any:
    """Read and parse a YAML file (see the module's docstring for what is refused)."""
    source = str(path)
    try:
        with Path(path).open("rb") as stream:
            data = stream.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"cannot read: {exc.strerror}", source=source) from exc
    if len(data) > MAX_FILE_BYTES:
        raise ConfigError(f"larger than {MAX_FILE_BYTES // 1024} KiB; is this the right file?", source=source)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"not UTF-8 text (byte {exc.start}: {exc.reason})", source=source) from exc
    return load_yaml(text, source=source)
