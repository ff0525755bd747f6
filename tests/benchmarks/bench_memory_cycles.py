"""Memory at scale, and given back: N talkers loaded and unloaded, cycle after cycle.

Run: ``.venv/bin/python tests/benchmarks/bench_memory_cycles.py [--nodes 200] [--cycles 3] [--cpus 1]``

Side by side in one run (at the same time, each on a ROS domain of its own):

* the container: ``container run`` on an empty file; a client loads
  ``--nodes`` demo talkers through ``~/_container/load_node`` (each
  configured and activated by the container: ``autostart``), then unloads
  them all through ``unload_node``;
* plain rclpy in one process: as many ``rclpy.lifecycle.LifecycleNode``
  talkers (a publisher and a 2 Hz timer each, the demo talker's), created,
  configured and activated, spun by a ``SingleThreadedExecutor``, then
  destroyed: what composing Python nodes by hand gives today.

Each process's PSS and RSS (``/proc/<pid>/smaps_rollup``) is read before the
first cycle, with the nodes loaded, and after they are gone: for the
container once its memory has settled (it gives freed heap back with
``malloc_trim`` a second after the last unload, see ``container/_memory.py``),
for rclpy after the same wait. Printed: PSS per node loaded, and RSS after
each cycle against before the first (the issue's budget: within 25%, and not
climbing from cycle to cycle).
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
from tests.benchmarks.container_client import CLIENT_PRELUDE, pss_and_rss  # noqa: E402

#: Load/unload client of the container: one line per phase on stdout, then waits for a line on stdin.
CONTAINER_CLIENT = CLIENT_PRELUDE + r"""
from rcl_interfaces.msg import Parameter, ParameterValue, ParameterType

nodes, cycles = int(sys.argv[1]), int(sys.argv[2])

autostart = Parameter(name="autostart", value=ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=True))
print("ready", flush=True); sys.stdin.readline()
for cycle in range(cycles):
    ids = []
    for index in range(nodes):
        request = LoadNode.Request(
            package_name="lifecycle_container", plugin_name="lifecycle_container::Talker",
            node_name=f"talker_{index}", extra_arguments=[autostart],
        )
        response = call(load, request, 60.0)
        if not response.success:
            sys.exit(response.error_message)
        ids.append(response.unique_id)
    print("loaded", flush=True); sys.stdin.readline()
    for unique_id in ids:
        if not call(unload, UnloadNode.Request(unique_id=unique_id), 60.0).success:
            sys.exit("unload failed")
    print("unloaded", flush=True); sys.stdin.readline()
executor.shutdown()
node.destroy_node()
rclpy.shutdown()
"""

#: The same in plain rclpy, in its own process (the one measured).
RCLPY = r"""
import sys, threading
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from std_msgs.msg import String

nodes, cycles = int(sys.argv[1]), int(sys.argv[2])

class Talker(LifecycleNode):
    def __init__(self, name):
        super().__init__(name)
        self.declare_parameter("rate", 2.0)
        self.pub = self.timer = None
        self.count = 0

    def on_configure(self, state):
        self.pub = self.create_lifecycle_publisher(String, "chatter", 10)
        self.timer = self.create_timer(0.5, self.tick)
        return TransitionCallbackReturn.SUCCESS

    def tick(self):
        self.count += 1
        self.pub.publish(String(data=f"Hello World: {self.count}"))

rclpy.init()
executor = SingleThreadedExecutor()
stop = threading.Event()
def spin():
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.1)
print("ready", flush=True); sys.stdin.readline()
for cycle in range(cycles):
    talkers = []
    for index in range(nodes):
        talker = Talker(f"talker_{index}")
        talker.trigger_configure()
        talker.trigger_activate()
        executor.add_node(talker)
        talkers.append(talker)
    stop.clear()
    spinner = threading.Thread(target=spin); spinner.start()
    print("loaded", flush=True); sys.stdin.readline()
    stop.set(); spinner.join()
    for talker in talkers:
        executor.remove_node(talker)
        talker.destroy_node()
    talkers.clear()
    print("unloaded", flush=True); sys.stdin.readline()
