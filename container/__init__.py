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

The errors and the hook markers load with the package; everything that needs
rclpy loads on first use, so a plugin's ROS-free parts (a decoder, a command
line tool) can use the error hierarchy without starting ROS. :func:`clip`
is how a value from outside (a peer's request, a parameter) is echoed in a
log line or an answer.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

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
from ._text import clip
from ._throttle import Throttle
from ._warnings import LoadWarning

if TYPE_CHECKING:
    from ._container import ComponentManager, LoadedNode, LoadRequest
    from ._registry import ENTRY_POINT_GROUP, NodeType, PluginRegistry
    from ._services import ContainerServices
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

#: Where each name that needs rclpy lives.
_LAZY = {
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
