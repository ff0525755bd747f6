"""An example plugin built by colcon: ``radar_nodes::Radar``.

Its message (``radar_interfaces/msg/Echo``) comes from ``radar_interfaces``,
an ordinary interface package beside it in the workspace. Without messages
of its own, a plugin is this package alone.
"""

from __future__ import annotations

from typing import Any

from radar_interfaces.msg import Echo
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle.publisher import LifecyclePublisher
from rclpy.timer import Timer

from container import LifecycleNode, RegisterNodeType, hookimpl

__all__ = ["Radar", "register_node_types"]


class Radar(LifecycleNode):
    """Publish a numbered ``Echo`` of ``range`` metres on ``echo`` at ``rate`` Hz while active."""

    default_node_name = "radar"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("rate", 10.0)
        self.declare_parameter("range", 1.5)
        self._publisher: LifecyclePublisher[Any] | None = None
        self._timer: Timer | None = None
        self._seq = 0

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        rate = float(self.get_parameter("rate").value)
        if not rate > 0:
            self.get_logger().error(f"rate must be positive, not {rate}")
            return TransitionCallbackReturn.FAILURE
        self._publisher = self.create_lifecycle_publisher(Echo, "echo", 10)
        self._timer = self.create_timer(1.0 / rate, self._send)
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        if self._publisher is not None:
            self.destroy_lifecycle_publisher(self._publisher)
            self._publisher = None

    def _send(self) -> None:
        if self._publisher is not None and self._publisher.is_activated:
            self._seq += 1
            self._publisher.publish(Echo(seq=self._seq, range=float(self.get_parameter("range").value)))


@hookimpl
def register_node_types(register: RegisterNodeType) -> None:
    """Register the Radar node type."""
    register(Radar)
