"""Every hot path of the executor, run thousands of times, leaves nothing behind.

A reference the compiled path (``container/executor/fastpath/``) forgets to
give back leaks the object, and whatever it holds, once per callback. So
each path runs :data:`WARM_UP` times (caches, free lists and lazily made
objects settle), then :data:`ITERATIONS` times between two censuses of the
process, which must agree within bounds that a leak of one object per
iteration exceeds several times over:

- the objects the garbage collector tracks, counted by type (a leaked
  message, work item, tuple, dict or coroutine is one of them);
- the memory Python allocated meanwhile and still holds, traced by
  ``tracemalloc`` (objects the collector does not track, too: a leaked int,
  bytes or str);
- the memory the C allocator has handed out and not got back (glibc's
  count, or AddressSanitizer's under the sanitizer run): a rosidl message
  made in C and never destroyed, an array never freed;
- the reference counts of the long-lived objects the path touches (nodes,
  entities, handles, callbacks, the message types, whose instances each
  hold a reference, and the compiled routes, takers, servers and callers):
  a missing ``Py_DECREF`` on one of those frees nothing and allocates
  nothing.

What none of these sees: a reference leaked on an immortal object (None,
True, small ints: CPython 3.12 does not count those). The sanitizer check
(``.ci/sanitize``) runs these tests too, under AddressSanitizer.

The executor runs in the test's thread (``spin_until_future_complete`` of a
driver coroutine), and each batch ends once no callback runs: nothing
changes while a census is taken.
"""

from __future__ import annotations

import asyncio
import ctypes
import functools
import gc
import socket
import sys
import threading
import time
import tracemalloc
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from rclpy.context import Context
from rclpy.node import Node
from std_msgs.msg import Int64
from std_srvs.srv import SetBool

from container import AsyncioExecutor, enable_intra_process, hand_over
from container.executor._engine import Route
from container.intra import IntraProcessNode
from tests.engine_support import ENGINE
from tests.waiting import wait_until

#: Runs of a path before the first census. After 300, the first census
#: after them still found up to 50 kB more allocated under the sanitizer
#: run (service calls; caches filling up, as much after 10,000 runs as
#: after 2,000); after 2,000, 3-5 kB.
WARM_UP = 2000
#: Runs of a path between the two censuses.
ITERATIONS = 5000
#: Live objects of any one type, and of all types together, the runs may
#: add. Measured here: 0-1 (the last message handed over, kept by the test);
#: after a shorter warm-up, up to 72 where plain callbacks run (worker
#: threads started meanwhile). One leaked per run adds ITERATIONS.
OBJECTS_BOUND = ITERATIONS // 20
#: Bytes of Python memory the runs may add. Measured here: -0.5 to +18 kB
#: (up to +6 kB under the sanitizer run), however many runs: nothing grows. One
#: leaked int (28 bytes) per run adds 140 kB, a leaked Int64 message 400 kB.
TRACED_BOUND = 16 * ITERATIONS
#: Bytes of C memory the runs may add. Measured here: +0.4 to +61 kB, as
#: much after 20,000 runs as after 5,000 (allocator and DDS caches); +1 to
#: +35 kB under the sanitizer run. A SetBool response's rosidl message
#: leaked per service call (Server.send without its destroy) added 430 kB
#: here (glibc counts its chunks: 88 bytes) and 165 kB under the sanitizer
#: run (which counts the bytes asked for: 33).
C_BOUND = 20 * ITERATIONS
#: How far a long-lived object's reference count may move. Measured here:
#: 0-1; after a shorter warm-up, up to 3 where plain callbacks run (the
#: work each worker thread keeps until its next). One reference leaked per
#: run moves it by ITERATIONS.
REFCOUNT_BOUND = 10
#: Tasks made at once by the task path.
TASKS_AT_ONCE = 50
#: Seconds one batch of runs may take (the sanitizer run is several times slower).
RUN_TIMEOUT = 40.0


@dataclass(frozen=True)
class Census:
    """What the process holds at one moment."""

    objects: Counter[str]
    refcounts: dict[str, int]


def _type_name(obj: object) -> str:
    kind = type(obj)
    return f"{kind.__module__}.{kind.__qualname__}"


def _census(watched: dict[str, object]) -> Census:
    gc.collect()
    objects = Counter(_type_name(obj) for obj in gc.get_objects())
    # getrefcount's own argument, and the dict's value, counted alike each time.
    return Census(objects, {name: sys.getrefcount(obj) for name, obj in watched.items()})


