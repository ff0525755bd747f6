"""Hook specifications a plugin distribution implements.

A plugin is a module (or object) named by an entry point of group
``container.plugins``. It marks its hook implementations with
:data:`hookimpl`::

    from container import hookimpl

    @hookimpl
    def register_node_types(register):
        register(Talker)
        register(FastListener, name="Listener")

Each registered class becomes the node type ``<package>::<Type>``, where
``<package>`` is the plugin's distribution name written as a ROS package name,
the way rclcpp components are named ``composition::Talker``.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING, Protocol

import pluggy

if TYPE_CHECKING:
    from rclpy.node import Node

__all__ = ["PROJECT_NAME", "RegisterNodeType", "hookimpl", "hookspec", "ros_package_name"]

#: The pluggy project name; markers of any other project are not ours.
PROJECT_NAME = "container"

hookspec = pluggy.HookspecMarker(PROJECT_NAME)


def ros_package_name(distribution: str) -> str:
    """Return the ROS package name that node types of ``distribution`` live in.

    Runs of ``-``, ``_`` and ``.`` collapse like in PEP 503, so two
    distributions that importlib.metadata tells apart never share a package.
    (Here, ROS-free, for the build backend as much as for the registry.)
    """
    return re.sub(r"[-_.]+", "_", distribution).lower()
hookimpl = pluggy.HookimplMarker(PROJECT_NAME)


class RegisterNodeType(Protocol):
    """The callback ``register_node_types`` receives.

    :param node_class: a subclass of :class:`rclpy.node.Node`, usually of
        :class:`rclpy.lifecycle.LifecycleNode`.
    :param name: the type name after ``::``; defaults to the class's
        ``__name__``. Must be a Python identifier.
    :raises PluginError: if the registration is invalid; the whole plugin is
        then skipped, even if the error is caught.
    """

    def __call__(self, node_class: type[Node], /, *, name: str | None = None) -> None: ...


@hookspec
def register_node_types(register: RegisterNodeType) -> None:
    """Register this plugin's lifecycle node classes by calling ``register``."""
