"""Everything a node runs is credited to it, checked against what it really burned.

Nodes burn a known amount of their thread's CPU (``burn``: CPU time, not
wall time, so a loaded machine changes nothing) in each place work can run:
a callback, an asyncio task the node started, a file descriptor's callback
(``add_reader``, a transport's protocol), a thread it started; started from
plain callbacks and from ``async def`` ones. Each window must credit each
node what it burned (within 20%), an idle node next to nothing, and the
nodes, the executor and the unattributed kinds together what the process
spent, as ``/proc`` says (within 10%).
"""

from __future__ import annotations

import asyncio
import os
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from rclpy.context import Context
from rclpy.node import Node

from container import AsyncioExecutor
from container.executor import ContainerLoad, NodeLoad
from container.executor._owners import SEES_THREAD_STARTS
from tests.component_support import burn
from tests.waiting import wait_until

pytestmark = pytest.mark.timeout(60)

#: Each burning node burns this much CPU every period: 0.2 of a core.
BURN_S = 0.010
PERIOD_S = 0.050
#: Burns per node in the measured window.
BURNS = 30

PLACES = ("callback", "task", "reader", "thread")
STYLES = ("plain", "async")


class Burns:
    """What one node burned, each burn with when it ended (the accounting credits a step when it ends)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._burns: list[tuple[float, float]] = []

    def burn(self) -> None:
        start = time.thread_time()
        burn(BURN_S)
        spent = time.thread_time() - start
        with self._lock:
            self._burns.append((time.monotonic(), spent))

    def count(self) -> int:
        with self._lock:
            return len(self._burns)

    def between(self, start: float, end: float) -> float:
        with self._lock:
            return sum(spent for at, spent in self._burns if start < at <= end)


class _Stop:
    """Ends what a test started outside the executor (threads, sockets), once it is over."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self._closers: list[Callable[[], object]] = []
        self._kept: list[object] = []

    def later(self, close: Callable[[], object]) -> None:
        self._closers.append(close)

    def keep(self, task: object) -> None:
        """Hold a task the test started (the loop holds its tasks weakly)."""
        self._kept.append(task)

    def close(self) -> None:
        self.event.set()
        for close in reversed(self._closers):
            close()


@pytest.fixture
def stop() -> Iterator[_Stop]:
    stopping = _Stop()
    yield stopping
    stopping.close()


def _once(start: Callable[[], object]) -> Callable[[], bool]:
    """True the first time only: a callback that starts something starts it once."""
    started: list[object] = []

    def first() -> bool:
        if started:
            return False
        started.append(start)
        return True

    return first


def _on_loop(executor: AsyncioExecutor, call: Callable[[], object]) -> None:
    """Run ``call`` on the spinning executor's loop, and wait for it (a test's clean-up)."""

    async def run() -> None:
        call()

    asyncio.run_coroutine_threadsafe(run(), executor.loop).result(5.0)


def burning_node(
    host: Callable[..., Any], executor: AsyncioExecutor, stop: _Stop, place: str, style: str, name: str
) -> Burns:
    """A node that burns ``BURN_S`` every ``PERIOD_S`` in ``place``, set going from a ``style`` callback."""
    node: Node = host(Node, name)
    burns = Burns()
    first = _once(lambda: None)

    def on_timer() -> None:
        burns.burn()

    async def loop_task() -> None:
        while True:
            burns.burn()
            await asyncio.sleep(PERIOD_S)

    ours, feeder = socket.socketpair()
    ours.setblocking(False)
    stop.later(ours.close)
    stop.later(feeder.close)

    def feed() -> None:  # the test's own thread: another process's writes, as it were
        while not stop.event.wait(PERIOD_S):
            try:
                feeder.send(b"x")
            except OSError:
                return

    class Reading(asyncio.Protocol):
        def data_received(self, data: bytes) -> None:
            burns.burn()

    def on_readable() -> None:
        try:
            ours.recv(64)
        except BlockingIOError:
            return
        burns.burn()

    async def connect() -> None:
        transport, _ = await asyncio.get_running_loop().connect_accepted_socket(Reading, ours)
        stop.later(lambda: _on_loop(executor, transport.close))

    def in_thread() -> None:
        while not stop.event.wait(PERIOD_S - BURN_S):
            burns.burn()

    if place == "callback":
        if style == "plain":
            node.create_timer(PERIOD_S, on_timer)
        else:

            async def on_timer_async() -> None:
                on_timer()

            node.create_timer(PERIOD_S, on_timer_async)  # type: ignore[arg-type, unused-ignore]
        return burns

    def start_plain() -> None:
        """From a plain callback, on a worker thread: what a plain node's code can do."""
        if place == "task":
            executor.create_task(loop_task())
        elif place == "reader":
            # A transport (its reads registered through the loop's own _add_reader), connected
            # from the worker thread the way asyncio offers: the coroutine posted to the loop.
            asyncio.run_coroutine_threadsafe(connect(), executor.loop)
        else:
            thread = threading.Thread(target=in_thread, name=f"{name}-burner", daemon=True)
            thread.start()
            stop.later(lambda: thread.join(5.0))

    async def start_async() -> None:
        """From an ``async def`` callback, on the loop."""
        loop = asyncio.get_running_loop()
        if place == "task":
            stop.keep(loop.create_task(loop_task()))  # cancelled as the executor shuts down
        elif place == "reader":
            loop.add_reader(ours.fileno(), on_readable)
            stop.later(lambda: _on_loop(executor, lambda: loop.remove_reader(ours.fileno())))
        else:
            thread = threading.Thread(target=in_thread, name=f"{name}-burner", daemon=True)
            thread.start()
            stop.later(lambda: thread.join(5.0))

    if style == "plain":

        def kick_plain() -> None:
            if first():
                start_plain()

        node.create_timer(PERIOD_S, kick_plain)
    else:

        async def kick() -> None:
            if first():
                await start_async()

        node.create_timer(PERIOD_S, kick)  # type: ignore[arg-type, unused-ignore]
    if place == "reader":
        feeding = threading.Thread(target=feed, name=f"{name}-feeder", daemon=True)
        feeding.start()
        stop.later(lambda: feeding.join(5.0))
    return burns


