"""Cost per callback against the node count: the same total work spread over 10 to 500 nodes.

Run: ``.venv/bin/python tests/benchmarks/bench_scale.py [--nodes 10 50 100 200 500] [--rounds 3]
[--seconds 3] [--cpus 1]``

Issue 47's second item: for a fixed total rate of work, the CPU a callback
costs at 500 nodes within 1.25x of what it costs at 10, for plain and
``async def`` callbacks, beside rclpy's executors. Each of N nodes has a
timer publishing every N ms to the next node's subscription: 1,000 timer
firings and 1,000 messages a second whatever N is (bench_executor.py's
``load_nodes``; its ten-node load is N = 10). An executor whose wait, take or dispatch walks
every entity on every wake-up pays more per callback as N grows.

Each figure is one process (a child of this script, a random
``ROS_DOMAIN_ID``): the nodes are created, the messages flow at the full
rate (500 nodes' 1,000 endpoints take seconds to match), discovery is over
(every node's services are seen, for 1.5 s: see ``_until_discovered``),
then the process's CPU is read over ``--seconds``. Printed per kind and node count: the CPU (% of
a core), the microseconds of CPU per callback (firings and messages), that
cost over the same kind's at the fewest nodes, and over rclpy's
SingleThreadedExecutor's at the same count (medians of ``--rounds``; each
round runs every kind back to back at each count, the order reversed every
other round).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.benchmarks

from tests.benchmarks import cpus
from tests.benchmarks.bench_executor import KINDS, _engine_env, _executor, _spin_until, load_nodes

#: The executors compared (bench_executor.py's kinds).
SCALE_KINDS = ("asyncio-plain", "asyncio-async", "single", "events")
#: Timer firings a second, in all, whatever the node count (and as many messages: ``load_nodes``).
RATE = 1000


def measure(kind: str, count: int, seconds: float) -> dict[str, float]:
    """One process's figures: CPU % of a core, callbacks a second, CPU microseconds per callback."""
    import rclpy

    rclpy.init()
    nodes, counts = load_nodes(kind, count=count)  # counts: messages, firings
    executor = _executor(kind)
    for node in nodes:
        executor.add_node(node)
    done = threading.Event()
    result: dict[str, float] = {}

    def window() -> None:
        # Until every subscription matched: a second's messages at the full rate.
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            before, start = counts[0], time.perf_counter()
            time.sleep(1.0)
            if (counts[0] - before) / (time.perf_counter() - start) >= 0.95 * RATE:
                break
        _until_discovered(nodes, deadline=time.monotonic() + 120.0)
        cpu0, wall0, calls0 = time.process_time(), time.perf_counter(), sum(counts)
        time.sleep(seconds)
        cpu1, wall1, calls1 = time.process_time(), time.perf_counter(), sum(counts)
        calls = calls1 - calls0
        result.update(
            cpu=100.0 * (cpu1 - cpu0) / (wall1 - wall0),
            rate=calls / (wall1 - wall0),
            us=1e6 * (cpu1 - cpu0) / calls if calls else float("nan"),
        )
        done.set()

    threading.Thread(target=window, daemon=True).start()
    _spin_until(executor, done, seconds + 120.0)
    return result


def _until_discovered(nodes: list[Any], *, deadline: float) -> None:
    """Until Fast DDS has discovered every node's services, and the count held for 1.5 s.

    Messages flow at the full rate long before that: 500 nodes' parameter
    services (3,000 of them, two endpoints each) are still being matched
    for some 40 s, and that matching (``ReaderProxyData::copy``, 23% of the
    process's CPU in ``perf``) is discovery's cost, not the callbacks'.
    Measured from the first full second instead, the 500-node figures
    included it.
    """
    expected = sum(len(list(node.services)) for node in nodes)
    seen, steady = -1, 0
    while time.monotonic() < deadline and steady < 3:
        found = len(nodes[0].get_service_names_and_types())
        steady = steady + 1 if found == seen and found >= expected else 0
        seen = found
        time.sleep(0.5)


def _run(kind: str, count: int, seconds: float) -> dict[str, float]:
    env = dict(os.environ) | _engine_env(kind)
    env["ROS_DOMAIN_ID"] = str(random.randint(1, 200))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    cmd = [sys.executable, __file__, "--child", kind, str(count), str(seconds)]
    try:
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=seconds + 240, check=False)
    except subprocess.TimeoutExpired:
        return {}
    for line in out.stdout.splitlines():
        if line.startswith("{"):
            figures: dict[str, float] = json.loads(line)
            return figures
    sys.stderr.write(out.stderr[-2000:])
    return {}


def _median(values: list[float]) -> float:
    values = [value for value in values if value == value]
    return statistics.median(values) if values else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, nargs="+", default=[10, 50, 100, 200, 500])
    parser.add_argument("--kinds", nargs="+", choices=SCALE_KINDS, default=list(SCALE_KINDS))
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--child", nargs=3, metavar=("KIND", "NODES", "SECONDS"))
    cpus.add_option(parser)
    args = parser.parse_args()
    if args.child:
        kind, count, seconds = args.child
        print(json.dumps(measure(kind, int(count), float(seconds))), flush=True)
        os._exit(0)
    cpus.pin(parser, args.cpus)
    print(cpus.header(), flush=True)
    runs: dict[tuple[str, int], list[dict[str, float]]] = {}
    for round_index in range(args.rounds):
        for count in args.nodes:
            kinds = args.kinds if round_index % 2 == 0 else args.kinds[::-1]
            for kind in kinds:
                figures = _run(kind, count, args.seconds)
                runs.setdefault((kind, count), []).append(figures)
                shown = (
                    f"{figures['cpu']:.1f}% {figures['rate']:.0f} callbacks/s {figures['us']:.1f} us"
                    if figures
                    else "failed"
                )
                print(f"round {round_index + 1} {count:4d} nodes {kind:14s} {shown}", flush=True)
    print()
    print(f"medians of {args.rounds} round(s); {RATE} firings and {RATE} messages a second in all")
    print("| executor | nodes | CPU | callbacks/s | us per callback | vs fewest nodes | vs single |")
    print("|---|---|---|---|---|---|---|")
    for kind in args.kinds:
        first = _median([f.get("us", float("nan")) for f in runs.get((kind, args.nodes[0]), [])])
        for count in args.nodes:
            measured = runs.get((kind, count), [])
            us = _median([f.get("us", float("nan")) for f in measured])
            single = _median([f.get("us", float("nan")) for f in runs.get(("single", count), [])])
            print(
                f"| {KINDS[kind]} | {count} | {_median([f.get('cpu', float('nan')) for f in measured]):.1f}% "
                f"| {_median([f.get('rate', float('nan')) for f in measured]):.0f} | {us:.1f} "
                f"| {us / first:.2f}x | {us / single:.2f}x |"
            )


if __name__ == "__main__":
    main()
