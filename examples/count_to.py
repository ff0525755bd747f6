"""Send a goal to the demo counter's ``count_to`` action and print its feedback.

    .venv/bin/python examples/count_to.py 5 [--cancel-after SECONDS] [--action /count_to]

An action client written the asyncio way: the goal, the cancel and the
result are rclpy futures, awaited in a coroutine that AsyncioExecutor runs.
Exit status 0 when the goal succeeded (or was cancelled as asked), 1 otherwise.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from typing import Any

import rclpy
import rclpy.utilities
from action_msgs.msg import GoalStatus
from lifecycle_container_interfaces.action import CountTo
from rclpy.action.client import ActionClient
from rclpy.node import Node

from container import AsyncioExecutor

STATUS = {
    GoalStatus.STATUS_SUCCEEDED: "succeeded",
    GoalStatus.STATUS_CANCELED: "canceled",
    GoalStatus.STATUS_ABORTED: "aborted",
}


async def count(node: Node, client: ActionClient[Any, Any, Any], target: int, cancel_after: float | None) -> bool:
    def on_feedback(message: Any) -> None:
        print(f"feedback: {message.feedback.current_count}", flush=True)

    goal = await client.send_goal_async(CountTo.Goal(target=target), feedback_callback=on_feedback)
    assert goal is not None
    if not goal.accepted:
        print("goal rejected", flush=True)
        return False
    print(f"goal accepted: counting to {target}", flush=True)
    if cancel_after is not None:
        await asyncio.sleep(cancel_after)
        await goal.cancel_goal_async()
        print("cancel requested", flush=True)
    outcome = await goal.get_result_async()
    assert outcome is not None
    print(f"result: {STATUS.get(outcome.status, outcome.status)}, final_count={outcome.result.final_count}", flush=True)
    wanted = GoalStatus.STATUS_CANCELED if cancel_after is not None else GoalStatus.STATUS_SUCCEEDED
    return bool(outcome.status == wanted)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("target", type=int)
    parser.add_argument("--cancel-after", type=float, default=None, metavar="SECONDS")
    parser.add_argument("--action", default="/count_to")
    parser.add_argument("--wait", type=float, default=10.0, help="seconds to wait for the server")
    args = parser.parse_args()
    rclpy.init()
    node = Node("count_to_client")
    client: ActionClient[Any, Any, Any] = ActionClient(node, CountTo, args.action)
    executor = AsyncioExecutor()
    executor.add_node(node)
    try:
        if not client.wait_for_server(timeout_sec=args.wait):
            print(f"no action server on {args.action}", file=sys.stderr)
            return 1
        task = executor.create_task(count(node, client, args.target, args.cancel_after))
        executor.spin_until_future_complete(task)
        return 0 if task.result() else 1
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.utilities.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
