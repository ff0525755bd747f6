"""The public API is exactly ``container.__all__``, and every name in it is real."""

from __future__ import annotations

import importlib
import inspect

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


def test_public_names_are_listed_once() -> None:
    assert len(container.__all__) == len(set(container.__all__))


def test_plugin_author_surface() -> None:
    """What the plugin-writing guide (docs/guide/plugins.md) imports."""
    from container import LifecycleNode, RegisterNodeType, hookimpl

    assert callable(hookimpl)
    assert issubclass(LifecycleNode, importlib.import_module("rclpy.lifecycle").LifecycleNode)
    assert RegisterNodeType.__doc__


def test_errors_share_one_root() -> None:
    for name in ("ConfigError", "DeviceError", "ExecutorError", "LoadError", "PluginError", "TransitionError"):
        assert issubclass(getattr(container, name), container.ContainerError)