def _process_cpu_s() -> float:
    """The process's CPU time from ``/proc`` (user and system, in clock ticks)."""
    with open("/proc/self/stat", encoding="ascii") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _measure(executor: AsyncioExecutor, burning: dict[str, Burns]) -> tuple[ContainerLoad, dict[str, float], float]:
    """One window once every node burned a few times: its load, what each node burned in it,
    and the process's CPU from ``/proc`` per second of it."""
    accounting = executor.accounting
    assert accounting is not None
    wait_until(lambda: all(burns.count() >= 3 for burns in burning.values()), "every node to burn", timeout=20.0)
    counts = {name: burns.count() for name, burns in burning.items()}
    cpu_before, start = _process_cpu_s(), time.monotonic()
    accounting.sample()
    wait_until(
        lambda: all(burns.count() >= counts[name] + BURNS for name, burns in burning.items()),
        f"{BURNS} more burns of every node",
        timeout=30.0,
    )
    load = accounting.sample()
    end, cpu_after = time.monotonic(), _process_cpu_s()
    burned = {name: burns.between(start, end) for name, burns in burning.items()}
    return load, burned, (cpu_after - cpu_before) / (end - start)


def _node(load: ContainerLoad, name: str) -> NodeLoad:
    found = [node for node in load.nodes if node.name == name]
    assert found, f"no {name} in {[node.name for node in load.nodes]}"
    return found[0]


def _check(load: ContainerLoad, burned: dict[str, float], process: float) -> None:
    for name, spent in burned.items():
        node = _node(load, f"/{name}")
        measured = node.cpu * load.period
        rows = [(c.kind, round(c.cpu * load.period, 4)) for c in node.callbacks if c.cpu > 0]
        assert measured == pytest.approx(spent, rel=0.2), (name, measured, spent, rows)
    idle = _node(load, "/idle")
    assert idle.cpu < 0.01, idle
    parts = load.nodes_cpu + load.executor_cpu + load.unattributed_cpu
    assert parts == pytest.approx(process, rel=0.1), (load.nodes_cpu, load.executor_cpu, load.unattributed, process)
    assert load.nodes_cpu == pytest.approx(sum(node.cpu for node in load.nodes))


def _skip_without_thread_attribution(place: str) -> None:
    if place == "thread" and not SEES_THREAD_STARTS:
        pytest.skip("Python 3.11 tells no audit hook of a thread's start: its threads are nobody's")


#: Where each place's CPU shows, by kind of row.
_KIND = {"callback": "timer", "task": "task", "reader": "fd", "thread": "thread"}


@pytest.mark.parametrize("style", STYLES)
@pytest.mark.parametrize("place", PLACES)
def test_a_node_is_credited_what_it_burns_in_each_place(
    spinning: AsyncioExecutor, host: Callable[..., Any], stop: _Stop, place: str, style: str
) -> None:
    _skip_without_thread_attribution(place)
    burning = {"burner": burning_node(host, spinning, stop, place, style, "burner")}
    host(Node, "idle").create_timer(1.0, lambda: None)
    load, burned, process = _measure(spinning, burning)
    _check(load, burned, process)
    burner = _node(load, "/burner")
    rows = {c.kind: c.cpu for c in burner.callbacks}
    assert rows[_KIND[place]] >= 0.8 * burner.cpu, rows


@pytest.mark.parametrize("style", STYLES)
def test_nodes_burning_in_every_place_side_by_side_are_each_credited_their_own(
    spinning: AsyncioExecutor, host: Callable[..., Any], stop: _Stop, style: str
) -> None:
    places = [place for place in PLACES if place != "thread" or SEES_THREAD_STARTS]
    burning = {place: burning_node(host, spinning, stop, place, style, place) for place in places}
    host(Node, "idle").create_timer(1.0, lambda: None)
    load, burned, process = _measure(spinning, burning)
    _check(load, burned, process)


