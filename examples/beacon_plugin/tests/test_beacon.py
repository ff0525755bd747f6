"""The beacon plugin's own tests: its message and action, in the container and across processes.

Fixtures from lifecycle-container's pytest plugin (``container.testing``).
Run with the plugin installed: ``pip install --no-build-isolation
./examples/beacon_plugin && pytest examples/beacon_plugin/tests``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest
from beacon_interfaces.action import Sweep
from beacon_interfaces.msg import Beacon
from rclpy.action.client import ActionClient

from container.testing import ContainerHost

pytestmark = pytest.mark.asyncio


async def test_publishes_numbered_beacons_while_active(container_host: ContainerHost) -> None:
    await container_host.load("beacon_nodes::Beacon", parameters={"name": "north", "rate": 20.0})

    first = await container_host.wait_for_message(Beacon, "/beacon")
    later = await container_host.wait_for_message(Beacon, "/beacon", where=lambda m: m.seq > first.seq)

    assert first.name == later.name == "north"
    assert later.seq > first.seq >= 1
    assert (later.stamp.sec, later.stamp.nanosec) > (first.stamp.sec, first.stamp.nanosec)


async def test_sweeps_with_feedback(container_host: ContainerHost) -> None:
    await container_host.load("beacon_nodes::Beacon")
    client: ActionClient[Any, Any, Any] = ActionClient(container_host.client, Sweep, "/sweep")
    await container_host.wait_until(client.server_is_ready, what="the sweep action server")
    steps: list[int] = []

    sent = client.send_goal_async(
        Sweep.Goal(steps=4, step_period=0.02), feedback_callback=lambda f: steps.append(f.feedback.step)
    )
    goal = await container_host.wait_for_future(sent)
    assert goal.accepted
    result = await container_host.wait_for_future(goal.get_result_async())

    assert result.result.done == 4
    await container_host.wait_until(lambda: steps == [1, 2, 3, 4], what=f"all feedback (got {steps})")
    client.destroy()


async def test_another_process_reads_the_plugins_message(container_host: ContainerHost, tmp_path: Path) -> None:
    # Usable across processes: a plain rclpy node in another process, with the
    # same generated package, takes the beacons and sees the same type hash.
    listener = textwrap.dedent(
        """
        import json, rclpy
        from rclpy.node import Node
        from beacon_interfaces.msg import Beacon
        rclpy.init()
        node = Node("beacon_listener")
        got = []
        node.create_subscription(Beacon, "/beacon", got.append, 10)
        while not got:
            rclpy.spin_once(node, timeout_sec=1.0)
        [info] = node.get_publishers_info_by_topic("/beacon")
        print(json.dumps({"name": got[0].name, "hash": str(info.topic_type_hash)}), flush=True)
        """
    )
    await container_host.load("beacon_nodes::Beacon", parameters={"name": "south"})
    result = subprocess.run([sys.executable, "-c", listener], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    seen = json.loads(result.stdout.splitlines()[-1])

    assert seen["name"] == "south"
    # The RIHS01 hash rosidl computed when the plugin was built (what a ROS
    # install's build of the same package computes from the same definitions).
    import beacon_interfaces

    description = Path(beacon_interfaces.__file__).parents[4] / "share" / "beacon_interfaces" / "msg" / "Beacon.json"
    built = json.loads(description.read_text())["type_hashes"][0]
    assert built["type_name"] == "beacon_interfaces/msg/Beacon"
    assert seen["hash"] == built["hash_string"]
