"""AsyncioExecutor: isolation, callback-group semantics, async callbacks, failures."""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import gc
import itertools
import logging
import subprocess
import sys
import threading
import time
import warnings
import weakref
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.client import Client
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from rclpy.task import Future as RclFuture
from std_msgs.msg import Int64
from std_srvs.srv import SetBool, Trigger

from container import AsyncioExecutor, ExecutorError, _compat
from container.executor import _waitset
from tests.engine_support import compiled_only


@pytest.fixture
def make_node(context: Context) -> Iterator[Callable[[str], Node]]:
    nodes: list[Node] = []

    def make(name: str) -> Node:
        node = Node(name, context=context)
        nodes.append(node)
        return node

    yield make
    for node in nodes:
        node.destroy_node()


def spin_in_thread(executor: AsyncioExecutor) -> threading.Thread:
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    return thread


def slow_pong(server: Node, client: Node, service: str) -> Any:
    """A ``Trigger`` service on ``server`` that answers "pong" after 0.3 s
    (a plain callback: its caller waits on an rclpy future meanwhile), and
    ``client``'s client of it."""

    def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        time.sleep(0.3)
        response.success = True
        response.message = "pong"
        return response

    server.create_service(Trigger, service, answer)
    return client.create_client(Trigger, service)


class Concurrency:
    """Track how many callbacks run at once."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.now = 0
        self.peak = 0
        self.calls = 0

    def __enter__(self) -> None:
        with self._lock:
            self.now += 1
            self.calls += 1
            self.peak = max(self.peak, self.now)

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            self.now -= 1


def test_blocking_plain_callback_in_one_node_does_not_delay_another(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    blocker, ticker = make_node("blocker"), make_node("ticker")
    blocking = threading.Event()
    ticks: list[float] = []
    enough = threading.Event()

    def block() -> None:
        blocking.set()
        time.sleep(1.5)

    def tick() -> None:
        if blocking.is_set():
            ticks.append(time.monotonic())
            if len(ticks) >= 20:
                enough.set()

    blocker.create_timer(0.01, block)
    ticker.create_timer(0.05, tick)
    executor.add_node(blocker)
    executor.add_node(ticker)
    thread = spin_in_thread(executor)
    assert enough.wait(10.0), "the ticker stalled behind the blocker"
    executor.shutdown(timeout_sec=5.0)
    thread.join(5.0)
    gaps = [b - a for a, b in itertools.pairwise(ticks)]
    # 20 ticks at 20 Hz all fell inside the blocker's 1.5 s callbacks.
    assert max(gaps) < 0.25, gaps


@compiled_only("rmw new-data callbacks (a worker carries on to what its callback published)")
def test_callback_carried_to_another_lanes_thread_that_blocks_delays_nobody(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    """A worker that finished node A's callback runs node B's next (see ``_lanes``).

    B's callback then blocks on A's thread: A's own timer must still fire
    (on another thread of A's lane) and B's group must stay exclusive.
    """
    a, b = make_node("carrier_a"), make_node("carrier_b")
    sender = a.create_publisher(Int64, "carried", 10)
    b_threads: list[str] = []
    b_seen = Concurrency()
    blocking = threading.Event()
    ticks: list[float] = []
    enough = threading.Event()
    #: Per thread: what it ran last (a worker's threads are shared by every lane).
    last = threading.local()

    def tick() -> None:
        sender.publish(Int64(data=len(ticks)))
        if blocking.is_set():
            ticks.append(time.monotonic())
            if len(ticks) >= 15:
                enough.set()
        last.ran = "a"

    def receive(msg: Int64) -> None:
        with b_seen:
            carried = getattr(last, "ran", None) == "a"
            last.ran = "b"
            b_threads.append(f"{threading.current_thread().name}{' after A' if carried else ''}")
            if carried and not blocking.is_set():
                ticks.append(time.monotonic())  # the gaps count from here
                blocking.set()
                time.sleep(1.5)  # carried onto A's thread, and stuck there

    a.create_timer(0.02, tick)
    b.create_subscription(Int64, "carried", receive, 10)
    executor.add_node(a)
    executor.add_node(b)
    thread = spin_in_thread(executor)
    try:
        assert enough.wait(15.0), f"A's timer stalled, or B never ran on A's thread: {set(b_threads)}"
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
    gaps = [later - earlier for earlier, later in itertools.pairwise(ticks)]
    # 15 ticks at 50 Hz from the moment B's callback got stuck on A's thread.
    assert max(gaps) < 0.25, gaps
    assert b_seen.peak == 1


@pytest.mark.parametrize("kind", ["plain", "async"])
def test_mutually_exclusive_group_never_overlaps(
    executor: AsyncioExecutor, make_node: Callable[[str], Node], kind: str
) -> None:
    node = make_node(f"exclusive_{kind}")
    group = MutuallyExclusiveCallbackGroup()
    seen = Concurrency()
    done = threading.Event()

    def plain() -> None:
        with seen:
            time.sleep(0.02)
        if seen.calls >= 20:
            done.set()

    async def coro() -> None:
        with seen:
            await asyncio.sleep(0.02)
        if seen.calls >= 20:
            done.set()

    for _ in range(4):
        # rclpy 9 annotates timer callbacks as plain
        node.create_timer(0.005, plain if kind == "plain" else coro, callback_group=group)  # type: ignore[arg-type, unused-ignore]
    executor.add_node(node)
    thread = spin_in_thread(executor)
    assert done.wait(10.0)
    executor.shutdown(timeout_sec=5.0)
    thread.join(5.0)
    assert seen.peak == 1


@pytest.mark.parametrize("kind", ["plain", "async"])
def test_reentrant_group_runs_callbacks_concurrently_within_its_bound(
    context: Context, make_node: Callable[[str], Node], kind: str
) -> None:
    executor = AsyncioExecutor(context=context, reentrant_limit=3)
    node = make_node(f"reentrant_{kind}")
    group = ReentrantCallbackGroup()
    seen = Concurrency()
    done = threading.Event()

    def plain() -> None:
        with seen:
            time.sleep(0.1)
        if seen.calls >= 12:
            done.set()

    async def coro() -> None:
        with seen:
            await asyncio.sleep(0.1)
        if seen.calls >= 12:
            done.set()

    for _ in range(6):
        # rclpy 9 annotates timer callbacks as plain
        node.create_timer(0.01, plain if kind == "plain" else coro, callback_group=group)  # type: ignore[arg-type, unused-ignore]
    executor.add_node(node)
    thread = spin_in_thread(executor)
    try:
        assert done.wait(10.0)
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
    assert seen.peak > 1, "a reentrant group ran its callbacks one at a time"
    assert seen.peak <= 3, "the reentrant bound was not respected"


def test_async_callback_awaits_asyncio_stream_io(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    node = make_node("streamer")
    pub = node.create_publisher(Int64, "numbers", 10)
    echoed: list[bytes] = []
    done = threading.Event()

    async def serve_echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(await reader.readline())
        await writer.drain()
        writer.close()

    async def on_number(msg: Int64) -> None:
        # Real asyncio I/O on the executor's loop, from inside a ROS callback.
        server = await asyncio.start_server(serve_echo, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(f"{msg.data}\n".encode())
        await writer.drain()
        echoed.append(await reader.readline())
        writer.close()
        server.close()
        await server.wait_closed()
        done.set()

    node.create_subscription(Int64, "numbers", on_number, 10)  # type: ignore[arg-type]  # rclpy types only plain callbacks
    node.create_timer(0.05, lambda: pub.publish(Int64(data=42)) if not done.is_set() else None)
    executor.add_node(node)
    thread = spin_in_thread(executor)
    assert done.wait(10.0)
    executor.shutdown(timeout_sec=5.0)
    thread.join(5.0)
    assert echoed[0] == b"42\n"


_where: contextvars.ContextVar[str] = contextvars.ContextVar("where", default="unset")


def test_async_callback_is_a_task_with_one_context_across_its_awaits(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    """The eager first step runs as a task: asyncio.timeout works, context persists."""
    node = make_node("timeouts")
    pub = node.create_publisher(Int64, "ticks", 10)
    seen: list[tuple[bool, str, str]] = []
    done = threading.Event()

    async def on_tick(msg: Int64) -> None:
        in_task = asyncio.current_task() is not None
        _where.set(f"tick {msg.data}")
        outcome = "finished"
        try:
            async with asyncio.timeout(0.02):  # raises RuntimeError outside a task
                await asyncio.sleep(5.0)
        except TimeoutError:
            outcome = "timed out"
        seen.append((in_task, outcome, _where.get()))
        if len(seen) >= 3:
            done.set()

    node.create_subscription(Int64, "ticks", on_tick, 10)  # type: ignore[arg-type]
    node.create_timer(0.05, lambda: pub.publish(Int64(data=len(seen))) if not done.is_set() else None)
    executor.add_node(node)
    thread = spin_in_thread(executor)
    assert done.wait(10.0)
    executor.shutdown(timeout_sec=5.0)
    thread.join(5.0)
    for in_task, outcome, where in seen[:3]:
        assert (in_task, outcome) == (True, "timed out")
        assert where.startswith("tick ")


_request: contextvars.ContextVar[str] = contextvars.ContextVar("request", default="unset")


@pytest.mark.parametrize("style", ["async", "plain"])
def test_each_callback_starts_in_a_copy_of_the_spinning_context(
    executor: AsyncioExecutor, make_node: Callable[[str], Node], style: str
) -> None:
    """As each asyncio task runs in a copy of the context it was created
    in: what a callback sets in a ContextVar stays its own (across its
    awaits), and the next callback of the same group starts afresh."""
    node = make_node(f"context_{style}")
    pub = node.create_publisher(Int64, f"context_{style}", 10)
    seen: list[tuple[str, str]] = []
    done = threading.Event()

    async def on_message_async(msg: Int64) -> None:
        seen.append((f"message {msg.data}", _request.get()))
        _request.set(f"message {msg.data}")
        await asyncio.sleep(0.001)
        seen.append((f"message {msg.data} after its await", _request.get()))

    def on_message(msg: Int64) -> None:
        seen.append((f"message {msg.data}", _request.get()))
        _request.set(f"message {msg.data}")

    def on_tick() -> None:
        seen.append(("tick", _request.get()))
        _request.set("tick")
        if len([what for what, _ in seen if what.startswith("message")]) >= 6:
            done.set()
        else:
            pub.publish(Int64(data=len(seen)))

    async def on_tick_async() -> None:
        on_tick()

    node.create_subscription(Int64, f"context_{style}", on_message_async if style == "async" else on_message, 10)  # type: ignore[arg-type]
    # Same group as the subscription. rclpy 9 annotates timer callbacks as plain.
    node.create_timer(0.02, on_tick_async if style == "async" else on_tick)  # type: ignore[arg-type, unused-ignore]
    executor.add_node(node)

    def spin() -> None:
        _request.set("spinner")  # what every callback's context is a copy of
        executor.spin()

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    assert done.wait(10.0)
    executor.shutdown(timeout_sec=5.0)
    thread.join(5.0)
    for what, value in seen:
        if what.endswith("after its await"):
            assert value == what.removesuffix(" after its await"), seen
        else:
            assert value == "spinner", seen


@pytest.mark.parametrize("kind", ["coroutine", "plain"])
def test_a_coroutine_awaiting_a_task_of_the_executor_goes_on_as_it_finishes(
    executor: AsyncioExecutor, make_node: Callable[[str], Node], kind: str
) -> None:
    """An rclpy future is awaited by parking on the executor's progress; a
    task's finishing is progress (it took the 10 ms poll each before)."""
    executor.add_node(make_node("awaits_tasks"))

    async def work() -> int:
        return 1

    def plain_work() -> int:
        return 1

    async def main() -> float:
        started = time.monotonic()
        for _ in range(100):
            assert await executor.create_task(work if kind == "coroutine" else plain_work) == 1
        return time.monotonic() - started

    outcome = executor.create_task(main)
    executor.spin_until_future_complete(outcome, timeout_sec=30.0)
    took = outcome.result()
    assert took is not None, "the awaits never finished"
    assert took < 0.5, f"100 awaits took {took:.2f} s: each waited for the poll"


def test_async_callback_awaits_a_service_call_without_busy_waiting(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    server_node, client_node = make_node("trigger_server"), make_node("trigger_client")

    client = slow_pong(server_node, client_node, "ping")
    replies: list[str] = []
    done = threading.Event()
    fired = threading.Event()

    async def call_once() -> None:
        if fired.is_set():
            return
        fired.set()
        while not client.service_is_ready():
            await asyncio.sleep(0.02)
        started = time.process_time()
        response = await client.call_async(Trigger.Request())
        replies.append(response.message)
        replies.append(f"cpu={time.process_time() - started:.3f}")
        done.set()

    # rclpy 9 annotates timer callbacks as plain
    client_node.create_timer(0.01, call_once)  # type: ignore[arg-type, unused-ignore]
    executor.add_node(server_node)
    executor.add_node(client_node)
    thread = spin_in_thread(executor)
    assert done.wait(10.0)
    executor.shutdown(timeout_sec=5.0)
    thread.join(5.0)
    assert replies[0] == "pong"
    # Awaiting 0.3 s must not spin a core: a busy loop burns ~0.3 s of CPU.
    assert float(replies[1].split("=")[1]) < 0.15, replies


def test_a_responses_done_callbacks_run_on_the_loop_in_order_and_an_error_is_logged(
    executor: AsyncioExecutor, make_node: Callable[[str], Node], caplog: pytest.LogCaptureFixture
) -> None:
    """A service response's done-callbacks skip the task machinery (one
    post each, see ``_tasks.DoneCallbacks``); they still run on the loop's
    thread, in the order added, and one that raises is logged and stops
    nothing: the next callback runs, the next call is answered."""
    server_node, client_node = make_node("done_server"), make_node("done_client")

    def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success = True
        return response

    server_node.create_service(Trigger, "done_order", answer)
    client: Client[Any, Any] = client_node.create_client(Trigger, "done_order")
    executor.add_node(server_node)
    executor.add_node(client_node)
    thread = spin_in_thread(executor)
    seen: list[tuple[str, int]] = []
    finished = threading.Event()

    def record(name: str) -> Callable[[RclFuture[Any]], None]:
        def done(_: RclFuture[Any]) -> None:
            seen.append((name, threading.get_ident()))
            if name == "last":
                finished.set()

        return done

    def fails(_: RclFuture[Any]) -> None:
        raise RuntimeError("told to fail")

    try:
        assert client.wait_for_service(timeout_sec=10.0)
        with caplog.at_level(logging.ERROR, logger="container.executor._tasks"):
            future = client.call_async(Trigger.Request())
            for callback in (record("first"), fails, record("last")):
                future.add_done_callback(callback)
            assert finished.wait(10.0), seen
            again = client.call_async(Trigger.Request())
            answered = threading.Event()
            again.add_done_callback(lambda _: answered.set())
            assert answered.wait(10.0)
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
    assert [name for name, _ in seen] == ["first", "last"]
    assert {ident for _, ident in seen} == {thread.ident}
    reply = again.result()
    assert reply is not None and reply.success
    assert [record.message for record in caplog.records] == ["a done-callback of a service response raised"]
    assert "told to fail" in caplog.text


@pytest.mark.parametrize("how", ["asyncio.create_task", "asyncio.wait_for"])
def test_an_asyncio_task_awaits_a_service_call_without_busy_waiting(
    executor: AsyncioExecutor, make_node: Callable[[str], Node], how: str
) -> None:
    # A task a plugin starts itself (or that asyncio starts for wait_for,
    # gather, ensure_future) is no callback; an rclpy future it awaits yields
    # a bare None until done, which a plain asyncio task re-runs at once:
    # before, such a wait burned a core for as long as the call took.
    server_node, client_node = make_node(f"slow_server_{how[8:]}"), make_node(f"task_client_{how[8:]}")

    client = slow_pong(server_node, client_node, "slow_ping")
    replies: list[tuple[str, float]] = []
    done = threading.Event()

    async def call() -> None:
        started = time.process_time()
        if how == "asyncio.wait_for":
            response = await asyncio.wait_for(client.call_async(Trigger.Request()), timeout=10.0)
        else:
            response = await client.call_async(Trigger.Request())
        replies.append((response.message, time.process_time() - started))
        done.set()

    async def start() -> None:
        timer.cancel()
        if how == "asyncio.wait_for":
            await call()
        else:
            background.append(asyncio.get_running_loop().create_task(call()))

    background: list[asyncio.Task[None]] = []
    executor.add_node(server_node)
    executor.add_node(client_node)
    assert client.wait_for_service(timeout_sec=10.0)
    # rclpy 9 annotates timer callbacks as plain
    timer = client_node.create_timer(0.01, start)  # type: ignore[arg-type, unused-ignore]
    thread = spin_in_thread(executor)
    assert done.wait(10.0)
    executor.shutdown(timeout_sec=5.0)
    thread.join(5.0)
    assert replies[0][0] == "pong"
    # Awaiting 0.3 s must not spin a core: a busy loop burns ~0.3 s of CPU.
    assert replies[0][1] < 0.15, replies


def test_a_task_cancelled_before_its_first_step_leaves_no_coroutine_unawaited(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    # Tasks on the executor's loop run their coroutine through a wrapper
    # (see the test above); cancelled before the wrapper starts, the
    # coroutine itself must still be closed, as asyncio closes it.
    executor.add_node(make_node("cancel_unstarted"))
    outcomes: list[bool] = []

    async def never_started() -> int:
        return 1

    async def main() -> None:
        task = asyncio.get_running_loop().create_task(never_started())
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        outcomes.append(task.cancelled())

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        executor.spin_until_future_complete(main(), timeout_sec=10.0)
        gc.collect()
    assert outcomes == [True]
    assert [str(w.message) for w in caught if "never awaited" in str(w.message)] == []


def test_a_task_cancelled_while_its_wake_up_is_queued_runs_no_step_past_its_await(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    """rclpy's ``task.cancel()`` takes effect at once. Between spins, with the
    task's wake-up already queued on the idle loop (its parked await looked
    again), a cancel posted behind it let one more step run: about one try in
    ten under load in the conformance test of the same name."""
    executor.add_node(make_node("cancel_queued"))
    gate: RclFuture[Any] = RclFuture()
    steps: list[str] = []

    async def waits() -> None:
        steps.append("before")
        await gate
        steps.append("after")

    task = executor.create_task(waits)
    for _ in range(3):
        executor.spin_once(timeout_sec=0.05)
    assert steps == ["before"]
    # The parked await looks again: its task's wake-up is queued on the loop, which nobody runs now.
    progress = executor._progress_future()
    progress.set_result(None)
    task.cancel()
    gate.set_result(None)
    for _ in range(3):
        executor.spin_once(timeout_sec=0.05)
    assert steps == ["before"], "the task went on past the await it was cancelled at"
    assert task.cancelled()


@pytest.mark.parametrize("where", ["task", "timer"])
def test_asyncio_sleep_zero_yields_to_the_loop_and_comes_straight_back(
    executor: AsyncioExecutor, make_node: Callable[[str], Node], where: str
) -> None:
    # asyncio's "let the others run": it yields a bare None, as an awaited
    # rclpy future does while not done; parked like one (until progress or
    # the 10 ms poll), a loop of them ran 100 times a second.
    node = make_node(f"sleep_zero_{where}")
    order: list[str] = []
    took: list[float] = []

    async def worker(name: str) -> None:
        for _ in range(500):
            order.append(name)
            await asyncio.sleep(0)

    async def both() -> None:
        timer.cancel()
        started = time.monotonic()
        other = asyncio.ensure_future(worker("b"))  # a plain asyncio task beside this callback
        await worker("a")  # in the callback's (or task's) own coroutine
        await other
        took.append(time.monotonic() - started)

    # rclpy 9 annotates timer callbacks as plain
    timer = node.create_timer(0.01 if where == "timer" else 3600.0, both)  # type: ignore[arg-type, unused-ignore]
    executor.add_node(node)
    if where == "task":
        executor.spin_until_future_complete(executor.create_task(both()), timeout_sec=30.0)
    else:
        deadline = time.monotonic() + 30.0
        while not took and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.5)
    assert took and took[0] < 2.0, took  # before: 10 s
    assert order[:6] == ["a", "b", "a", "b", "a", "b"], "each sleep(0) lets the other run"


@pytest.mark.parametrize("watched", [True, False], ids=["watched", "watched-after"])
def test_a_client_takes_its_response_behind_another_clients(
    executor: AsyncioExecutor, make_node: Callable[[str], Node], context: Context, watched: bool
) -> None:
    # Every client of a service reads every response on its reply topic; a
    # take of another client's response takes nothing. Two responses that
    # reached the second client's reader before the loop looked were
    # reported together, and the takes stopped at the first (the other
    # client's), leaving its own there with no callback to come. The same,
    # when the responses came before the executor first saw the clients.
    server = make_node("two_clients_server")
    sent = threading.Event()
    answered: list[int] = []

    def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        answered.append(1)
        if len(answered) == 2:
            after.trigger()  # its callback runs once this answer is sent
        response.message = "pong"
        return response

    server.create_service(Trigger, "two_clients", answer)
    after = server.create_guard_condition(sent.set)
    serving = SingleThreadedExecutor(context=context)
    serving.add_node(server)
    callers = make_node("two_clients_callers")
    first: Client[Any, Any]
    second: Client[Any, Any]
    first, second = (callers.create_client(Trigger, "two_clients") for _ in range(2))
    if watched:
        executor.add_node(callers)
        executor.spin_once(timeout_sec=0.1)  # the clients are watched from now on
    assert first.wait_for_service(timeout_sec=10.0) and second.wait_for_service(timeout_sec=10.0)
    futures: list[RclFuture[Any]] = [first.call_async(Trigger.Request()), second.call_async(Trigger.Request())]
    spinner = threading.Thread(target=serving.spin, daemon=True)
    spinner.start()
    try:
        # Both answered, and delivered in this process, while the loop is not spinning.
        assert sent.wait(10.0)
        if not watched:
            executor.add_node(callers)
        for future in futures:
            executor.spin_until_future_complete(future, timeout_sec=5.0)
        results = [future.result() if future.done() else None for future in futures]
        assert [result.message if result is not None else None for result in results] == ["pong", "pong"]
    finally:
        serving.shutdown(timeout_sec=5.0)
        spinner.join(5.0)


def test_async_service_callback_can_await(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    server_node, client_node = make_node("async_server"), make_node("async_client")

    async def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        await asyncio.sleep(0.05)
        response.success = True
        response.message = "slept"
        return response

    server_node.create_service(Trigger, "nap", answer)
    client: Client[Any, Any] = client_node.create_client(Trigger, "nap")
    executor.add_node(server_node)
    executor.add_node(client_node)
    thread = spin_in_thread(executor)
    try:
        assert client.wait_for_service(timeout_sec=10.0)
        response: Any = client.call(Trigger.Request(), timeout_sec=10.0)
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
    assert response is not None and response.message == "slept"


@pytest.mark.parametrize("kind", ["plain", "async"])
def test_exception_in_callback_is_reported_and_executor_survives(
    context: Context, make_node: Callable[[str], Node], kind: str
) -> None:
    reports: list[tuple[str, str]] = []
    executor = AsyncioExecutor(
        context=context,
        on_callback_error=lambda node, entity, exc: reports.append(
            (node.get_name(), str(exc))
        ),
    )
    faulty, healthy = make_node(f"faulty_{kind}"), make_node(f"healthy_{kind}")
    ticks = threading.Event()
    count = [0]

    def explode() -> None:
        raise RuntimeError("boom")

    async def explode_async() -> None:
        await asyncio.sleep(0)
        raise RuntimeError("boom")

    def tick() -> None:
        count[0] += 1
        if count[0] >= 10 and len(reports) >= 3:
            ticks.set()

    # rclpy 9 annotates timer callbacks as plain
    faulty.create_timer(0.02, explode if kind == "plain" else explode_async)  # type: ignore[arg-type, unused-ignore]
    healthy.create_timer(0.02, tick)
    executor.add_node(faulty)
    executor.add_node(healthy)
    thread = spin_in_thread(executor)
    try:
        assert ticks.wait(10.0)
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
    assert reports[0] == (f"faulty_{kind}", "boom")


def test_spin_until_future_complete_with_rclpy_future(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    node = make_node("future_setter")
    future: RclFuture[Any] = RclFuture()
    node.create_timer(0.05, lambda: future.set_result("done") if not future.done() else None)
    executor.add_node(node)
    executor.spin_until_future_complete(future, timeout_sec=10.0)
    assert future.result() == "done"


def test_spin_once_runs_one_callback(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    node = make_node("once")
    calls: list[int] = []
    node.create_timer(0.01, lambda: calls.append(1))
    executor.add_node(node)
    executor.spin_once(timeout_sec=10.0)
    assert calls


@pytest.mark.parametrize("late", [False, True], ids=["prompt", "late"])
def test_spin_once_looks_in_rcl_no_more_after_its_timeout(
    executor: AsyncioExecutor, make_node: Callable[[str], Node], monkeypatch: pytest.MonkeyPatch, late: bool
) -> None:
    """With nothing ready, a ``spin_once(timeout_sec=...)``'s last look in rcl
    is the wait its timeout ends, as in rclpy. The look a ``spin_once``
    owes was still owed after that wait (only a poll paid it), so one more
    rcl poll ran after the timeout: a timer due just then fired in a call
    that had already timed out (rclpy's ``test_zero_callback[0.001]``).

    ``late``: the loop comes back to select a while after each look in rcl
    (the while is cut to nothing here; under a sanitizer or on a loaded CI
    machine it passed 1 ms), so its selects that must not block look in rcl
    again: two polls followed the timed-out wait (CI saw ``[..., 0]``)."""
    if late:
        monkeypatch.setattr(_waitset, "_POLL_MAX_NS", 0)
    node = make_node("once_timeout")
    executor.add_node(node)
    executor.spin_once(timeout_sec=0)
    hot = executor._dispatcher._hot
    waits: list[int] = []
    wait_and_dispatch = hot.wait_and_dispatch

    def recorded(timeout_ns: int) -> int:
        waits.append(timeout_ns)
        return wait_and_dispatch(timeout_ns)

    monkeypatch.setattr(hot, "wait_and_dispatch", recorded)
    executor.spin_once(timeout_sec=0.05)
    assert waits and waits[-1] > 0, waits  # before: [..., 50 ms, 0]
    assert max(waits) <= 50_000_000, waits


def test_rclpy_spin_helpers_accept_it(context: Context, make_node: Callable[[str], Node]) -> None:
    executor = AsyncioExecutor(context=context)
    node = make_node("drop_in")
    future: RclFuture[Any] = RclFuture()
    node.create_timer(0.02, lambda: future.set_result(7) if not future.done() else None)
    rclpy.spin_until_future_complete(node, future, executor=executor, timeout_sec=10.0)
    assert future.result() == 7
    executor.shutdown(timeout_sec=5.0)


def test_spin_async_on_a_foreign_event_loop(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    node = make_node("foreign")
    pub = node.create_publisher(Int64, "foreign_topic", 10)
    got: list[int] = []

    async def main() -> None:
        received = asyncio.Event()

        async def on_message(msg: Int64) -> None:
            got.append(msg.data)
            received.set()

        node.create_subscription(Int64, "foreign_topic", on_message, 10)  # type: ignore[arg-type]
        executor.add_node(node)
        spinning = asyncio.ensure_future(executor.spin_async())
        for _ in range(200):
            pub.publish(Int64(data=5))
            try:
                await asyncio.wait_for(received.wait(), 0.05)
                break
            except TimeoutError:
                continue
        executor.shutdown(timeout_sec=5.0)
        await asyncio.wait_for(spinning, 10.0)

    asyncio.run(main())
    assert got and got[0] == 5


def test_spin_async_lends_a_foreign_loop_its_task_factory_while_it_spins(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    server_node, client_node = make_node("foreign_server"), make_node("foreign_client")

    client = slow_pong(server_node, client_node, "foreign_ping")
    factories: list[object] = []

    async def main() -> tuple[str, float]:
        loop = asyncio.get_running_loop()
        executor.add_node(server_node)
        executor.add_node(client_node)
        spinning = asyncio.ensure_future(executor.spin_async())
        await asyncio.sleep(0)  # it starts spinning
        while not client.service_is_ready():
            await asyncio.sleep(0.02)
        factories.append(loop.get_task_factory())

        async def call() -> tuple[str, float]:
            started = time.process_time()
            response = await client.call_async(Trigger.Request())
            return response.message, time.process_time() - started

        outcome = await asyncio.wait_for(loop.create_task(call()), 10.0)
        executor.shutdown(timeout_sec=5.0)
        await asyncio.wait_for(spinning, 10.0)
        factories.append(loop.get_task_factory())
        return outcome

    message, cpu = asyncio.run(main())
    assert message == "pong"
    assert cpu < 0.15, "the loop's own task spun a core while it waited"
    assert factories[0] is not None and factories[1] is None, "lent while spinning, given back after"


def test_spin_from_inside_a_running_loop_is_refused(executor: AsyncioExecutor) -> None:
    async def main() -> None:
        with pytest.raises(ExecutorError, match="spin_async"):
            executor.spin()

    asyncio.run(main())


def test_busy_subscription_keeps_its_qos_depth_of_newest_messages(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    node = make_node("slow_reader")
    pub = node.create_publisher(Int64, "burst", 100)
    received: list[int] = []
    first = threading.Event()
    release = threading.Event()
    last = threading.Event()

    def slow(msg: Int64) -> None:
        received.append(msg.data)
        first.set()
        release.wait(10.0)
        if msg.data == 49:
            last.set()

    node.create_subscription(Int64, "burst", slow, 5)
    executor.add_node(node)
    thread = spin_in_thread(executor)
    try:
        deadline = time.monotonic() + 10.0
        while not first.is_set() and time.monotonic() < deadline:
            pub.publish(Int64(data=-1))
            first.wait(0.05)
        assert first.is_set()
        for value in range(50):
            pub.publish(Int64(data=value))
        release.set()
        assert last.wait(10.0)
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
    after = [value for value in received if value >= 0]
    # While the first callback blocked, at most the QoS depth (5) waited.
    assert len(after) <= 5 + 1, after
    assert after[-1] == 49


def test_shutdown_leaves_no_thread_behind(
    context: Context, make_node: Callable[[str], Node]
) -> None:
    before = {t.ident for t in threading.enumerate()}
    executor = AsyncioExecutor(context=context)
    node = make_node("threads")
    ran = threading.Event()
    node.create_timer(0.01, ran.set)
    executor.add_node(node)
    thread = spin_in_thread(executor)
    assert ran.wait(10.0)
    assert executor.threads(), "a plain callback should have started a lane thread"
    assert executor.shutdown(timeout_sec=5.0)
    thread.join(5.0)
    leftover = [t for t in threading.enumerate() if t.ident not in before and t.is_alive()]
    assert leftover == []


def test_shutdown_joins_the_loops_default_thread_pool(context: Context) -> None:
    """A task's ``asyncio.to_thread`` starts a thread of the loop's default pool
    (the LiDAR plugin opens its port so); shutdown joins it, as ``asyncio.run``
    ends: a container that counts the threads it leaves found it still ending
    and exited 1 after a clean stop. Only told to end, the thread is gone a
    moment later in about half the tries: ten tries, each checked at once."""
    before = {t.ident for t in threading.enumerate()}

    async def job() -> int:
        return await asyncio.to_thread(threading.get_ident)

    for _ in range(10):
        executor = AsyncioExecutor(context=context)
        try:
            task = executor.create_task(job)
            executor.spin_until_future_complete(task, timeout_sec=10.0)
            assert task.result() not in before  # a thread of the pool, started here
        finally:
            assert executor.shutdown(timeout_sec=5.0)
        leftover = [t.name for t in threading.enumerate() if t.ident not in before and t.is_alive()]
        assert leftover == []


def test_removed_node_gets_no_more_callbacks_and_its_lane_ends(
    executor: AsyncioExecutor, make_node: Callable[[str], Node]
) -> None:
    node, other = make_node("removed"), make_node("kept")
    calls = [0]
    ran = threading.Event()
    other_ticks = threading.Event()

    def count() -> None:
        calls[0] += 1
        ran.set()

    node.create_timer(0.01, count)
    executor.add_node(node)
    executor.add_node(other)
    thread = spin_in_thread(executor)
    try:
        assert ran.wait(10.0)
        executor.remove_node(node)
        node.destroy_node()
        settled = calls[0]
        # Keep the executor busy long enough for a stray timer to show up.
        hits = [0]

        def tick() -> None:
            hits[0] += 1
            if hits[0] >= 10:
                other_ticks.set()

        other.create_timer(0.01, tick)
        assert other_ticks.wait(10.0)
        assert calls[0] <= settled + 1
        assert all("/removed" not in t.name for t in executor.threads())
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)


def test_program_that_forgets_shutdown_still_exits_cleanly(tmp_path: Path) -> None:
    """A waiter thread left in rcl_wait at exit would abort the process (exit 134)."""
    script = tmp_path / "forgetful.py"
    script.write_text(
        "import rclpy\n"
        "from rclpy.node import Node\n"
        "from container import AsyncioExecutor\n"
        "rclpy.init()\n"
        "executor = AsyncioExecutor()\n"
        "executor.add_node(Node('forgetful'))\n"
        "executor.spin_once(timeout_sec=0.1)\n"
        "print('done', flush=True)\n",
        encoding="utf-8",
    )
    result = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=60, check=False
    )
    assert (result.returncode, result.stdout) == (0, "done\n"), result.stderr[-2000:]


@pytest.mark.parametrize("path", ["compiled", "rclpy"])
@pytest.mark.parametrize("style", ["plain", "async"])
def test_an_answer_the_client_cannot_receive_yet_is_sent_again(
    style: str, path: str, host: Callable[..., Any], executor: AsyncioExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Fast DDS fails a response to a client the service has not matched yet
    ("client will not receive response"): the caller got no answer, ever.

    The first two sends find the client unmatched: the compiled send says so
    (as it does when rmw times out; the next test has a client that never
    matches), or, for a service the compiled path cannot serve, rclpy's
    ``send_response`` raises rmw's error."""
    from container.executor import _answers, _waitset

    server, caller = host(Node, f"respond_server_{style}"), host(Node, f"respond_caller_{style}")

    def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = True, "late but there"
        return response

    async def answer_async(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return answer(request, response)

    service = server.create_service(Trigger, f"respond_{style}", answer_async if style == "async" else answer)
    refusals = [2]
    if path == "compiled":
        sent = _answers._sent

        def not_matched_yet(*args: Any, **kwargs: Any) -> bool:
            if refusals[0] > 0:
                refusals[0] -= 1
                return False
            return sent(*args, **kwargs)

        monkeypatch.setattr(_answers, "_sent", not_matched_yet)
    else:
        monkeypatch.setattr(_waitset, "_server", lambda service: None)
        send = service.send_response

        def refuse(response: Any, header: Any) -> None:
            if refusals[0] > 0:
                refusals[0] -= 1
                raise _compat.RCLError("Failed to send response: client will not receive response")
            send(response, header)

        service.send_response = refuse  # type: ignore[method-assign, unused-ignore]  # rclpy 9 types it
    client: Client[Any, Any] = caller.create_client(Trigger, f"respond_{style}")
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(Trigger.Request())
    executor.spin_until_future_complete(future, timeout_sec=10.0)
    assert future.done() and refusals == [0]
    result = future.result()
    assert result is not None and result.message == "late but there"


@pytest.mark.parametrize("style", ["plain", "async"])
def test_services_and_clients_the_compiled_takes_cannot_serve_are_served_by_rclpys(
    style: str, host: Callable[..., Any], executor: AsyncioExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """rclpy's takes and ``send_response`` where no compiled ``Server`` or ``Caller`` could be made."""
    from container.executor import _waitset

    monkeypatch.setattr(_waitset, "_server", lambda service: None)
    monkeypatch.setattr(_waitset, "_caller", lambda client: None)
    server, caller = host(Node, f"rclpy_takes_server_{style}"), host(Node, f"rclpy_takes_caller_{style}")
    served: list[bool] = []

    def answer(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        served.append(request.data)
        response.success, response.message = request.data, f"call {len(served)}"
        return response

    async def answer_async(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        return answer(request, response)

    server.create_service(SetBool, f"rclpy_takes_{style}", answer_async if style == "async" else answer)
    client: Client[Any, Any] = caller.create_client(SetBool, f"rclpy_takes_{style}")
    assert client.wait_for_service(timeout_sec=10.0)
    futures = [client.call_async(SetBool.Request(data=index % 2 == 0)) for index in range(5)]
    for future in futures:
        executor.spin_until_future_complete(future, timeout_sec=10.0)
    results = [future.result() for future in futures]
    assert [(result.success if result else None) for result in results] == [True, False, True, False, True]
    assert sorted(result.message for result in results if result) == [f"call {n}" for n in range(1, 6)]


@compiled_only("GIL let go while rmw waits for an unmatched client (Server.send's let_go)")
def test_retrying_an_answer_its_client_cannot_match_holds_up_no_other_thread(
    executor: AsyncioExecutor,
    make_node: Callable[[str], Node],
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each retry waits 100 ms in rmw for the client's response reader: without
    the GIL, so a peer asking for answers it can never match (a transient-local
    client) stalls no other thread of the container meanwhile."""
    from container.executor import _answers

    monkeypatch.setattr(_answers, "RETRY_S", 1.0)
    retries: list[tuple[float, float]] = []
    sent = _answers._sent

    def timed(*args: Any, **kwargs: Any) -> bool:
        started = time.perf_counter()
        try:
            return sent(*args, **kwargs)
        finally:
            if threading.current_thread().name == "respond-again":  # the resender's
                retries.append((started, time.perf_counter()))

    monkeypatch.setattr(_answers, "_sent", timed)
    server, callers = make_node("stall_server"), make_node("stall_callers")
    served = threading.Event()
    def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        served.set()
        return response

    server.create_service(Trigger, "stall", answer)
    unmatched: Client[Any, Any] = callers.create_client(
        Trigger, "stall", qos_profile=QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    )
    good: Client[Any, Any] = callers.create_client(Trigger, "stall")  # the one wait_for_service can see
    executor.add_node(server)
    executor.add_node(callers)
    ticks: list[float] = []
    stop = threading.Event()

    def tick() -> None:
        while not stop.is_set():
            ticks.append(time.perf_counter())
            stop.wait(0.002)

    ticker = threading.Thread(target=tick, daemon=True)
    thread = spin_in_thread(executor)
    try:
        assert good.wait_for_service(timeout_sec=10.0)
        with caplog.at_level(logging.WARNING, logger=_answers.__name__):
            ticker.start()
            unmatched.call_async(Trigger.Request())
            assert served.wait(10.0)
            deadline = time.monotonic() + 10.0
            while "did not match" not in caplog.text and time.monotonic() < deadline:
                served.wait(0.05)  # a poll of the log, not a pause the test relies on
        assert "did not match" in caplog.text, caplog.text
    finally:
        stop.set()
        ticker.join(5.0)
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
    blocked = [(start, end) for start, end in retries if end - start >= 0.09]
    assert len(blocked) >= 3, retries  # rmw did wait for the client, each time
    # The ticker (a 2 ms period) ran during each 100 ms wait: with the GIL held
    # through the wait it could tick in none of them. A loaded machine may
    # leave the ticker unscheduled through one wait; not through most.
    ticked = [sum(start <= t <= end for t in ticks) for start, end in blocked]
    assert sum(n >= 5 for n in ticked) > len(blocked) // 2, f"ticks during each of {len(blocked)} retries: {ticked}"


def test_an_answer_its_client_cannot_match_is_retried_off_the_loop_then_dropped(
    executor: AsyncioExecutor,
    make_node: Callable[[str], Node],
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A client whose response reader never matches (it asks for transient-local answers).

    rmw blocks 100 ms and gives up on each try ("client will not receive
    response", a warning rclpy raises from C++); the executor sends the answer
    again from its resender thread until the (here shortened) deadline, says
    so once, and meanwhile answers a well-formed client at once. The same
    path answers a client that has not been matched *yet*, right after
    ``wait_for_service``.
    """
    from container.executor import _answers

    monkeypatch.setattr(_answers, "RETRY_S", 0.5)
    server, callers = make_node("answers_server"), make_node("answers_callers")
    served = threading.Event()

    def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        served.set()
        response.success = True
        return response

    server.create_service(Trigger, "answers", answer)
    unmatched: Client[Any, Any] = callers.create_client(
        Trigger, "answers", qos_profile=QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    )
    good: Client[Any, Any] = callers.create_client(Trigger, "answers")
    executor.add_node(server)
    executor.add_node(callers)
    thread = spin_in_thread(executor)
    try:
        assert good.wait_for_service(timeout_sec=10.0)
        with caplog.at_level(logging.WARNING, logger=_answers.__name__):
            lost = unmatched.call_async(Trigger.Request())
            assert served.wait(10.0)
            response: Any = good.call(Trigger.Request(), timeout_sec=5.0)
            assert response is not None and response.success
            deadline = time.monotonic() + 10.0
            while "did not match" not in caplog.text and time.monotonic() < deadline:
                served.wait(0.05)  # a poll of the log, not a pause the test relies on
        assert "service answers: client " in caplog.text and "did not match" in caplog.text, caplog.text
        assert not lost.done()
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)


@pytest.mark.parametrize("started_by", ["executor.create_task", "asyncio.create_task"])
def test_a_task_whose_caller_let_go_of_it_is_not_collected_while_it_waits(
    executor: AsyncioExecutor, started_by: str
) -> None:
    """rclpy's executors hold the tasks they run: ``executor.create_task(coro)`` runs to its end
    whether or not its caller keeps what it returns. A task waiting on a future that only the
    task holds (a client's ``asyncio.open_connection``: its protocol holds the stream reader
    weakly) is a cycle nothing else reaches; a garbage collection then closed it mid-await."""
    held: list[Any] = []
    finished = threading.Event()

    async def waits() -> None:
        future = asyncio.get_running_loop().create_future()
        held.append(weakref.ref(future))
        await future
        finished.set()

    async def starts() -> None:
        if started_by == "asyncio.create_task":
            asyncio.get_running_loop().create_task(waits())  # not kept, as a plugin might
        else:
            executor.create_task(waits())

    thread = spin_in_thread(executor)
    executor.create_task(starts())
    deadline = time.monotonic() + 5.0
    while not held and time.monotonic() < deadline:
        time.sleep(0.01)
    assert held, "the task never started"
    for _ in range(3):
        gc.collect()
    future = held[0]()
    assert future is not None, "the waiting task and its future were collected"
    executor.loop.call_soon_threadsafe(future.set_result, None)
    del future
    assert finished.wait(5.0), "the task did not run to its end"
    executor.shutdown()
    thread.join(5.0)