def test_a_task_holding_the_loop_is_its_nodes_and_shown_stuck(context: Context, host: Callable[..., Any]) -> None:
    """A task a node started blocks the loop past the threshold: the node is stuck, in that task's row,
    while it lasts, and the watchdog names the node."""
    executor = AsyncioExecutor(context=context, stall_after=0.3)
    release = threading.Event()
    node = Node("holder", context=context)

    async def hold() -> None:
        release.wait(10.0)  # blocking code in an async def: the fault

    async def kick() -> None:
        if first():
            asyncio.get_running_loop().create_task(hold())

    first = _once(lambda: None)
    node.create_timer(0.05, kick)  # type: ignore[arg-type, unused-ignore]
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    accounting = executor.accounting
    assert accounting is not None
    windows: list[ContainerLoad] = []

    def stuck() -> bool:
        windows.append(accounting.sample())
        return any(item.name == "/holder" and item.stuck_for >= 0.3 for item in windows[-1].nodes)

    try:
        wait_until(stuck, "the node to be stuck")
        holder = _node(windows[-1], "/holder")
        assert max(holder.callbacks, key=lambda c: c.stuck_for).kind == "task"
        watchdog = executor.watchdog
        assert watchdog is not None
        wait_until(lambda: watchdog.stall is not None, "the watchdog to see the stall")
        stall = watchdog.stall
        assert stall is not None and stall.plugin and stall.what.startswith("/holder: task "), stall
    finally:
        release.set()
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)
        executor.remove_node(node)
        node.destroy_node()


def test_a_reader_holding_the_loop_is_its_nodes_and_shown_stuck(context: Context, stop: _Stop) -> None:
    executor = AsyncioExecutor(context=context, stall_after=0.3)
    release = threading.Event()
    node = Node("reader_holder", context=context)
    ours, feeder = socket.socketpair()
    stop.later(ours.close)
    stop.later(feeder.close)

    def on_readable() -> None:
        ours.recv(64)
        release.wait(10.0)  # a reader that blocks: the fault

    async def kick() -> None:
        if first():
            asyncio.get_running_loop().add_reader(ours.fileno(), on_readable)
            feeder.send(b"x")

    first = _once(lambda: None)
    node.create_timer(0.05, kick)  # type: ignore[arg-type, unused-ignore]
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    accounting = executor.accounting
    assert accounting is not None
    windows: list[ContainerLoad] = []

    def stuck() -> bool:
        windows.append(accounting.sample())
        return any(item.name == "/reader_holder" and item.stuck_for >= 0.3 for item in windows[-1].nodes)

    try:
        wait_until(stuck, "the node to be stuck")
        holder = _node(windows[-1], "/reader_holder")
        assert max(holder.callbacks, key=lambda c: c.stuck_for).kind == "fd"
        watchdog = executor.watchdog
        assert watchdog is not None
        wait_until(lambda: watchdog.stall is not None, "the watchdog to see the stall")
        stall = watchdog.stall
        assert stall is not None and stall.plugin, stall
        assert stall.what == "/reader_holder: file descriptors (readers, transports)", stall
    finally:
        release.set()
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)
        executor.remove_node(node)
        node.destroy_node()


def test_a_sleep_that_wakes_late_is_late_in_its_nodes_figures(
    spinning: AsyncioExecutor, host: Callable[..., Any], stop: _Stop
) -> None:
    """A node's task sleeps 20 ms at a time; another node's ``async def`` callback holds the loop
    for 100 ms every 300 ms: the sleeper's wake-ups are late, and its figures say so."""
    woke: list[float] = []

    async def sleeper() -> None:
        while True:
            await asyncio.sleep(0.02)
            woke.append(time.monotonic())

    async def start() -> None:
        if first():
            stop.keep(asyncio.get_running_loop().create_task(sleeper()))  # cancelled as the executor shuts down

    first = _once(lambda: None)
    host(Node, "sleeper").create_timer(0.05, start)

    async def hog() -> None:
        time.sleep(0.1)  # holds the loop (the other node's fault)

    host(Node, "hog").create_timer(0.3, hog)
    accounting = spinning.accounting
    assert accounting is not None
    wait_until(lambda: len(woke) >= 3, "the sleeper to wake")
    accounting.sample()
    count = len(woke)
    wait_until(lambda: len(woke) >= count + 40, "40 more wake-ups", timeout=20.0)
    load = accounting.sample()
    sleeper_load = _node(load, "/sleeper")
    timers = next(c for c in sleeper_load.callbacks if c.kind == "loop_timer")
    assert timers.rate > 5, timers
    assert timers.lateness_max >= 0.05, timers
    assert sleeper_load.lateness_p99 >= timers.lateness_p99 >= 0.03, sleeper_load
