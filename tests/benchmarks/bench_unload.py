"""Load/unload soak: what a container keeps after many load/unload cycles.

One ``container run`` process; a client process loads a Talker and a
Listener through ``~/_container/load_node``, brings the talker to active
over its ``change_state`` service, and unloads both, ``--cycles`` times. The
container's memory (USS and RSS, from ``/proc``) is read after the warm-up
hundred cycles and at the end, the time of every hundred cycles is kept,
and the ROS graph is compared before and after.

Side by side in one run (at the same time, on two ROS domains): the
container as shipped, and the same container
with rclpy's default ``start_type_description_service:=true`` forced on every
node (what rclpy keeps per node, about 100 kB, is what the container works
around).

    .venv/bin/python tests/benchmarks/bench_unload.py --cycles 1000
"""

from __future__ import annotations

import argparse
import concurrent.futures
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # tests.benchmarks

from tests.benchmarks import cpus  # noqa: E402
from tests.benchmarks.container_client import CLIENT_PRELUDE, smaps_rollup  # noqa: E402

CLIENT = CLIENT_PRELUDE + r"""
import time
from rclpy.parameter import Parameter
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState

cycles, tds = int(sys.argv[1]), sys.argv[2] == "on"
change = node.create_client(ChangeState, "/talker/change_state")

extra = [Parameter("start_type_description_service", value=True).to_parameter_msg()] if tds else []
started = time.monotonic()
for cycle in range(1, cycles + 1):
    ids = []
    for plugin in ("lifecycle_container::Talker", "lifecycle_container::Listener"):
        request = LoadNode.Request(package_name="lifecycle_container", plugin_name=plugin, parameters=extra)
        response = call(load, request)
        if not response.success:
            sys.exit(response.error_message)
        ids.append(response.unique_id)
    assert change.wait_for_service(timeout_sec=30.0)
    for transition in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
        if not call(change, ChangeState.Request(transition=Transition(id=transition))).success:
            sys.exit("talker did not come up")
    for unique_id in ids:
        if not call(unload, UnloadNode.Request(unique_id=unique_id)).success:
            sys.exit("unload failed")
    if cycle % 100 == 0:
        print(f"cycle {cycle} {time.monotonic() - started:.3f}", flush=True)
        sys.stdin.readline()
        started = time.monotonic()
executor.shutdown()
node.destroy_node()
rclpy.shutdown()
"""


def memory_kb(pid: int) -> tuple[int, int]:
    fields = smaps_rollup(pid)
    return fields["Private_Clean"] + fields["Private_Dirty"], fields["Rss"]


def graph(env: dict[str, str]) -> tuple[int, int]:
    """Nodes and services on the graph, as another process sees them."""
    probe = (
        "import rclpy, time\nfrom rclpy.node import Node\nrclpy.init()\nn = Node('_soak_probe')\n"
        "time.sleep(2.0)\n"
        "print(len(n.get_node_names()), len(n.get_service_names_and_types()))\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    nodes, services = out.stdout.split()
    return int(nodes), int(services)


def soak(cycles: int, *, tds: bool) -> dict[str, float]:
    domain = random.randint(100, 149) + (50 if tds else 0)  # distinct for the two soaks
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    with tempfile.TemporaryDirectory() as work:
        config = Path(work) / "empty.yaml"
        config.write_text("container: {name: ComponentManager}\n", encoding="utf-8")
        container = subprocess.Popen(
            [sys.executable, "-m", "container", "run", str(config)],
            cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        client_script = Path(work) / "client.py"
        client_script.write_text(CLIENT, encoding="utf-8")
        try:
            time.sleep(3.0)  # a benchmark, not a test: let the container come up
            graph_before = graph(env)
            client = subprocess.Popen(
                [sys.executable, str(client_script), str(cycles), "on" if tds else "off"],
                env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
            )
            assert client.stdin is not None and client.stdout is not None
            hundreds: list[float] = []
            memory: list[tuple[int, int]] = []
            for line in client.stdout:
                _, _, seconds = line.split()
                hundreds.append(float(seconds))
                memory.append(memory_kb(container.pid))
                client.stdin.write("\n")
                client.stdin.flush()
            if client.wait() != 0:
                raise SystemExit("the client failed")
            graph_after = graph(env)
        finally:
            container.terminate()
            container.wait(30)
    (uss0, rss0), (uss1, rss1) = memory[0], memory[-1]
    return {
        "uss_growth_mb": (uss1 - uss0) / 1024,
        "rss_growth_mb": (rss1 - rss0) / 1024,
        "first_hundred_s": hundreds[0],
        "last_hundred_s": hundreds[-1],
        "slowdown": hundreds[-1] / hundreds[0],
        "graph_nodes_left": graph_after[0] - graph_before[0],
        "graph_services_left": graph_after[1] - graph_before[1],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cycles", type=int, default=1000, help="load/unload cycles (multiple of 100)")
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    print(cpus.header(), flush=True)
    # Both at once, each on a ROS domain of its own: the same machine load
    # for both, and half the wall time.
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        ours = pool.submit(soak, args.cycles, tds=False)
        peer = pool.submit(soak, args.cycles, tds=True)
        results = {"container": ours.result(), "rclpy default (type description on)": peer.result()}
    print(f"{args.cycles} cycles, 2 nodes each; memory from cycle 100 to the end")
    header = ("USS MB", "RSS MB", "1st 100 s", "last 100 s", "x", "nodes", "srvs")
    print(f"{'':38} {header[0]:>8} {header[1]:>8} {header[2]:>10} {header[3]:>11} {header[4]:>5} "
          f"{header[5]:>6} {header[6]:>5}")
    for name, r in results.items():
        print(
            f"{name:38} {r['uss_growth_mb']:+8.1f} {r['rss_growth_mb']:+8.1f} {r['first_hundred_s']:10.1f} "
            f"{r['last_hundred_s']:11.1f} {r['slowdown']:5.2f} {r['graph_nodes_left']:+6.0f} "
            f"{r['graph_services_left']:+5.0f}"
        )
    mine, theirs = results.values()
    ratio = theirs["rss_growth_mb"] / max(mine["rss_growth_mb"], 0.1)
    print(f"RSS growth ratio (rclpy default / container): {ratio:.1f}x")


if __name__ == "__main__":
    main()
