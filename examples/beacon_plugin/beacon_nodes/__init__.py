"""An example plugin with interfaces of its own: ``beacon_nodes::Beacon``.

Its message (``beacon_interfaces/msg/Beacon``) and action
(``beacon_interfaces/action/Sweep``) are defined in ``beacon_interfaces/``,
an ordinary ament_cmake interface package that the plugin's build generates
with rosidl (see ``CMakeLists.txt``), installed and uninstalled with the
plugin by pip.
"""

from __future__ import annotations

import asyncio
from typing import Any

from beacon_interfaces.action import Sweep
from beacon_interfaces.msg import Beacon as BeaconMsg
from rclpy.action.server import ActionServer, CancelResponse, GoalResponse, ServerGoalHandle
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle.publisher import LifecyclePublisher
from rclpy.timer import Timer

from container import LifecycleNode, RegisterNodeType, hookimpl

__all__ = ["Beacon", "register_node_types"]


class Beacon(LifecycleNode):
    """Publish a numbered ``Beacon`` on ``beacon`` at ``rate`` Hz while active; serve ``sweep``.

    The ``sweep`` action steps through a goal's ``steps``, one feedback per
    step, and takes goals only while the node is active.
    """

    default_node_name = "beacon"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("name", "beacon")
        self.declare_parameter("rate", 10.0)
        self._publisher: LifecyclePublisher[Any] | None = None
        self._timer: Timer | None = None
        self._server: ActionServer[Any, Any, Any] | None = None
        self._seq = 0

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        rate = float(self.get_parameter("rate").value)
        if not rate > 0:
            self.get_logger().error(f"rate must be positive, not {rate}")
            return TransitionCallbackReturn.FAILURE
        self._publisher = self.create_lifecycle_publisher(BeaconMsg, "beacon", 10)
        self._timer = self.create_timer(1.0 / rate, self._send)
        self._server = ActionServer(
            self,
            Sweep,
            "sweep",
            self._sweep,
            goal_callback=self._on_goal,
            cancel_callback=lambda _: CancelResponse.ACCEPT,
        )
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def destroy_node(self) -> None:
        # rclpy's destroy_node() leaves an action server's handles alive until collected.
        self._release()
        super().destroy_node()

    def _release(self) -> None:
        if self._server is not None:
            self._server.destroy()
            self._server = None
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        if self._publisher is not None:
            self.destroy_lifecycle_publisher(self._publisher)
            self._publisher = None

    def _send(self) -> None:
        if self._publisher is None or not self._publisher.is_activated:
            return
        self._seq += 1
        message = BeaconMsg(name=str(self.get_parameter("name").value), seq=self._seq)
        message.stamp = self.get_clock().now().to_msg()
        self._publisher.publish(message)

    def _on_goal(self, goal: Any) -> GoalResponse:
        if self.lifecycle_state.label != "active":
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    async def _sweep(self, goal_handle: ServerGoalHandle[Any, Any, Any]) -> Any:
        request = goal_handle.request
        feedback = Sweep.Feedback()
        for step in range(1, request.steps + 1):
            await asyncio.sleep(max(float(request.step_period), 0.0))
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
                return Sweep.Result(done=step - 1)
            feedback.step = step
            goal_handle.publish_feedback(feedback)
        goal_handle.succeed()
        return Sweep.Result(done=request.steps)


@hookimpl
def register_node_types(register: RegisterNodeType) -> None:
    """Register the beacon node type."""
    register(Beacon)
