"""What the executor's accounting costs: the executor benchmarks with it on and off, side by side.

Run: ``.venv/bin/python tests/benchmarks/bench_accounting.py [--rounds 5] [--seconds 3]``

The per-node accounting (``container.executor.Accounting``) is always on in
a container; its budget is 3%. This runs bench_executor.py's measurements
that exercise the paths it times (ping-pong: the loop's compiled chain and
the worker threads' plain calls; services) for ``async def`` and plain
callbacks, each in a fresh process with the accounting on and off
(``AsyncioExecutor(accounting=False)``), the two taking turns in each round
and swapping order every other round.

The ten-node 100 Hz load is measured differently: its CPU differs by up to
2x from one process to the next on this VM (where the threads land, how
the host schedules them), far more than 3%. So ``load`` runs in one process
per round, the same ten nodes moved between two executors, accounting on
and off, for ``--seconds`` each, alternating five times; a round's figure is
the median of its five on/off ratios.

Printed as medians and as on/off ratios: throughput on/off at or above 0.97
and CPU on/off at or below 1.03 are within budget.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.benchmarks

from tests.benchmarks import cpus
from tests.benchmarks.bench_executor import ACCOUNTING_VARIABLE, _run_child, load_nodes

#: measure -> (what it prints, whether more is better).
MEASURES = {
    "pingpong": ("round trips/s", True),
    "services": ("service calls/s", True),
    "load": ("load CPU %", False),
}
KINDS = ("asyncio-async", "asyncio-plain")
#: Turns of each state per process in the load measurement.
LOAD_TURNS = 5


def _load_in_one_process(kind: str, seconds: float) -> list[tuple[float, float]]:
    """CPU % of the ten-node load (bench_executor's ``load``) under executors with
    the accounting on and off, taking turns in this process: ``(on, off)`` pairs."""
    import rclpy

    from container import AsyncioExecutor

    rclpy.init()
    nodes, received = load_nodes(kind)

    def turn(accounting: bool) -> float:
        executor = AsyncioExecutor(accounting=accounting)
        for node in nodes:
            executor.add_node(node)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        settled = received[0] + 1000
        deadline = time.monotonic() + 30.0
        while received[0] < settled and time.monotonic() < deadline:
            time.sleep(0.05)
        cpu0, wall0 = time.process_time(), time.perf_counter()
        time.sleep(seconds)
        cpu = 100.0 * (time.process_time() - cpu0) / (time.perf_counter() - wall0)
        executor.shutdown(timeout_sec=2.0)
        spinner.join(5.0)
        for node in nodes:
            executor.remove_node(node)
        return cpu

    pairs = []
    for index in range(LOAD_TURNS):
        first = index % 2 == 0
        a = turn(first)
        b = turn(not first)
        pairs.append((a, b) if first else (b, a))
    return pairs


def _load_round(kind: str, seconds: float) -> tuple[float, float, float]:
    """One process of :func:`_load_in_one_process`: median on, median off, median of the on/off ratios."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(random.randint(1, 200))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    out = subprocess.run(
        [sys.executable, __file__, "--load-child", kind, str(seconds)],
        env=env, capture_output=True, text=True, timeout=LOAD_TURNS * 2 * (seconds + 35) + 60, check=False,
    )
    for line in out.stdout.splitlines():
        if line.startswith("["):
            pairs = json.loads(line)
            on = statistics.median(pair[0] for pair in pairs)
            off = statistics.median(pair[1] for pair in pairs)
            return on, off, statistics.median(pair[0] / pair[1] for pair in pairs)
    sys.stderr.write(out.stderr[-2000:])
    return float("nan"), float("nan"), float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--only", choices=sorted(MEASURES), help="run one measurement")
    parser.add_argument("--load-child", nargs=2, metavar=("KIND", "SECONDS"), help=argparse.SUPPRESS)
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    if args.load_child:
        print(json.dumps(_load_in_one_process(args.load_child[0], float(args.load_child[1]))), flush=True)
        os._exit(0)
    print(cpus.header(), flush=True)
    measures = [args.only] if args.only else list(MEASURES)
    results: dict[tuple[str, str, str], list[float]] = {}
    for round_index in range(args.rounds):
        states = ("on", "off") if round_index % 2 == 0 else ("off", "on")
        for measure in measures:
            for kind in KINDS:
                if measure == "load":
                    on_cpu, off_cpu, pair_ratio = _load_round(kind, args.seconds)
                    for state, value in (("on", on_cpu), ("off", off_cpu), ("ratio", pair_ratio)):
                        results.setdefault((measure, kind, state), []).append(value)
                    line = (
                        f"round {round_index + 1} load     {kind:14} on {on_cpu:5.1f} off {off_cpu:5.1f}"
                        f" on/off {pair_ratio:.3f}"
                    )
                    print(line, flush=True)
                    continue
                for state in states:
                    value, _ = _run_child(
                        measure, kind, args.seconds, sys.executable, env_extra={ACCOUNTING_VARIABLE: state}
                    )
                    results.setdefault((measure, kind, state), []).append(value)
                    line = f"round {round_index + 1} {measure:8} {kind:14} accounting {state:3} {value:10.1f}"
                    print(line, flush=True)
    print(f"\n{'measure':18} {'callbacks':14} {'on':>10} {'off':>10} {'on/off':>8} {'by round':>20}  within 3%")
    for measure in measures:
        title, more_is_better = MEASURES[measure]
        for kind in KINDS:
            on, off = results[(measure, kind, "on")], results[(measure, kind, "off")]
            # load: each round's own ratio (on and off in one process); else the runs' medians.
            by_round = results.get((measure, kind, "ratio")) or [a / b for a, b in zip(on, off, strict=True) if b]
            ratio = statistics.median(by_round) if measure == "load" else statistics.median(on) / statistics.median(off)
            within = ratio >= 0.97 if more_is_better else ratio <= 1.03
            print(
                f"{title:18} {kind.removeprefix('asyncio-'):14} {statistics.median(on):10.1f}"
                f" {statistics.median(off):10.1f} {ratio:7.3f}x {min(by_round):8.3f}-{max(by_round):.3f}x"
                f"  {'yes' if within else 'NO'}"
            )


if __name__ == "__main__":
    main()
