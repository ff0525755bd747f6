"""A component container for ROS 2 lifecycle nodes, on one asyncio executor.

The public API is what this module exports, plus the public subpackages
:mod:`container.executor`, :mod:`container.lifecycle`, the value checks
:mod:`container.checks`, the device policy :mod:`container.devices`, the
pytest plugin :mod:`container.testing`, the plugins' build backend
:mod:`container.build_backend` and their colcon commands
:mod:`container.colcon`; everything in an underscored module is
private and may change. Plugin authors need :data:`hookimpl`, :class:`LifecycleNode` and
:class:`RegisterNodeType`; embedders need :class:`AsyncioExecutor`,
:class:`ComponentManager` and :class:`LifecycleManager`.

Every name loads on first use (:pep:`562`), so importing the package costs
nothing: the ``container`` command's entry point (:mod:`container.__main__`)
takes SIGINT and SIGTERM before anything else is imported. The errors, the
hook markers and the other ROS-free names never import rclpy, so a plugin's
ROS-free parts (a decoder, a command line tool) can use the error hierarchy
without starting ROS. :func:`clip` is how a value from outside (a peer's
request, a parameter) is echoed in a log line or an answer.
"""

from __future__ import annotations

import importlib

# typing.TYPE_CHECKING without importing typing (a few milliseconds of the
# command's start): type checkers take the name's meaning.
TYPE_CHECKING = False
if TYPE_CHECKING:
    from typing import Any

    from ._container import ComponentManager, LoadedNode, LoadRequest
    from ._errors import (
        ConfigError,
        ContainerError,
        DeviceError,
        ExecutorError,
        LoadError,
        PluginError,
        SecurityError,
        TransitionError,
    )
    from ._hookspecs import RegisterNodeType, hookimpl, hookspec
    from ._registry import ENTRY_POINT_GROUP, NodeType, PluginRegistry
    from ._services import ContainerServices
    from ._text import clip
    from ._throttle import Throttle
    from ._warnings import LoadWarning
    from .executor import AsyncioExecutor, CallbackErrorHandler
    from .intra import copy_message, enable_intra_process, hand_over
    from .lifecycle import LifecycleManager, LifecycleNode, ManagerSettings, contain_fault

__all__ = [
    "ENTRY_POINT_GROUP",
    "AsyncioExecutor",
    "CallbackErrorHandler",
    "ComponentManager",
    "ConfigError",
    "ContainerError",
    "ContainerServices",
    "DeviceError",
    "ExecutorError",
    "LifecycleManager",
    "LifecycleNode",
    "LoadError",
    "LoadRequest",
    "LoadWarning",
    "LoadedNode",
    "ManagerSettings",
    "NodeType",
    "PluginError",
    "PluginRegistry",
    "RegisterNodeType",
    "SecurityError",
    "Throttle",
    "TransitionError",
    "clip",
    "contain_fault",
    "copy_message",
    "enable_intra_process",
    "hand_over",
    "hookimpl",
    "hookspec",
]

#: Where each name lives.
_LAZY = {
    "ConfigError": "._errors",
    "ContainerError": "._errors",
    "DeviceError": "._errors",
    "ExecutorError": "._errors",
    "LoadError": "._errors",
    "PluginError": "._errors",
    "SecurityError": "._errors",
    "TransitionError": "._errors",
    "RegisterNodeType": "._hookspecs",
    "hookimpl": "._hookspecs",
    "hookspec": "._hookspecs",
    "clip": "._text",
    "Throttle": "._throttle",
    "LoadWarning": "._warnings",
    "ComponentManager": "._container",
    "LoadRequest": "._container",
    "LoadedNode": "._container",
    "ENTRY_POINT_GROUP": "._registry",
    "NodeType": "._registry",
    "PluginRegistry": "._registry",
    "ContainerServices": "._services",
    "AsyncioExecutor": ".executor",
    "CallbackErrorHandler": ".executor",
    "LifecycleManager": ".lifecycle",
    "LifecycleNode": ".lifecycle",
    "ManagerSettings": ".lifecycle",
    "contain_fault": ".lifecycle",
    "copy_message": ".intra",
    "enable_intra_process": ".intra",
    "hand_over": ".intra",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'container' has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
