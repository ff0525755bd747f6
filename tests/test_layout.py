"""The package's layout holds: dependencies point one way, and the public names are pinned."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

import container
import container.checks
import container.executor
import container.intra
import container.lifecycle
from tests.container_support import REPO

PACKAGE = REPO / "container"

#: Where each part may import from inside ``container``; anything else is upward.
ALLOWED = {
    "container.executor": ("container._compat", "container._errors", "container.executor"),
    "container.intra": ("container._compat", "container._errors", "container.executor", "container.intra"),
    "container.lifecycle": (
        "container._compat",
        "container._errors",
        "container._logger",
        "container._qos",
        "container._text",
        "container.checks",
        "container.executor",
        "container.intra",
        "container.lifecycle",
    ),
}


@dataclass(frozen=True)
class _Import:
    """One imported module, as the importing file names it (relative imports resolved)."""

    #: The module imported: ``a.b`` for ``from a.b import name``, ``a.b.c`` when ``c`` is a module of ``a.b``.
    module: str
    #: The names taken from it (``from module import ...``); empty for a module itself.
    names: tuple[str, ...]
    line: int
    #: Run when the importing module is imported: not inside a function, not ``if TYPE_CHECKING:``.
    at_import: bool
    #: Inside a function: run when the function is.
    in_function: bool


def _module_name(path: Path, root: Path) -> str:
    """The dotted name of the module at ``path``, a file under the import root ``root``."""
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(name: str, *roots: Path) -> bool:
    for root in roots:
        path = root.joinpath(*name.split("."))
        # A compiled module is known by its stub.
        if any(path.with_suffix(suffix).is_file() for suffix in (".py", ".pyi")) or (path / "__init__.py").is_file():
            return True
    return False


def _root_of(path: Path) -> Path:
    """The import root of the file at ``path``: the first directory up that is not a package."""
    root = path.parent
    while (root / "__init__.py").is_file():
        root = root.parent
    return root


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _statements(body: list[ast.stmt], *, at_import: bool, in_function: bool) -> Iterator[tuple[ast.stmt, bool, bool]]:
    """Every statement in ``body``, nested ones too, with when it runs."""
    for statement in body:
        yield statement, at_import, in_function
        if isinstance(statement, ast.FunctionDef | ast.AsyncFunctionDef):
            yield from _statements(statement.body, at_import=False, in_function=True)
        elif isinstance(statement, ast.If) and _is_type_checking(statement.test):
            yield from _statements(statement.body, at_import=False, in_function=in_function)
            yield from _statements(statement.orelse, at_import=at_import, in_function=in_function)
        else:
            for field in ("body", "orelse", "finalbody", "handlers", "cases"):
                for child in getattr(statement, field, ()):
                    nested = child.body if isinstance(child, ast.ExceptHandler | ast.match_case) else [child]
                    yield from _statements(nested, at_import=at_import, in_function=in_function)


def _imports_of(path: Path) -> Iterator[_Import]:
    """What the file at ``path`` imports."""
    root = _root_of(path)
    module = _module_name(path, root)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node, at_import, in_function in _statements(tree.body, at_import=True, in_function=False):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield _Import(alias.name, (), node.lineno, at_import, in_function)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join([*base, node.module] if node.module else base)
            else:
                target = node.module or ""
            names: list[str] = []
            for alias in node.names:
                # ``from .. import checks`` imports the module ``checks``, not a name of ``..``.
                submodule = f"{target}.{alias.name}"
                if _is_module(submodule, root, REPO):
                    yield _Import(submodule, (), node.lineno, at_import, in_function)
                else:
                    names.append(alias.name)
            if names:
                yield _Import(target, tuple(names), node.lineno, at_import, in_function)


def _imports(path: Path) -> set[str]:
    """The ``container...`` modules a file imports, relative imports resolved."""
    return {found.module for found in _imports_of(path) if found.module.startswith("container")}


@pytest.mark.parametrize("part", sorted(ALLOWED))
def test_lower_layers_never_import_upward(part: str) -> None:
    directory = PACKAGE / part.split(".")[1]
    upward = {
        f"{path.relative_to(REPO)} imports {name}"
        for path in directory.rglob("*.py")
        for name in _imports(path)
        if not name.startswith(ALLOWED[part])
    }
    assert upward == set()


def test_only_the_cli_imports_the_cli() -> None:
    offenders = [
        str(path.relative_to(REPO))
        for path in PACKAGE.rglob("*.py")
        if "cli" not in path.relative_to(PACKAGE).parts[:1]
        and path.name != "__main__.py"
        and any(name.startswith("container.cli") for name in _imports(path))
    ]
    assert offenders == []


def test_public_names_are_exactly_these() -> None:
    assert sorted(container.__all__) == sorted([
        "ENTRY_POINT_GROUP", "AsyncioExecutor", "CallbackErrorHandler", "ComponentManager",
        "ConfigError", "ContainerError", "ContainerServices", "DeviceError", "ExecutorError",
        "LifecycleManager", "LifecycleNode", "LoadError", "LoadRequest", "LoadWarning", "LoadedNode",
        "ManagerSettings", "NodeType", "PluginError", "PluginRegistry", "RegisterNodeType", "SecurityError",
        "Throttle", "TransitionError", "clip", "contain_fault", "copy_message", "enable_intra_process", "hand_over",
        "hookimpl", "hookspec",
    ])  # fmt: skip
    assert container.executor.__all__ == [
        "HAS_PUBLISHER_GID", "Accounting", "AsyncioExecutor", "CallbackErrorHandler", "CallbackLoad", "ContainerLoad",
        "Deadline", "Escaped", "ExecutorState", "GroupLoad", "NodeLoad", "UnattributedLoad", "call_soon", "contained",
        "describe",
        "end_resender", "end_spare_threads", "format_plugin_frames", "in_thread", "publisher_gid", "result",
        "run_coroutine", "working_for",
    ]  # fmt: skip
    assert container.lifecycle.__all__ == [
        "LifecycleClient", "LifecycleManager", "LifecycleNode", "ManagerSettings", "bring_down", "bring_up",
        "contain_fault", "is_lifecycle", "state_of", "transition",
    ]  # fmt: skip
    assert container.checks.__all__ == ["boolean", "integer", "number", "string", "strings", "unread_parameters"]
    assert container.intra.__all__ == [
        "IntraProcessNode", "copy_message", "enable_intra_process", "hand_over", "intra_process_class",
        "intra_process_enabled",
    ]  # fmt: skip


def test_importing_the_package_does_not_start_ros() -> None:
    """Errors and hook markers load without rclpy: ROS-free plugin tools rely on it."""
    probe = "import sys, container; container.ContainerError; print('rclpy' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"


def test_a_container_that_never_reloads_does_not_import_the_reload_machinery() -> None:
    """Reloading is on demand: ``container run`` starts without importing it (11 ms measured) or watchfiles."""
    probe = (
        "import sys, container._app; "
        "print(sorted(m for m in ('container._reload', 'container._reimport', 'container._watch', 'watchfiles') "
        "if m in sys.modules))"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]"


#: The container's subpackages: other parts use them by the names their ``__init__`` exports.
SUBPACKAGES = sorted(path.parent.name for path in PACKAGE.glob("*/__init__.py"))

#: The plugin's package and the examples: code written as users write it.
LDLIDAR = REPO / "plugins" / "ldlidar" / "ldlidar"
EXAMPLES = REPO / "examples"


def _sources(directory: Path) -> list[Path]:
    """The Python files of ``directory``, without build output."""
    return sorted(
        path
        for path in directory.rglob("*.py")
        if not any(part == "build" or part.endswith(".egg-info") for part in path.relative_to(directory).parts)
    )


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _exported(module: str) -> set[str]:
    exported: list[str] = importlib.import_module(module).__all__
    return set(exported)


def test_subpackages_import_each_other_by_exported_names() -> None:
    """A subpackage's private modules are its own: everyone else imports what its ``__init__`` exports."""
    offenders: set[str] = set()
    for path in _sources(PACKAGE):
        importer = _module_name(path, REPO).split(".")
        for found in _imports_of(path):
            parts = found.module.split(".")
            if parts[0] != "container" or len(parts) < 2 or parts[1] not in SUBPACKAGES or importer[:2] == parts[:2]:
                continue
            where = f"{path.relative_to(REPO)}:{found.line}"
            if any(_is_private(part) for part in parts[2:]):
                offenders.add(f"{where} imports {found.module}")
            elif found.names and len(parts) == 2:
                hidden = sorted(set(found.names) - _exported(found.module))
                if hidden:
                    offenders.add(f"{where} imports {', '.join(hidden)} from {found.module}, which does not export it")
    assert sorted(offenders) == []


