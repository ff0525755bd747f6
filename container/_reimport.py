"""A plugin distribution's modules: which they are, where their files are, importing them afresh.

What ``container reload`` needs of Python's import system. A distribution's
modules are the packages its entry points name (``acme_nodes.plugin`` →
``acme_nodes`` and everything under it; below a namespace package, the first
regular package), whether it is installed in editable mode or not: what
counts is the module objects Python holds, and their files.

Importing afresh takes the old modules out of ``sys.modules`` and imports
the entry points again, with the byte-code cache pointed at an empty
directory: Python checks a cached ``.pyc`` by the source's modification time
in whole seconds and its size, so a file saved twice within one second at
the same length would otherwise load its stale byte code. A failed import
puts the old modules back, so the old code's nodes keep running on modules
that are still the ones ``sys.modules`` names.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import os
import sys
import tempfile
import traceback
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, TypeVar

from ._errors import LoadError

if TYPE_CHECKING:
    from ._registry import NodeType

__all__ = [
    "DistributionModules",
    "Reimport",
    "Reimported",
    "distribution_modules",
    "failure_location",
    "import_afresh",
]

T = TypeVar("T")

#: This package: its own distribution's modules are never taken out.
_OWN_PACKAGE = __name__.partition(".")[0]


@dataclass(frozen=True, slots=True)
class DistributionModules:
    """The module trees of one distribution, by their roots' names."""

    distribution: str
    roots: tuple[str, ...]

    def owns(self, name: str) -> bool:
        """Whether the module ``name`` is one of the distribution's."""
        return any(name == root or name.startswith(f"{root}.") for root in self.roots)

    def loaded(self) -> dict[str, ModuleType]:
        """The distribution's modules Python holds now."""
        return {name: module for name, module in list(sys.modules.items()) if self.owns(name)}

    def sources(self) -> list[Path]:
        """What holds the distribution's code on disk: each root package's directory, or a root module's file."""
        found: list[Path] = []
        for root in self.roots:
            module = sys.modules.get(root)
            if module is not None:
                origin, package = getattr(module, "__file__", None), hasattr(module, "__path__")
            else:  # not imported (yet, or any more: its first import failed)
                try:
                    spec = importlib.util.find_spec(root)
                except (ImportError, ValueError):
                    spec = None
                origin = spec.origin if spec is not None and spec.has_location else None
                package = spec is not None and spec.submodule_search_locations is not None
            if origin:
                path = Path(origin).resolve()
                found.append(path.parent if package else path)
        return found


def distribution_modules(
    distribution: str, entry_points: Iterable[importlib.metadata.EntryPoint]
) -> DistributionModules:
    """The module trees the entry points of ``distribution`` name.

    :raises LoadError: a tree is this container's own (the demo plugin ships
        with the container: its code is the container's), or none is loaded.
    """
    roots: list[str] = []
    for entry_point in entry_points:
        root = _regular_root(entry_point.module)
        if root.partition(".")[0] == _OWN_PACKAGE:
            raise LoadError(
                f"distribution {distribution!r} is the container's own code ({entry_point.module}): "
                "it cannot be reloaded; restart the container to run new code"
            )
        if root not in roots:
            roots.append(root)
    if not roots:
        raise LoadError(f"distribution {distribution!r} has no plugin entry point to reload")
    return DistributionModules(distribution, tuple(roots))


def _regular_root(module: str) -> str:
    """The first regular module along ``module``'s dotted path: namespace packages are shared."""
    parts = module.split(".")
    for end in range(1, len(parts) + 1):
        name = ".".join(parts[:end])
        if getattr(sys.modules.get(name), "__file__", None):
            return name
    return module


@dataclass(slots=True)
class Reimport:
    """What :func:`import_afresh` replaced, to put back with :meth:`undo`."""

    modules: DistributionModules
    old: dict[str, ModuleType]

    def undo(self) -> None:
        """Put the old modules back in place of whatever the new import left."""
        _put_back(self.modules, self.old)


@dataclass(eq=False, slots=True)
class Reimported:
    """A distribution whose code :meth:`PluginRegistry.reimport` imported afresh.

    The registry hands out the new code's types from then on; :meth:`undo`
    puts the old code (modules, hook implementations, types) back.
    """

    distribution: str
    #: The new code's node types, by full name.
    types: Mapping[str, NodeType]
    _undo: Callable[[], None]

    def undo(self) -> None:
        self._undo()


def import_afresh(modules: DistributionModules, load: Callable[[], T]) -> tuple[T, Reimport]:
    """Run ``load`` (the entry points' imports) with ``modules`` taken out of ``sys.modules``.

    :return: what ``load`` returned, and how to undo the import.
    :raises BaseException: whatever ``load`` raised; the old modules are back.
    """
    old = modules.loaded()
    for name in old:
        del sys.modules[name]
    importlib.invalidate_caches()
    previous = sys.pycache_prefix
    try:
        with tempfile.TemporaryDirectory(prefix="container-reload-") as cache:
            sys.pycache_prefix = cache
            try:
                result = load()
            finally:
                sys.pycache_prefix = previous
    except BaseException:
        _put_back(modules, old)
        raise
    return result, Reimport(modules, old)


def _put_back(modules: DistributionModules, old: dict[str, ModuleType]) -> None:
    for name in [name for name in sys.modules if modules.owns(name)]:
        del sys.modules[name]
    sys.modules.update(old)
    # A root below a namespace package is its parent's attribute too.
    for root in modules.roots:
        parent, _, child = root.rpartition(".")
        if parent and root in old and parent in sys.modules:
            setattr(sys.modules[parent], child, old[root])


def failure_location(error: BaseException, modules: DistributionModules) -> str:
    """Where the new code failed, as ``file:line``: a syntax error's own place, else the
    innermost frame in the distribution's files; ``""`` if no frame is (a transition that
    returned FAILURE: the node's log says why)."""
    if isinstance(error, SyntaxError) and error.filename:
        return f"{error.filename}:{error.lineno}" if error.lineno else error.filename
    sources = [os.path.join(str(path), "") if path.is_dir() else str(path) for path in modules.sources()]
    own = [
        frame
        for frame in traceback.extract_tb(error.__traceback__)
        if any(frame.filename.startswith(source) for source in sources)
    ]
    return f"{own[-1].filename}:{own[-1].lineno}" if own else ""