class _MallInfo2(ctypes.Structure):
    """glibc's ``struct mallinfo2``."""

    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost",
        )
    ]  # fmt: skip


def _c_allocator() -> Callable[[], int]:
    """How many bytes the C allocator has handed out and not got back.

    AddressSanitizer's own count where its runtime is loaded (it replaces
    malloc: glibc's arenas then hold nothing); glibc's (``mallinfo2``, all
    arenas) otherwise.
    """
    process = ctypes.CDLL(None)
    asan = getattr(process, "__sanitizer_get_current_allocated_bytes", None)
    if asan is not None:
        asan.restype = ctypes.c_size_t
        return lambda: int(asan())
    mallinfo2 = process.mallinfo2
    mallinfo2.restype = _MallInfo2
    return lambda: int(mallinfo2().uordblks)


_c_allocated = _c_allocator()


def _assert_flat(path: str, before: Census, after: Census, traced: int, c_allocated: int) -> None:
    # The first census is alive during the second: its two objects are not the runs'.
    grown = after.objects - before.objects - Counter({_type_name(before): 1, _type_name(before.objects): 1})
    total = sum(after.objects.values()) - sum(before.objects.values()) - 2
    top = ", ".join(f"{name} +{count}" for name, count in grown.most_common(6))
    moved = {name: after.refcounts[name] - count for name, count in before.refcounts.items()}
    moved = {name: change for name, change in moved.items() if change}
    report = (
        f"{path}, {ITERATIONS} runs: {total:+} objects ({top or 'no type grew'}), {traced:+} bytes traced, "
        f"{c_allocated:+} bytes of C memory, references moved: {moved or 'none'}"
    )
    print(report)
    assert not [name for name, count in grown.items() if count > OBJECTS_BOUND], report
    assert total <= OBJECTS_BOUND, report
    assert traced <= TRACED_BOUND, report
    assert c_allocated <= C_BOUND, report
    assert all(abs(change) <= REFCOUNT_BOUND for change in moved.values()), report


def _check(path: str, run: Callable[[int], None], watched: dict[str, object]) -> None:
    """Run ``path`` WARM_UP times, then ITERATIONS times between two censuses.

    ``tracemalloc`` traces the warm-up too: what fills free lists and caches
    then is traced before the first census, and the difference is what the
    measured runs left allocated.
    """
    tracemalloc.start()
    try:
        run(WARM_UP)
        _census(watched)  # the first census of a process makes a few objects of its own
        before = _census(watched)
        traced, c_allocated = tracemalloc.get_traced_memory()[0], _c_allocated()
        run(ITERATIONS)
        gc.collect()
        traced, c_allocated = tracemalloc.get_traced_memory()[0] - traced, _c_allocated() - c_allocated
    finally:
        tracemalloc.stop()
    _assert_flat(path, before, _census(watched), traced, c_allocated)


@pytest.fixture(autouse=True)
def _no_tracemalloc() -> Iterator[None]:
    """tracemalloc is this module's alone: started by :func:`_check`, never left on."""
    assert not tracemalloc.is_tracing()
    yield
    assert not tracemalloc.is_tracing()


# -- driving the executor --------------------------------------------------------------


def _drive(executor: AsyncioExecutor, start: Callable[[asyncio.Future[None]], None]) -> None:
    """Spin ``executor`` in this thread until what ``start(done)`` set going sets ``done``."""

    async def driver() -> None:
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        start(done)
        await asyncio.wait_for(done, RUN_TIMEOUT)

    executor.spin_until_future_complete(driver(), timeout_sec=RUN_TIMEOUT + 5)


def _finish(executor: AsyncioExecutor, done: asyncio.Future[None]) -> None:
    """Set ``done`` from any thread."""

    def finish() -> None:
        if not done.done():
            done.set_result(None)

    executor.loop.call_soon_threadsafe(finish)


def _quiesce(executor: AsyncioExecutor, nodes: Iterable[Node]) -> None:
    """Spin until no callback of ``nodes`` runs (a plain one may still be
    returning on its worker thread when the last run of a batch is done),
    then long enough for the loop's polls of rclpy futures (a timer each,
    10 ms) to have fired."""
    deadline = time.monotonic() + RUN_TIMEOUT
    while any(executor._dispatcher.running(node) for node in nodes):
        assert time.monotonic() < deadline, "callbacks still running"
        executor.spin_once(timeout_sec=0.001)
    executor.spin_until_future_complete(asyncio.sleep(0.03))


