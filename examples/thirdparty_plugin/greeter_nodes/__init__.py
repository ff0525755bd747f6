"""An example plugin: registers ``greeter_nodes::Greeter`` with the container.

The package name before ``::`` comes from the distribution's name
(``greeter-nodes`` in pyproject.toml), the type name from the class.
"""

from __future__ import annotations

from typing import Any

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle.publisher import LifecyclePublisher
from rclpy.timer import Timer
from std_msgs.msg import String

from container import hookimpl

__all__ = ["Greeter", "register_node_types"]


class Greeter(LifecycleNode):
    """Publish ``Hello, <name>!`` on ``greeting`` once a second while active."""

    #: The node name the container uses when a load request names none.
    default_node_name = "greeter"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        # The container passes namespace, context, parameter overrides and
        # ROS arguments as keyword arguments: hand them all to the base class.
        super().__init__(node_name, **kwargs)
        self.declare_parameter("name", "world")
        self._publisher: LifecyclePublisher[Any] | None = None
        self._timer: Timer | None = None

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._publisher = self.create_lifecycle_publisher(String, "greeting", 10)
        self._timer = self.create_timer(1.0, self._greet)
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        # Whatever configure created, cleanup and shutdown destroy: an unload
        # must leave nothing of the node behind.
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        if self._publisher is not None:
            self.destroy_lifecycle_publisher(self._publisher)
            self._publisher = None

    def _greet(self) -> None:
        # The timer runs from configure on; greet only while active.
        if self._publisher is not None and self._publisher.is_activated:
            self._publisher.publish(String(data=f"Hello, {self.get_parameter('name').value}!"))


@hookimpl
def register_node_types(register: Any) -> None:
    """Register the Greeter node type."""
    register(Greeter)