rclpy.shutdown()
"""


def settled(pid: int, *, quiet: float = 2.0, timeout: float = 30.0) -> tuple[int, int]:
    """``pid``'s memory once its RSS has moved less than 1% for ``quiet`` seconds."""
    deadline = time.monotonic() + timeout
    last = pss_and_rss(pid)
    since = time.monotonic()
    while time.monotonic() < deadline:
        time.sleep(0.25)
        now = pss_and_rss(pid)
        if abs(now[1] - last[1]) > last[1] / 100:
            last, since = now, time.monotonic()
        elif time.monotonic() - since >= quiet:
            return now
    return pss_and_rss(pid)


def run(layout: str, nodes: int, cycles: int) -> list[tuple[str, int, int, float]]:
    """``(phase, PSS kB, RSS kB, seconds)`` of the measured process: before, then
    loaded/unloaded per cycle, with how long the driver took to get there (the
    load or the unload of every node)."""
    env = {
        **os.environ,
        "ROS_DOMAIN_ID": str(random.randint(100, 140) + (50 if layout == "rclpy" else 0)),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
    }
    phases: list[tuple[str, int, int, float]] = []
    with tempfile.TemporaryDirectory() as work:
        container = None
        if layout == "container":
            config = Path(work) / "empty.yaml"
            config.write_text("container: {name: ComponentManager}\n", encoding="utf-8")
            container = subprocess.Popen(
                [sys.executable, "-m", "container", "run", str(config)],
                cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )
            script = CONTAINER_CLIENT
        else:
            script = RCLPY
        path = Path(work) / "driver.py"
        path.write_text(script, encoding="utf-8")
        driver = subprocess.Popen(
            [sys.executable, str(path), str(nodes), str(cycles)],
            cwd=REPO, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )
        measured = container if container is not None else driver
        assert driver.stdin is not None and driver.stdout is not None
        try:
            went = time.monotonic()
            for line in driver.stdout:
                phase = line.strip()
                took = time.monotonic() - went
                pss, rss = settled(measured.pid)
                phases.append((phase, pss, rss, took))
                driver.stdin.write("\n")
                driver.stdin.flush()
                went = time.monotonic()
            if driver.wait() != 0:
                raise SystemExit(f"the {layout} driver failed")
        finally:
            if container is not None:
                container.terminate()
                container.wait(60)
    return phases


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, default=200)
    parser.add_argument("--cycles", type=int, default=3)
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    print(cpus.header(), flush=True)
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        futures = {layout: pool.submit(run, layout, args.nodes, args.cycles) for layout in ("container", "rclpy")}
        results = {layout: future.result() for layout, future in futures.items()}
    mib = 1024.0
    print(f"{args.nodes} demo talkers, {args.cycles} cycles; PSS and RSS in MiB")
    print(f"{'':11} {'phase':10} {'PSS':>8} {'RSS':>8} {'RSS/before':>11} {'took':>7} {'PSS/node kB':>12}")
    for layout, phases in results.items():
        _, pss0, rss0, _ = phases[0]
        for phase, pss, rss, took in phases:
            per_node = f"{(pss - pss0) / args.nodes:12.0f}" if phase == "loaded" else ""
            print(
                f"{layout:11} {phase:10} {pss / mib:8.1f} {rss / mib:8.1f} {rss / rss0:10.2f}x {took:6.1f}s {per_node}"
            )
    container, rclpy = results["container"], results["rclpy"]
    worst = max(rss for phase, _, rss, _ in container if phase == "unloaded") / container[0][2]
    print(f"container: RSS after unloading, worst cycle against before: {worst:.2f}x (budget 1.25x)")
    last_c = [rss for phase, _, rss, _ in container if phase == "unloaded"]
    last_r = [rss for phase, _, rss, _ in rclpy if phase == "unloaded"]
    print(f"RSS after each unload, container: {', '.join(f'{r / mib:.0f}' for r in last_c)} MiB; "
          f"rclpy: {', '.join(f'{r / mib:.0f}' for r in last_r)} MiB")


if __name__ == "__main__":
    main()