def _spun_once(executor: AsyncioExecutor) -> None:
    """Let the executor take its nodes in (its wait set is rebuilt on its next spin)."""
    executor.spin_once(timeout_sec=0.05)


def _matched(executor: AsyncioExecutor, publishers: Iterable[Any]) -> None:
    for publisher in publishers:
        wait_until(functools.partial(_has_subscription, publisher), "a subscription", executor=executor)


def _has_subscription(publisher: Any) -> bool:
    return bool(publisher.get_subscription_count() >= 1)


def _expressed(executor: AsyncioExecutor) -> int:
    """How many callbacks the compiled chain (Express) ran so far."""
    express = executor._dispatcher._hot._express
    assert express is not None, "no compiled chain"
    return express.expressed


# -- what each path holds ----------------------------------------------------------------


def _entity_refs(name: str, entity: Any) -> dict[str, object]:
    return {name: entity, f"{name}.handle": entity.handle, f"{name}.callback": entity.callback}


def _compiled_refs(executor: AsyncioExecutor, name: str, entity: Any, node: Node, kind: str) -> dict[str, object]:
    """The compiled object that takes for ``entity`` (it must have one); none on the
    Python engine, whose entities are waited on and taken by rclpy (docs/executor/engines.md)."""
    entry = executor._dispatcher.entry(entity, node, kind)
    part = {"subscription": "taker", "service": "server", "client": "caller"}[kind]
    compiled = getattr(entry, part)
    if ENGINE == "python" and kind == "subscription":
        assert compiled is None, f"{name} has a taker on the Python engine"
        return {}
    assert compiled is not None, f"{name} has no compiled {part}"
    return {f"{name}.{part}": compiled}


def _route_refs(executor: AsyncioExecutor) -> dict[str, object]:
    """The compiled routes of the executor's hot wait set, and what each holds."""
    routes = executor._dispatcher._hot.routes
    refs: dict[str, object] = {}
    for kind, table in (("subscription", routes.subscriptions), ("timer", routes.timers)):
        for address, route in table.items():
            assert isinstance(route, Route)
            refs[f"route {kind} {address:#x}"] = route
            for part in ("first", "entry", "lane", "slots", "marker", "token"):
                refs[f"route {kind} {address:#x}.{part}"] = getattr(route, part)
    return refs


# -- the paths ------------------------------------------------------------------------------


def _ping_pong(
    executor: AsyncioExecutor, host: Callable[..., Any], name: str, *, callback: str, intra: bool = False
) -> tuple[Callable[[int], None], dict[str, object], list[int]]:
    """A message bounced between two nodes, ``n`` round trips a run.

    :param callback: ``plain`` (worker threads), ``async`` (its first step on
        the loop: the compiled chain, where the subscription has a route) or
        ``suspending`` (an ``async def`` that awaits once: its runner task
        steps it again).
    :param intra: the nodes hand the messages over in process
        (:func:`~container.hand_over`); the list returned counts the
        messages received that were not the very object handed over.
    """
    a, b = host(Node, f"{name}_a"), host(Node, f"{name}_b")
    if intra:
        enable_intra_process(a)
        enable_intra_process(b)
    ping = a.create_publisher(Int64, f"{name}_ping", 10)
    pong = b.create_publisher(Int64, f"{name}_pong", 10)
    left = [0]
    sent: list[Int64] = []
    copies = [0]
    done: list[asyncio.Future[None]] = []

    def send(publisher: Any, message: Int64) -> None:
        if intra:
            sent[:] = [message]
            hand_over(publisher, message)
        else:
            publisher.publish(message)

    def echo(msg: Int64) -> None:
        send(pong, msg)

    def got(msg: Int64) -> None:
        if intra and msg is not sent[0]:
            copies[0] += 1
        left[0] -= 1
        if left[0] <= 0:
            _finish(executor, done[-1])
        else:
            send(ping, Int64(data=left[0]))

    async def echo_async(msg: Int64) -> None:
        echo(msg)

    async def got_async(msg: Int64) -> None:
        got(msg)

    async def echo_suspending(msg: Int64) -> None:
        await asyncio.sleep(0)
        echo(msg)

    echoes = {"plain": echo, "async": echo_async, "suspending": echo_suspending}
    gots = {"plain": got, "async": got_async, "suspending": got_async}
    sub_b = b.create_subscription(Int64, f"{name}_ping", echoes[callback], 10)
    sub_a = a.create_subscription(Int64, f"{name}_pong", gots[callback], 10)
    _spun_once(executor)
    _matched(executor, (ping, pong))

    def run(n: int) -> None:
        def start(future: asyncio.Future[None]) -> None:
            done.append(future)
            left[0] = n
            send(ping, Int64(data=n))

        _drive(executor, start)
        done.clear()
        _quiesce(executor, (a, b))

    watched = {
        "node a": a, "node b": b, "Int64": Int64, "ping": ping, "pong": pong,
        **_entity_refs("subscription b", sub_b), **_entity_refs("subscription a", sub_a),
        **_route_refs(executor),
    }  # fmt: skip
    if not intra:
        watched.update(_compiled_refs(executor, "subscription b", sub_b, b, "subscription"))
        watched.update(_compiled_refs(executor, "subscription a", sub_a, a, "subscription"))
    return run, watched, copies


