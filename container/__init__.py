"""A component container for ROS 2 lifecycle nodes, on one asyncio executor.

The public API is what this module exports; everything in an underscored
module is private and may change. Plugin authors need :data:`hookimpl`,
:class:`LifecycleNode` and :class:`RegisterNodeType`; embedders need
:class:`AsyncioExecutor`, :class:`ComponentManager` and :class:`LifecycleManager`.
"""

from ._container import ComponentManager, LoadedNode, LoadRequest
from ._errors import (
    ConfigError,
    ContainerError,
    DeviceError,
    ExecutorError,
    LoadError,
    PluginError,
    TransitionError,
)
from .executor import AsyncioExecutor, CallbackErrorHandler
from ._hookspecs import RegisterNodeType, hookimpl, hookspec
from .lifecycle import LifecycleManager, LifecycleNode, ManagerSettings, contain_fault
from ._registry import ENTRY_POINT_GROUP, NodeType, PluginRegistry
from ._services import ContainerServices

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
    "LoadedNode",
    "ManagerSettings",
    "NodeType",
    "PluginError",
    "PluginRegistry",
    "RegisterNodeType",
    "TransitionError",
    "contain_fault",
    "hookimpl",
    "hookspec",
]
