"""The package's layout holds: dependencies point one way, and the public names are pinned."""

from __future__ import annotations

import ast
import subprocess
import sys
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
        "container._text",
        "container.checks",
        "container.executor",
        "container.intra",
        "container.lifecycle",
    ),
}


def _imports(path: Path) -> set[str]:
    """The ``container...`` modules a file imports, relative imports resolved."""
    module = ".".join(path.relative_to(REPO).with_suffix("").parts)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    if path.name == "__init__.py":
        module = module.removesuffix(".__init__")
        package = module
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join([*base, node.module] if node.module else base)
            else:
                target = node.module or ""
            names = [f"{target}.{alias.name}" for alias in node.names]
            # ``from .. import checks`` imports the module, not the package's own names.
            candidates = names if node.module is None else [target]
            found.update(name for name in candidates if name.startswith("container"))
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.startswith("container"))
    return found


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
        "LifecycleManager", "LifecycleNode", "LoadError", "LoadRequest", "LoadedNode",
        "ManagerSettings", "NodeType", "PluginError", "PluginRegistry", "RegisterNodeType",
        "TransitionError", "contain_fault", "copy_message", "enable_intra_process", "hand_over",
        "hookimpl", "hookspec",
    ])  # fmt: skip
    assert container.executor.__all__ == [
        "HAS_PUBLISHER_GID", "AsyncioExecutor", "CallbackErrorHandler", "ExecutorState", "publisher_gid",
    ]  # fmt: skip
    assert container.lifecycle.__all__ == ["LifecycleManager", "LifecycleNode", "ManagerSettings", "contain_fault"]
    assert container.checks.__all__ == ["boolean", "integer", "number", "string", "strings"]
    assert container.intra.__all__ == [
        "copy_message", "enable_intra_process", "hand_over", "intra_process_enabled",
    ]  # fmt: skip


def test_importing_the_package_does_not_start_ros() -> None:
    """Errors and hook markers load without rclpy: ROS-free plugin tools rely on it."""
    probe = "import sys, container; container.ContainerError; print('rclpy' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"