@pytest.mark.parametrize("callback", ["async", "plain", "suspending"])
def test_a_message_taken_leaves_nothing_behind(
    callback: str, executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    """``async``: taken and run by the compiled chain (Express, Taker); ``plain``:
    taken in C (Taker), run on a worker thread, which carries on with what
    it published; ``suspending``: its first step on the chain, the rest
    stepped by its lane's runner task. On the Python engine, every message is
    waited on and taken by rclpy, and the chain runs none of them."""
    run, watched, _ = _ping_pong(executor, host, f"leak_{callback}", callback=callback)
    expressed = _expressed(executor)
    _check(f"message ({callback})", run, watched)
    ran = _expressed(executor) - expressed
    if ENGINE == "python":
        assert ran == 0, ran
        return
    # Two callbacks a round trip: the chain ran at least half of those it could.
    assert ran >= {"async": ITERATIONS, "suspending": ITERATIONS // 2, "plain": 0}[callback], ran


def test_an_intra_process_hand_over_leaves_nothing_behind(executor: AsyncioExecutor, host: Callable[..., Any]) -> None:
    run, watched, copies = _ping_pong(executor, host, "leak_intra", callback="async", intra=True)
    assert isinstance(watched["node a"], IntraProcessNode)
    _check("intra-process hand-over", run, watched)
    assert copies == [0], "messages came through DDS, not handed over"


@pytest.mark.parametrize("style", ["async", "plain"])
def test_a_timer_firing_leaves_nothing_behind(style: str, executor: AsyncioExecutor, host: Callable[..., Any]) -> None:
    """``async``: called and run by the compiled chain (call_timers, run_fired); ``plain``: on a worker thread."""
    node = host(Node, f"leak_timer_{style}")
    left = [0]
    done: list[asyncio.Future[None]] = []

    def tick() -> None:
        left[0] -= 1
        if left[0] == 0:
            timer.cancel()
            _finish(executor, done[-1])

    async def tick_async() -> None:
        tick()

    timer = node.create_timer(0.0002, tick_async if style == "async" else tick)
    timer.cancel()
    _spun_once(executor)

    def run(n: int) -> None:
        def start(future: asyncio.Future[None]) -> None:
            done.append(future)
            left[0] = n
            timer.reset()

        _drive(executor, start)
        done.clear()
        _quiesce(executor, (node,))

    expressed = _expressed(executor)
    _check(f"timer ({style})", run, {"node": node, **_entity_refs("timer", timer), **_route_refs(executor)})
    ran = _expressed(executor) - expressed
    assert ran >= (ITERATIONS if style == "async" else 0), ran


@pytest.mark.parametrize("style", ["async", "plain"])
def test_a_service_call_leaves_nothing_behind(style: str, executor: AsyncioExecutor, host: Callable[..., Any]) -> None:
    """A request taken and answered in C (Server), its response taken in C (Caller), one call after another."""
    server, caller = host(Node, f"leak_server_{style}"), host(Node, f"leak_caller_{style}")

    def answer(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        response.success = request.data
        return response

    async def answer_async(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        return answer(request, response)

    service = server.create_service(SetBool, f"leak_service_{style}", answer_async if style == "async" else answer)
    client = caller.create_client(SetBool, f"leak_service_{style}")
    _spun_once(executor)
    wait_until(client.service_is_ready, "the service", executor=executor)

    def run(n: int) -> None:
        async def calls() -> None:
            for index in range(n):
                response = await client.call_async(SetBool.Request(data=index % 2 == 0))
                assert response.success == (index % 2 == 0)

        executor.spin_until_future_complete(calls(), timeout_sec=RUN_TIMEOUT)
        _quiesce(executor, (server, caller))

    watched = {
        "server": server, "caller": caller, "SetBool.Request": SetBool.Request, "SetBool.Response": SetBool.Response,
        **_entity_refs("service", service), "client": client, "client.handle": client.handle,
        **_compiled_refs(executor, "service", service, server, "service"),
        **_compiled_refs(executor, "client", client, caller, "client"),
    }  # fmt: skip
    _check(f"service call ({style})", run, watched)


def test_a_task_step_leaves_nothing_behind(executor: AsyncioExecutor, host: Callable[..., Any]) -> None:
    """Tasks of create_task, each stepped twice (it awaits once), their rclpy futures completed."""
    host(Node, "leak_tasks")
    _spun_once(executor)

    async def step(index: int) -> int:
        await asyncio.sleep(0)
        return index

    def run(n: int) -> None:
        async def tasks() -> None:
            # TASKS_AT_ONCE made, then awaited: awaiting each as it is made
            # waits for the loop's 10 ms poll of rclpy futures every time. A
            # fixed number: the executor's tables grow to the most tasks at
            # once, and dicts keep their size.
            for first in range(0, n, TASKS_AT_ONCE):
                futures = [executor.create_task(step(index)) for index in range(first, min(n, first + TASKS_AT_ONCE))]
                for index, future in enumerate(futures, first):
                    assert await future == index

        executor.spin_until_future_complete(tasks(), timeout_sec=RUN_TIMEOUT)
        _quiesce(executor, ())

    _check("task step", run, {"executor": executor})


def test_a_nodes_loop_work_leaves_nothing_behind(executor: AsyncioExecutor, host: Callable[..., Any]) -> None:
    """A node's loop work, each metered as its (``_loop``, ``HandleMeter``): a loop callback, a
    timer, a task of two steps and a reader's run, per round."""
    host(Node, "leak_loop")
    _spun_once(executor)
    accounting = executor.accounting
    assert accounting is not None
    ours, theirs = socket.socketpair()
    ours.setblocking(False)

    def run(n: int) -> None:
        async def work() -> None:
            loop = asyncio.get_running_loop()
            with accounting.working_as("/leak_loop"):
                for _ in range(n):
                    read: asyncio.Future[None] = loop.create_future()

                    def on_readable(read: asyncio.Future[None] = read) -> None:
                        ours.recv(16)
                        if not read.done():
                            read.set_result(None)

                    timer: asyncio.Future[None] = loop.create_future()
                    loop.call_soon(len, ())
                    loop.call_later(0, timer.set_result, None)
                    loop.add_reader(ours.fileno(), on_readable)
                    theirs.send(b"x")
                    await loop.create_task(asyncio.sleep(0))
                    await timer
                    await read
                    loop.remove_reader(ours.fileno())

        executor.spin_until_future_complete(work(), timeout_sec=RUN_TIMEOUT)
        _quiesce(executor, ())

    owner = accounting.owner_named("/leak_loop")
    try:
        watched: dict[str, object] = {"executor": executor, "loop": executor.loop, "owner": owner}
        run(1)
        watched |= {f"{account.kind} meter": account.meter for account in owner.accounts()}
        _check("a node's loop work", run, watched)
    finally:
        ours.close()
        theirs.close()


def test_a_node_added_and_removed_leaves_nothing_behind(
    context: Context, executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    """The wait set rebuilt twice a run: the node's entities watched and
    unwatched, its route and compiled wait set made and dropped."""
    talker = host(Node, "leak_talker")
    pub = talker.create_publisher(Int64, "leak_added", 10)
    node = Node("leak_added", context=context)
    received = threading.Event()

    async def heard(msg: Int64) -> None:
        received.set()

    sub = node.create_subscription(Int64, "leak_added", heard, 10)  # type: ignore[arg-type]  # rclpy types only plain callbacks
    timer = node.create_timer(3600.0, lambda: None)

    def rebuilt() -> None:
        hot = executor._dispatcher._hot
        while hot.dirty:
            executor.spin_once(timeout_sec=0)

    def run(n: int) -> None:
        for _ in range(n):
            executor.add_node(node)
            rebuilt()
            executor.remove_node(node)
            rebuilt()

    try:
        # One message through first: what taking it makes is made before the census.
        executor.add_node(node)
        _matched(executor, (pub,))
        pub.publish(Int64(data=1))
        wait_until(received.is_set, "the message", executor=executor)
        executor.remove_node(node)
        watched = {"node": node, "Int64": Int64, **_entity_refs("subscription", sub), **_entity_refs("timer", timer)}
        _check("node added and removed", run, watched)
    finally:
        executor.remove_node(node)
        node.destroy_node()
