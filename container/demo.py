"""Demo lifecycle nodes, shipped as the ``lifecycle_container`` plugin.

They are registered through this distribution's own entry point, exactly
like a third-party plugin's, and give ``container run`` something to host:
``lifecycle_container::Talker`` publishes ``std_msgs/String`` on ``chatter``
while active; ``lifecycle_container::Listener`` logs what it hears;
``lifecycle_container::Counter`` is the seed tutorial's counter action
server (``count_to``, ``lifecycle_container_interfaces/action/CountTo``)
with an ``async def`` execute callback that ``await asyncio.sleep()``s.

Both are built on the project's :class:`~container.LifecycleNode`: the
talker's publisher and timer follow its state without any ``on_activate``.
"""

from __future__ import annotations

import asyncio
from typing import Any

from lifecycle_container_interfaces.action import CountTo
from rclpy.action.server import ActionServer, CancelResponse, GoalResponse, ServerGoalHandle
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.timer import Timer
from std_msgs.msg import String

from ._hookspecs import RegisterNodeType, hookimpl
from .lifecycle import LifecycleNode

__all__ = ["Counter", "Listener", "Talker", "register_node_types"]


class _Releasing(LifecycleNode):
    """A demo node whose configure creates what cleanup, shutdown and error processing release."""

    def _release(self) -> None:
        raise NotImplementedError

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS


class Talker(_Releasing):
    """Publish ``Hello World: N`` on ``chatter`` at ``rate`` Hz while active."""

    default_node_name = "talker"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("rate", 2.0)
        self.declare_parameter("message", "Hello World")
        self._publisher: Publisher[Any] | None = None
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


class Counter(_Releasing):
    """Count to a goal's ``target`` on the ``count_to`` action, one step per ``step`` seconds.

    The seed tutorial's server as a lifecycle node: the action server exists
    from configure to cleanup and takes goals only while active; feedback
    every step; a cancel is accepted and honoured at the next step; goals
    running when the node deactivates are aborted there. The execute
    callback is ``async def`` and sleeps with asyncio, which rclpy's own
    executors cannot run ("no running event loop").
    """

    default_node_name = "counter"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("step", 1.0)
        self._server: ActionServer[Any, Any, Any] | None = None
        self._step = 1.0

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        step = float(self.get_parameter("step").value)
        if not step >= 0:
            self.get_logger().error(f"step must be zero or more seconds, not {step}")
            return TransitionCallbackReturn.FAILURE
        self._step = step
        self._server = ActionServer(
            self,
            CountTo,
            "count_to",
            self._execute,
            goal_callback=self._on_goal,
            cancel_callback=lambda _: CancelResponse.ACCEPT,
        )
        return TransitionCallbackReturn.SUCCESS

    def destroy_node(self) -> None:
        # rclpy's destroy_node() leaves an action server's rcl handles alive
        # (and answering on the graph) until collected.
        self._release()
        super().destroy_node()

    def _release(self) -> None:
        if self._server is not None:
            self._server.destroy()
            self._server = None

    def _active(self) -> bool:
        return self.lifecycle_state.label == "active"

    def _on_goal(self, goal: Any) -> GoalResponse:
        if not self._active():
            self.get_logger().warning(f"goal to count to {goal.target} rejected: not active")
            return GoalResponse.REJECT
        if goal.target < 0:
            self.get_logger().warning(f"goal to count to {goal.target} rejected: the target must be 0 or more")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    async def _execute(self, goal_handle: ServerGoalHandle[Any, Any, Any]) -> Any:
        target = goal_handle.request.target
        feedback = CountTo.Feedback()
        for i in range(target):
            feedback.current_count = i
            goal_handle.publish_feedback(feedback)
            await asyncio.sleep(self._step)
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
                return CountTo.Result(final_count=i)
            if not self._active():
                goal_handle.abort()
                return CountTo.Result(final_count=i)
        goal_handle.succeed()
        return CountTo.Result(final_count=target)


@hookimpl
def register_node_types(register: RegisterNodeType) -> None:
    """Register the demo talker, listener and counter."""
    register(Talker)
    register(Listener)
    register(Counter)
