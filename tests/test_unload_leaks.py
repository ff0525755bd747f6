"""60 load/unload cycles leave nothing behind: nodes, threads, tasks, memory.

Here the container runs in the test process, so that its executor, tasks
and memory can be inspected directly; the load and unload requests come
from a client child process over DDS, like any ``ros2 component`` call.
"""

from __future__ import annotations

import asyncio
import ctypes
import gc
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from rclpy.context import Context

from container._app import ContainerApp
from container._config import ContainerConfig
from container.executor._workers import WORKER_IDLE_S
from tests import component_support
from tests.component_support import BUSY_NODES

WARM_UP_CYCLES = 20
CYCLES = 60
#: Private memory the container may gain over CYCLES cycles after warm-up:
#: allocator arenas settle (runs here: +0.9 to +5.8 MB, in the whole suite
#: up to +12 MB before malloc_trim), a node leaked per cycle would not (one
#: costs about 100 kB: three per cycle, +18 MB over these cycles; so does a
#: ~/get_type_description service rclpy leaves, without the container's
#: finalising it). The long soak is the benchmark
#: ``tests/benchmarks/bench_unload.py --cycles 1000``.
MEMORY_BOUND_KB = 10 * 1024

#: The client: loads a Talker (then brings it to active over its
#: change_state service), a Busy and a Listener, and unloads all three, per
#: cycle; it pauses for the test to measure after the warm-up and at the end.
CLIENT = """
import sys
import rclpy
from rclpy.node import Node
from composition_interfaces.srv import LoadNode, UnloadNode
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue

rclpy.init(args=[])
node = Node("leak_cycler")
base = "/ComponentManager/_container/"
load = node.create_client(LoadNode, base + "load_node")
unload = node.create_client(UnloadNode, base + "unload_node")
change = node.create_client(ChangeState, "/talker/change_state")


def wait_ready(client):
    for _ in range(2000):
        if client.service_is_ready():
            return
        rclpy.spin_once(node, timeout_sec=0.01)
    sys.exit(f"{client.srv_name} never became ready")


def call(client, request):
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=30.0)
    if not future.done():
        sys.exit(f"no answer from {client.srv_name}")
    return future.result()


def cycle():
    ids = []
    # The listener with rclpy's ~/get_type_description service, which the
    # container leaves off unless asked: rclpy never finalises it.
    described = [Parameter(
        name="start_type_description_service",
        value=ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=True),
    )]
    for package, plugin, parameters in (
        ("lifecycle_container", "lifecycle_container::Talker", []),
        ("test_nodes", "test_nodes::Busy", []),
        ("lifecycle_container", "lifecycle_container::Listener", described),
    ):
        request = LoadNode.Request(package_name=package, plugin_name=plugin, parameters=parameters)
        response = call(load, request)
        if not response.success:
            sys.exit(response.error_message)
        ids.append(response.unique_id)
    wait_ready(change)
    for transition in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
        if not call(change, ChangeState.Request(transition=Transition(id=transition))).success:
            sys.exit("talker did not come up")
    for unique_id in ids:
        response = call(unload, UnloadNode.Request(unique_id=unique_id))
        if not response.success:
            sys.exit(response.error_message)


wait_ready(load)
wait_ready(unload)
for rounds in (int(sys.argv[1]), int(sys.argv[2])):
    for _ in range(rounds):
        cycle()
    print("paused", flush=True)
    sys.stdin.readline()
node.destroy_node()
rclpy.shutdown()
"""


@dataclass(frozen=True)
class Snapshot:
    loaded: int
    executor_nodes: int
    graph_nodes: frozenset[str]
    graph_services: frozenset[str]
    busy_objects: int
    executor_threads: int
    threads: tuple[str, ...]
    executor_tasks: int
    asyncio_tasks: int
    uss_kb: int
    rss_kb: int


def memory_kb() -> tuple[int, int]:
    """USS (private memory) and RSS of this process, from the kernel's own summary.

    Private memory, not PSS: PSS divides shared library pages among the
    processes that map them, so it moves whenever another Python process
    (a parallel test, a child) starts or ends; a leak is private memory.
    Freed memory the C allocator still holds is handed back first
    (``malloc_trim``): how much of it there is depends on what earlier
    tests in this process allocated, not on the cycles measured.
    """
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    fields = {}
    for line in Path("/proc/self/smaps_rollup").read_text().splitlines()[1:]:
        key, value = line.split(":", 1)
        fields[key] = int(value.split()[0])
    return fields["Private_Clean"] + fields["Private_Dirty"], fields["Rss"]