@pytest.mark.parametrize("directory", [LDLIDAR, EXAMPLES], ids=["ldlidar", "examples"])
def test_plugins_and_examples_import_only_public_names_of_the_container(directory: Path) -> None:
    offenders: set[str] = set()
    for path in _sources(directory):
        for found in _imports_of(path):
            parts = found.module.split(".")
            if parts[0] != "container":
                continue
            where = f"{path.relative_to(REPO)}:{found.line}"
            if any(_is_private(part) for part in parts[1:]):
                offenders.add(f"{where} imports {found.module}")
            elif found.names:
                hidden = sorted(set(found.names) - _exported(found.module))
                if hidden:
                    offenders.add(f"{where} imports {', '.join(hidden)} from {found.module}, which does not export it")
    assert sorted(offenders) == []


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of ``graph``: its strongly connected parts of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for target in sorted(graph[module]):
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            part: list[str] = []
            while not part or part[-1] != module:
                part.append(stack.pop())
            if len(part) > 1:
                cycles.append(sorted(part))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return cycles


@pytest.mark.parametrize(
    ("directory", "in_functions"),
    # The plugin's function-level imports count too: they only hide a circle
    # until the function first runs.
    [(PACKAGE, False), (LDLIDAR, True)],
    ids=["container", "ldlidar"],
)
def test_no_import_circles(directory: Path, in_functions: bool) -> None:
    files = _sources(directory)
    modules = {_module_name(path, _root_of(path)) for path in files}
    graph = {
        _module_name(path, _root_of(path)): {
            found.module
            for found in _imports_of(path)
            if found.module in modules and (found.at_import or (in_functions and found.in_function))
        }
        for path in files
    }
    for module, targets in graph.items():
        targets.discard(module)
    assert _cycles(graph) == []
