"""Small executor scenarios whose event logs must not depend on the engine.

``tests/executor/test_engines.py`` runs each in a child process per engine
(``CONTAINER_EXECUTOR_ENGINE``): ``python engine_scenarios.py NAME`` prints
one JSON line, ``{"engine": ..., "log": ...}``. Each scenario drives its
nodes one step at a time (publishing the next message once the log shows
the last one arrived), so that the log is what the executor's contract
decides, not what the machine's timing happens to be: a wait that times out
is logged as ``"timeout"`` and ends the scenario.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.client import Client
from rclpy.node import Node
from rclpy.task import Future
from std_msgs.msg import Int64
from std_srvs.srv import Trigger

from container import AsyncioExecutor
from container.executor import _engine
from container.intra import enable_intra_process

#: How long any one step of a scenario may take.
STEP_S = 10.0

Log = list[Any]


class _Timeout(Exception):
    """A step of the scenario did not happen in time."""


def _until(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + STEP_S
    while not condition():
        if time.monotonic() > deadline:
            raise _Timeout(what)
        time.sleep(0.002)


@contextlib.contextmanager
def _spinning(executor: AsyncioExecutor) -> Iterator[None]:
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        yield
    finally:
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)


def _matched(publisher: Any) -> None:
    _until(lambda: publisher.get_subscription_count() >= 1, "a match")


def exclusive_group(log: Log) -> None:
    """A plain and an ``async def`` callback of one mutually exclusive group: each
    message published while the other callback runs (the async one suspended in
    an await) starts only once it ended."""
    node = Node("engines_exclusive")
    group = MutuallyExclusiveCallbackGroup()
    inside = [0]
    lock = threading.Lock()

    def enter(name: str, n: int) -> None:
        with lock:
            inside[0] += 1
            log.append([f"{name} start", n, inside[0]])

    def leave(name: str, n: int) -> None:
        with lock:
            inside[0] -= 1
            log.append([f"{name} end", n])

    def on_plain(msg: Int64) -> None:
        enter("plain", msg.data)
        time.sleep(0.1)
        leave("plain", msg.data)

    async def on_async(msg: Int64) -> None:
        enter("async", msg.data)
        await asyncio.sleep(0.1)
        leave("async", msg.data)

    plain = node.create_publisher(Int64, "engines_plain", 10)
    coroutine = node.create_publisher(Int64, "engines_async", 10)
    node.create_subscription(Int64, "engines_plain", on_plain, 10, callback_group=group)
    node.create_subscription(Int64, "engines_async", on_async, 10, callback_group=group)  # type: ignore[arg-type]  # rclpy types only plain callbacks
    executor = AsyncioExecutor()
    executor.add_node(node)
    _matched(plain)
    _matched(coroutine)

    def started(name: str, n: int) -> Callable[[], bool]:
        return lambda: any(entry[:2] == [f"{name} start", n] for entry in list(log))

    with _spinning(executor):
        plain.publish(Int64(data=1))
        _until(started("plain", 1), "the plain callback")
        coroutine.publish(Int64(data=1))  # while the plain one runs
        _until(started("async", 1), "the async callback")
        plain.publish(Int64(data=2))  # while the async one is suspended
        _until(lambda: ["plain end", 2] in log, "the plain callback's end")


def keep_last(log: Log) -> None:
    """A subscription of depth 2 whose group is busy: of the five messages taken
    meanwhile the lane keeps the last two, and drops three."""
    node = Node("engines_keep_last")
    release = threading.Event()
    got: list[int] = []

    def on(msg: Int64) -> None:
        got.append(msg.data)
        if msg.data == 1:
            release.wait(STEP_S)

    publisher = node.create_publisher(Int64, "engines_keep_last", 10)
    subscription = node.create_subscription(Int64, "engines_keep_last", on, 2)
    executor = AsyncioExecutor()
    executor.add_node(node)
    _matched(publisher)
    with _spinning(executor):
        publisher.publish(Int64(data=1))
        _until(lambda: got == [1], "the first message")
        lane = executor._dispatcher.lane_for(subscription.callback_group, node)
        for n in range(2, 7):
            publisher.publish(Int64(data=n))
            # Taken into the lane (waiting or dropped there) before the next is published.
            _until(lambda: lane.slots.waiting + lane.dropped == n - 1, f"message {n} taken")  # noqa: B023
        log.append(["waiting", lane.slots.waiting, "dropped", lane.dropped])
        release.set()
        _until(lambda: len(got) == 3, "the kept messages")
        log.append(["got", *got])


def spin_once(log: Log) -> None:
    """``spin_once`` runs one callback per call, three messages waiting."""
    node = Node("engines_spin_once")
    got: list[int] = []

    async def on(msg: Int64) -> None:
        got.append(msg.data)

    publisher = node.create_publisher(Int64, "engines_spin_once", 10)
    node.create_subscription(Int64, "engines_spin_once", on, 10)  # type: ignore[arg-type]  # rclpy types only plain callbacks
    executor = AsyncioExecutor()
    executor.add_node(node)
    _matched(publisher)
    for n in (1, 2, 3):
        publisher.publish(Int64(data=n))
    try:
        for timeout in (STEP_S, STEP_S, STEP_S, 0.2):
            before = len(got)
            executor.spin_once(timeout_sec=timeout)
            log.append(["ran", got[before:]])
    finally:
        executor.shutdown(timeout_sec=5.0)


def _service_chain(log: Log, *, style: str) -> None:
    """Five calls, each made from the previous response's done-callback."""
    server, caller = Node(f"engines_server_{style}"), Node(f"engines_caller_{style}")
    served = [0]

    def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        served[0] += 1
        log.append(["served", served[0]])
        response.success, response.message = True, f"call {served[0]}"
        return response

    async def answer_async(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        await asyncio.sleep(0)
        return answer(request, response)

    server.create_service(Trigger, f"engines_{style}", answer_async if style == "async" else answer)
    client: Client[Any, Any] = caller.create_client(Trigger, f"engines_{style}")
    executor = AsyncioExecutor()
    executor.add_node(server)
    executor.add_node(caller)
    finished: Future[None] = Future()

    def answered(future: Future[Any]) -> None:
        response = future.result()
        log.append(["answered", response.message if response is not None else None])
        if len(log) >= 10:
            finished.set_result(None)
        else:
            client.call_async(Trigger.Request()).add_done_callback(answered)

    if not client.wait_for_service(timeout_sec=STEP_S):
        raise _Timeout("the service")
    with _spinning(executor):
        executor.loop.call_soon_threadsafe(lambda: client.call_async(Trigger.Request()).add_done_callback(answered))
        _until(finished.done, "the fifth answer")


def service_chain_plain(log: Log) -> None:
    _service_chain(log, style="plain")


def service_chain_async(log: Log) -> None:
    _service_chain(log, style="async")


def intra_process(log: Log) -> None:
    """Messages between two nodes of the process with intra-process enabled: in process, in order,
    with rclpy's keys of message info."""
    source, sink = Node("engines_intra_source"), Node("engines_intra_sink")
    enable_intra_process(source)
    enable_intra_process(sink)
    publisher = source.create_publisher(Int64, "engines_intra", 10)

    def on(msg: Int64, info: dict[str, Any]) -> None:
        in_process = info["received_timestamp"] == info["source_timestamp"]
        log.append([msg.data, info["publication_sequence_number"], in_process, sorted(info)])

    subscription = sink.create_subscription(Int64, "engines_intra", on, 10)  # type: ignore[arg-type, unused-ignore]  # rclpy 7 types one-argument callbacks
    executor = AsyncioExecutor()
    executor.add_node(source)
    executor.add_node(sink)
    with _spinning(executor):
        _until(lambda: executor._dispatcher._hot.entry_of(subscription) is not None, "the subscription")
        for n in (1, 2, 3):
            publisher.publish(Int64(data=n))
            _until(lambda: len(log) >= n, f"message {n}")  # noqa: B023


SCENARIOS: dict[str, Callable[[Log], None]] = {
    "exclusive_group": exclusive_group,
    "keep_last": keep_last,
    "spin_once": spin_once,
    "service_chain_plain": service_chain_plain,
    "service_chain_async": service_chain_async,
    "intra_process": intra_process,
}


def main() -> None:
    rclpy.init()
    log: Log = []
    try:
        SCENARIOS[sys.argv[1]](log)
    except _Timeout as timeout:
        log.append(["timeout", str(timeout)])
    finally:
        rclpy.shutdown()
    print(json.dumps({"engine": _engine.ENGINE, "log": log}), flush=True)


if __name__ == "__main__":
    main()
