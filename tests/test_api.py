"""The public API is exactly ``container.__all__``, and every name in it is real."""

from __future__ import annotations

import importlib
import inspect

import pytest

import container


def test_every_exported_name_exists_and_is_documented() -> None:
    missing = [name for name in container.__all__ if not hasattr(container, name)]
    assert missing == []
    undocumented = [
        name
        for name in container.__all__
        if (inspect.isclass(getattr(container, name)) or inspect.isfunction(getattr(container, name)))
        and not inspect.getdoc(getattr(container, name))
    ]
    assert undocumented == []


@pytest.mark.parametrize("name", ["container.checks", "container.executor", "container.intra", "container.lifecycle"])
def test_every_name_a_subpackage_exports_exists_and_is_documented(name: str) -> None:
    """What other packages import from a subpackage is in its ``__all__`` (tests/test_layout.py): real, documented."""
    module = importlib.import_module(name)
    exported: list[str] = module.__all__
    assert len(exported) == len(set(exported))
    missing = [export for export in exported if not hasattr(module, export)]
    assert missing == []
    undocumented = [
        export
        for export in exported
        if (inspect.isclass(getattr(module, export)) or inspect.isfunction(getattr(module, export)))
        and not inspect.getdoc(getattr(module, export))
    ]
    assert undocumented == []


def test_public_names_are_listed_once() -> None:
    assert len(container.__all__) == len(set(container.__all__))


def test_plugin_author_surface() -> None:
    """What the plugin-writing guide (docs/guide/plugins.md) imports."""
    from container import LifecycleNode, RegisterNodeType, hookimpl

    assert callable(hookimpl)
    assert issubclass(LifecycleNode, importlib.import_module("rclpy.lifecycle").LifecycleNode)
    assert RegisterNodeType.__doc__


def test_errors_share_one_root() -> None:
    for name in (
        "ConfigError", "DeviceError", "ExecutorError", "LoadError", "PluginError", "SecurityError", "TransitionError"
    ):
        assert issubclass(getattr(container, name), container.ContainerError)
