"""Scale: a container of many idle nodes keeps few threads."""

from __future__ import annotations

import asyncio
import os
import threading

import pytest
from rclpy.node import Node

from container.executor import _lanes
from container.testing import ContainerHost
from tests.waiting import wait_until_async

pytestmark = pytest.mark.timeout(60)

#: Nodes loaded; every one's callback group gets a worker thread of its own below.
NODES = 40
#: Threads the idle nodes may keep beyond what the process had with none:
#: an empty ``container run`` has 18 or 19 (Fast DDS's, rcl's, the
#: executor's), so a container of idle nodes keeps at most 20.
MOST_EXTRA_THREADS = 2


def threads_in_process() -> int:
    return len(os.listdir("/proc/self/task"))


async def test_a_container_of_idle_nodes_settles_to_few_threads(
    container_host: ContainerHost, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_lanes, "WORKER_IDLE_S", 0.3)
    empty = threads_in_process()
    # Listeners with no talker: lifecycle nodes that take no traffic.
    nodes: list[Node] = [
        await container_host.load("lifecycle_container::Listener", name=f"idle{i}") for i in range(NODES)
    ]
    # Run a plain call in every node's group at once, as service calls to
    # every node would: each group's lane starts a worker thread.
    gate = threading.Barrier(NODES + 1)
    executor = container_host.executor
    calls = [
        executor.run_in_group(node.default_callback_group, lambda: gate.wait(10.0), node=node) for node in nodes
    ]
    await asyncio.to_thread(gate.wait, 10.0)
    await asyncio.gather(*calls)
    assert threads_in_process() > NODES
    most = empty + MOST_EXTRA_THREADS
    await wait_until_async(
        lambda: threads_in_process() <= most,
        lambda: f"at most {most} threads, {empty} with no node loaded (now {threads_in_process()})",
        timeout=5.0,
    )
