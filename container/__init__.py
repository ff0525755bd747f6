"""A component container for ROS 2 lifecycle nodes, on one asyncio executor."""

from ._errors import (
    ConfigError,
    ContainerError,
    DeviceError,
    ExecutorError,
    LoadError,
    PluginError,
    TransitionError,
)
from ._executor import AsyncioExecutor, CallbackErrorHandler

__all__ = [
    "AsyncioExecutor",
    "CallbackErrorHandler",
    "ConfigError",
    "ContainerError",
    "DeviceError",
    "ExecutorError",
    "LoadError",
    "PluginError",
    "TransitionError",
]