#: Workers an idle container itself keeps: its own two 1 Hz timers (the load
#: window and ``/diagnostics``) are plain callbacks, run by the worker idle
#: last, or by two when they overlap.
OWN_WORKERS = 2


async def settled_snapshot(app: ContainerApp) -> Snapshot:
    """A snapshot once the worker threads the cycles used have gone idle and exited.

    A worker outlives its last callback by up to ``WORKER_IDLE_S``, so how
    many are alive right after a cycle depends on how lately each ran (2
    against 3 between the two pauses of one CI run): a count, not a leak.
    A worker that never ends, or a callback still running, fails here.
    """
    deadline = time.monotonic() + 4 * WORKER_IDLE_S
    while len(app.executor.threads()) > OWN_WORKERS:
        assert time.monotonic() < deadline, f"workers never ended: {app.executor.threads()}"
        await asyncio.sleep(0.05)
    return snapshot(app)


def snapshot(app: ContainerApp) -> Snapshot:
    gc.collect()
    uss, rss = memory_kb()
    return Snapshot(
        loaded=len(app.manager.loaded()),
        executor_nodes=len(app.executor.get_nodes()),
        graph_nodes=frozenset(
            f"{ns.rstrip('/')}/{name}" for name, ns in app.manager.get_node_names_and_namespaces()
        ),
        graph_services=frozenset(name for name, _ in app.manager.get_service_names_and_types()),
        busy_objects=len(BUSY_NODES),
        executor_threads=len(app.executor.threads()),
        # Every thread but the worker pool's (counted above, and numbered as
        # they start: ``lane-3``).
        threads=tuple(sorted(t.name for t in set(threading.enumerate()) - set(app.executor.threads()))),
        executor_tasks=len(app.executor.tasks()),
        asyncio_tasks=len(asyncio.all_tasks(app.executor.loop)),
        uss_kb=uss,
        rss_kb=rss,
    )


# A soak: 80 load/unload cycles (about 15 s here); its own limits end it first.
@pytest.mark.slow
@pytest.mark.timeout(180)
def test_load_unload_cycles_leave_nothing_behind(context: Context, tmp_path: Path) -> None:
    script = tmp_path / "cycler.py"
    script.write_text(CLIENT, encoding="utf-8")
    app = ContainerApp.create(ContainerConfig(), context=context)
    app.registry.add_plugin(component_support, distribution="test-nodes")
    snapshots: list[Snapshot] = []

    async def drive() -> int:
        client = await asyncio.create_subprocess_exec(
            sys.executable, str(script), str(WARM_UP_CYCLES), str(CYCLES),
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
        )
        assert client.stdin is not None and client.stdout is not None
        try:
            for _ in range(2):
                line = await asyncio.wait_for(client.stdout.readline(), 120)
                assert line == b"paused\n", f"client stopped early: {line!r}"
                snapshots.append(await settled_snapshot(app))
                client.stdin.write(b"go\n")
                await client.stdin.drain()
            return await asyncio.wait_for(client.wait(), 30)
        finally:
            if client.returncode is None:
                client.kill()
                await client.wait()

    try:
        outcome: list[int] = []

        async def main() -> None:
            outcome.append(await drive())

        app.executor.spin_until_future_complete(main(), timeout_sec=170)
        assert outcome == [0], "the client failed or timed out"
    finally:
        app.close()
        app.executor.shutdown()

    before, after = snapshots
    assert (after.loaded, after.executor_nodes, after.busy_objects) == (0, 1, 0)
    assert after.graph_nodes == before.graph_nodes
    assert after.graph_services == before.graph_services
    # The listener's /listener/get_type_description was left on the graph by rclpy's destroy_node.
    assert "/listener/get_type_description" not in after.graph_services
    assert not {"/talker", "/busy", "/listener"} & after.graph_nodes
    assert after.executor_threads <= OWN_WORKERS  # settled_snapshot waited for it
    assert after.threads == before.threads
    assert after.executor_tasks == before.executor_tasks
    assert after.asyncio_tasks == before.asyncio_tasks
    growth = after.uss_kb - before.uss_kb
    print(
        f"USS {before.uss_kb} -> {after.uss_kb} kB ({growth:+} kB over {CYCLES} cycles); "
        f"RSS {before.rss_kb} -> {after.rss_kb} kB"
    )
    # Absolute: the container finalises what rclpy leaks per node (its type
    # description service), so nothing is left to discount.
    assert growth < MEMORY_BOUND_KB
