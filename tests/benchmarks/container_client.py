"""What the container benchmarks share: a client of a container's load and unload services
(a script run as a process of its own), and a process's memory as the kernel sums it."""

from __future__ import annotations

from pathlib import Path

#: The start of a client script: rclpy up, ``node`` spun by an ``AsyncioExecutor``
#: (rclpy's SingleThreadedExecutor spent 85% of a core here and set the pace), ``load``
#: and ``unload`` clients of ``/ComponentManager`` ready, and ``call(client, request,
#: timeout)``, which exits the script when no answer comes. The script goes on after it.
CLIENT_PRELUDE = r"""
import sys
import rclpy
from rclpy.node import Node
from composition_interfaces.srv import LoadNode, UnloadNode

from container import AsyncioExecutor

rclpy.init()
node = Node("_bench_client")
executor = AsyncioExecutor()
executor.add_node(node)
load = node.create_client(LoadNode, "/ComponentManager/_container/load_node")
unload = node.create_client(UnloadNode, "/ComponentManager/_container/unload_node")
for client in (load, unload):
    assert client.wait_for_service(timeout_sec=30.0)

def call(client, request, timeout=30.0):
    future = client.call_async(request)
    executor.spin_until_future_complete(future, timeout_sec=timeout)
    if not future.done():
        sys.exit(f"no answer from {client.srv_name}")
    return future.result()
"""


def smaps_rollup(pid: int) -> dict[str, int]:
    """``/proc/<pid>/smaps_rollup``'s fields (``Rss``, ``Pss``, ``Private_Dirty``, ...), kB."""
    fields: dict[str, int] = {}
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:]:
        key, value = line.split(":", 1)
        fields[key] = int(value.split()[0])
    return fields


def pss_and_rss(pid: int) -> tuple[int, int]:
    """PSS and RSS of ``pid``, kB."""
    fields = smaps_rollup(pid)
    return fields["Pss"], fields["Rss"]
