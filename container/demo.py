"""Demo lifecycle nodes, shipped as the ``lifecycle_container`` plugin.

They are registered through this distribution's own entry point, exactly
like a third-party plugin's, and give ``container run`` something to host:
``lifecycle_container::Talker`` publishes ``std_msgs/String`` on ``chatter``
while active; ``lifecycle_container::Listener`` logs what it hears.

Both are built on the project's :class:`~container.LifecycleNode`: the
talker's publisher and timer follow its state without any ``on_activate``.
"""

from __future__ import annotations

from typing import Any

from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.timer import Timer
from std_msgs.msg import String

from ._hookspecs import RegisterNodeType, hookimpl
from .lifecycle import LifecycleNode

__all__ = ["Listener", "Talker", "register_node_types"]


class Talker(LifecycleNode):
    """Publish ``Hello World: N`` on ``chatter`` at ``rate`` Hz while active."""

    default_node_name = "talker"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("rate", 2.0)
        self.declare_parameter("message", "Hello World")
        self._publisher: Publisher | None = None
        self._timer: Timer | None = None
        self._count = 0

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        rate = float(self.get_parameter("rate").value)
        if rate <= 0:
            self.get_logger().error(f"rate must be positive, not {rate}")
            return TransitionCallbackReturn.FAILURE
        self._publisher = self.create_publisher(String, "chatter", 10)
        self._timer = self.create_timer(1.0 / rate, self._publish)
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        if self._publisher is not None:
            self.destroy_publisher(self._publisher)
            self._publisher = None

    def _publish(self) -> None:
        if self._publisher is None:
            return
        self._count += 1
        text = f"{self.get_parameter('message').value}: {self._count}"
        self._publisher.publish(String(data=text))


class Listener(LifecycleNode):
    """Log what arrives on ``chatter`` while active."""

    default_node_name = "listener"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.heard = 0
        self.create_subscription(String, "chatter", self._hear, 10)

    def _hear(self, message: String) -> None:
        if self.lifecycle_state.label == "active":
            self.heard += 1
            self.get_logger().info(f"I heard: [{message.data}]")


@hookimpl
def register_node_types(register: RegisterNodeType) -> None:
    """Register the demo talker and listener."""
    register(Talker)
    register(Listener)
