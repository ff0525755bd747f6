"""Run by ``test_one_cpu`` in a process of its own, under ``taskset -c 0``.

One executor, spinning in a thread, runs in turn: a plain ping-pong
between two nodes, a chain of plain service calls (each response's
done-callback makes the next call), a chain of ``async def`` ones (an
``async def`` service, called from a coroutine on the executor's loop),
and a 20 Hz plain timer in one node beside another node's plain callback
that blocks for 1 s at a time. Prints one JSON object with what it saw;
the test judges it.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import threading
import time
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.client import Client
from rclpy.node import Node
from rclpy.utilities import try_shutdown
from std_msgs.msg import Int64
from std_srvs.srv import Trigger

from container import AsyncioExecutor
from container.executor._cores import usable_cpus

#: How long each scenario may take before it counts as stuck, in seconds.
TIMEOUT = 10.0
ROUND_TRIPS = 300
CALLS = 300
#: The timer's period, and how many of its ticks are timed beside the blocker.
PERIOD = 0.05
TICKS = 30
#: How long the neighbour's plain callback blocks, each time it runs.
BLOCK_S = 1.0


def until(condition: Callable[[], bool], timeout: float = TIMEOUT) -> bool:
    """Whether ``condition`` came true within ``timeout`` (this thread sleeps between looks)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True


def ping_pong(executor: AsyncioExecutor, nodes: list[Node]) -> int:
    """Plain callbacks: A publishes a ping, B's callback answers, A's sends the next."""
    a = Node("one_cpu_ping", context=executor.context)
    b = Node("one_cpu_pong", context=executor.context)
    nodes += [a, b]
    pings = a.create_publisher(Int64, "one_cpu/ping", 10)
    pongs = b.create_publisher(Int64, "one_cpu/pong", 10)
    b.create_subscription(Int64, "one_cpu/ping", pongs.publish, 10)
    count = [0]
    done = threading.Event()

    def pong(message: Int64) -> None:
        count[0] += 1
        if count[0] >= ROUND_TRIPS:
            done.set()
        else:
            pings.publish(Int64(data=count[0]))

    a.create_subscription(Int64, "one_cpu/pong", pong, 10)
    executor.add_node(a)
    executor.add_node(b)
    if until(lambda: pings.get_subscription_count() > 0 and pongs.get_subscription_count() > 0):
        pings.publish(Int64(data=0))
        done.wait(TIMEOUT)
    return count[0]


def plain_service_calls(executor: AsyncioExecutor, nodes: list[Node]) -> int:
    """A plain service; each response's done-callback makes the next call."""
    server = Node("one_cpu_server", context=executor.context)
    caller = Node("one_cpu_caller", context=executor.context)
    nodes += [server, caller]
    server.create_service(Trigger, "one_cpu/plain", lambda request, response: response)
    client: Client[Any, Any] = caller.create_client(Trigger, "one_cpu/plain")
    count = [0]
    done = threading.Event()

    def next_call(_: Any = None) -> None:
        count[0] += 1
        if count[0] > CALLS:
            done.set()
        else:
            client.call_async(Trigger.Request()).add_done_callback(next_call)

    executor.add_node(server)
    executor.add_node(caller)
    if client.wait_for_service(timeout_sec=TIMEOUT):
        executor.loop.call_soon_threadsafe(next_call)
        done.wait(TIMEOUT)
    return count[0] - 1


def async_service_calls(executor: AsyncioExecutor, nodes: list[Node]) -> int:
    """An ``async def`` service, awaited call after call by a coroutine on the loop."""
    server = Node("one_cpu_async_server", context=executor.context)
    caller = Node("one_cpu_async_caller", context=executor.context)
    nodes += [server, caller]

    async def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        await asyncio.sleep(0)
        response.success = True
        return response

    server.create_service(Trigger, "one_cpu/async", answer)
    client: Client[Any, Any] = caller.create_client(Trigger, "one_cpu/async")
    count = [0]

    async def chain() -> None:
        for _ in range(CALLS):
            response = await client.call_async(Trigger.Request())
            if response is not None and response.success:
                count[0] += 1

    executor.add_node(server)
    executor.add_node(caller)
    if client.wait_for_service(timeout_sec=TIMEOUT):
        calls = asyncio.run_coroutine_threadsafe(chain(), executor.loop)
        try:
            calls.result(TIMEOUT)
        except TimeoutError:
            calls.cancel()
    return count[0]


def timer_beside_a_blocker(executor: AsyncioExecutor, nodes: list[Node]) -> list[float]:
    """A 20 Hz plain timer's ticks while another node's plain callback blocks; their gaps."""
    blocker = Node("one_cpu_blocker", context=executor.context)
    ticker = Node("one_cpu_ticker", context=executor.context)
    nodes += [blocker, ticker]
    blocking = threading.Event()
    ticks: list[float] = []
    enough = threading.Event()

    def block() -> None:
        blocking.set()
        time.sleep(BLOCK_S)

    def tick() -> None:
        if blocking.is_set():
            ticks.append(time.monotonic())
            if len(ticks) > TICKS:
                enough.set()

    blocker.create_timer(0.01, block)
    ticker.create_timer(PERIOD, tick)
    executor.add_node(blocker)
    executor.add_node(ticker)
    enough.wait(TIMEOUT)
    executor.remove_node(blocker)
    return [later - earlier for earlier, later in itertools.pairwise(ticks[: TICKS + 1])]


def main() -> None:
    rclpy.init()
    executor = AsyncioExecutor()
    handoff = executor._dispatcher.handoff
    nodes: list[Node] = []
    seen: dict[str, Any] = {
        "affinity": sorted(os.sched_getaffinity(0)),
        "usable_cpus": usable_cpus(),
        "spin": handoff.spin,
    }
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        seen["ping_pong"] = ping_pong(executor, nodes)
        seen["plain_service_calls"] = plain_service_calls(executor, nodes)
        seen["async_service_calls"] = async_service_calls(executor, nodes)
        seen["gaps"] = timer_beside_a_blocker(executor, nodes)
        seen["lingered"] = handoff.lingered
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
        for node in nodes:
            node.destroy_node()
        try_shutdown()
    print(json.dumps(seen), flush=True)


if __name__ == "__main__":
    main()
