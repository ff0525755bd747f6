"""Executor benchmark: AsyncioExecutor against rclpy's executors, side by side.

Run: ``.venv/bin/python tests/benchmarks/bench_executor.py [--rounds 3] [--seconds 2]``

Two measurements, each executor in a fresh process, the executors taking
turns round after round so that drift on a shared machine hits all alike:

* **ping-pong**: node A publishes ``ping``, node B's callback publishes
  ``pong``, A's callback publishes the next ping; round trips per second.
* **gap**: node A runs a plain callback that blocks 1 s every 0.5 s while node
  B runs a 20 Hz timer; the largest gap between B's timer callbacks.

Printed as medians and as ratios to rclpy's SingleThreadedExecutor.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import random
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

KINDS = {
    "asyncio-async": "AsyncioExecutor, async def callbacks",
    "asyncio-plain": "AsyncioExecutor, plain callbacks",
    "single": "rclpy SingleThreadedExecutor",
    "multi": "rclpy MultiThreadedExecutor",
}


def _executor(kind: str) -> Any:
    if kind.startswith("asyncio"):
        from container import AsyncioExecutor

        return AsyncioExecutor()
    from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

    return SingleThreadedExecutor() if kind == "single" else MultiThreadedExecutor()


def _spin_until(executor: Any, done: threading.Event, limit: float) -> None:
    """Spin ``executor`` until ``done`` is set, whatever the executor kind."""

    def stop_later() -> None:
        done.wait(limit)
        done.set()
        # Wakes any executor out of its wait so its spin loop sees ``done``.
        executor.wake()

    threading.Thread(target=stop_later, daemon=True).start()
    if hasattr(executor, "spin_async"):
        stopper = threading.Thread(
            target=lambda: (done.wait(), executor.shutdown(0.5)), daemon=True
        )
        stopper.start()
        executor.spin()
    else:
        while not done.is_set():
            executor.spin_once(timeout_sec=0.05)


def ping_pong(kind: str, seconds: float) -> float:
    import rclpy
    from rclpy.node import Node
    from std_msgs.msg import Int64

    rclpy.init()
    a, b = Node("bench_a"), Node("bench_b")
    ping = a.create_publisher(Int64, "ping", 10)
    pong = b.create_publisher(Int64, "pong", 10)
    count = 0
    started = threading.Event()
    done = threading.Event()
    t0 = 0.0

    def echo(msg: Int64) -> None:
        pong.publish(msg)

    def got(msg: Int64) -> None:
        nonlocal count, t0
        if not started.is_set():
            started.set()
            t0 = time.perf_counter()
        elif time.perf_counter() - t0 >= seconds:
            done.set()
            return
        else:
            count += 1
        ping.publish(msg)

    async def echo_async(msg: Int64) -> None:
        echo(msg)

    async def got_async(msg: Int64) -> None:
        got(msg)

    is_async = kind == "asyncio-async"
    b.create_subscription(Int64, "ping", echo_async if is_async else echo, 10)  # type: ignore[arg-type]  # rclpy types only plain callbacks
    a.create_subscription(Int64, "pong", got_async if is_async else got, 10)  # type: ignore[arg-type]
    executor = _executor(kind)
    executor.add_node(a)
    executor.add_node(b)
    # Ping until discovery completes and the first pong arrives.
    kicker_stop = threading.Event()

    def kick() -> None:
        while not started.is_set() and not kicker_stop.wait(0.05):
            ping.publish(Int64(data=0))

    threading.Thread(target=kick, daemon=True).start()
    _spin_until(executor, done, seconds + 30.0)
    kicker_stop.set()
    elapsed = time.perf_counter() - t0
    return count / elapsed if started.is_set() else 0.0


def timer_gap(kind: str, seconds: float) -> float:
    import rclpy
    from rclpy.node import Node

    rclpy.init()
    a, b = Node("bench_blocker"), Node("bench_ticker")
    ticks: list[float] = []
    done = threading.Event()

    def block() -> None:
        time.sleep(1.0)

    def tick() -> None:
        ticks.append(time.perf_counter())
        if ticks[-1] - ticks[0] >= seconds:
            done.set()

    a.create_timer(0.5, block)
    b.create_timer(0.05, tick)
    executor = _executor(kind)
    executor.add_node(a)
    executor.add_node(b)
    _spin_until(executor, done, seconds + 30.0)
    gaps = [later - earlier for earlier, later in itertools.pairwise(ticks)]
    return max(gaps) * 1000.0 if gaps else float("inf")


MEASURES: dict[str, Callable[[str, float], float]] = {
    "pingpong": ping_pong,
    "gap": timer_gap,
}


def _child(measure: str, kind: str, seconds: float) -> None:
    value = MEASURES[measure](kind, seconds)
    print(json.dumps({"value": value}), flush=True)
    os._exit(0)  # rclpy's MultiThreadedExecutor may leave threads behind


def _run_child(measure: str, kind: str, seconds: float) -> float:
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(random.randint(1, 200))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    cmd = [sys.executable, __file__, "--child", measure, kind, str(seconds)]
    try:
        out = subprocess.run(
            cmd, env=env, capture_output=True, text=True, timeout=seconds + 60, check=False
        )
    except subprocess.TimeoutExpired:
        return float("nan")
    for line in out.stdout.splitlines():
        if line.startswith("{"):
            return float(json.loads(line)["value"])
    sys.stderr.write(out.stderr[-2000:])
    return float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--only", choices=sorted(MEASURES), help="run one measurement")
    parser.add_argument("--child", nargs=3, metavar=("MEASURE", "KIND", "SECONDS"))
    args = parser.parse_args()
    if args.child:
        _child(args.child[0], args.child[1], float(args.child[2]))
    results: dict[tuple[str, str], list[float]] = {}
    for round_index in range(args.rounds):
        for measure in [args.only] if args.only else MEASURES:
            for kind in KINDS:
                seconds = args.seconds if measure == "pingpong" else max(args.seconds, 3.0)
                value = _run_child(measure, kind, seconds)
                results.setdefault((measure, kind), []).append(value)
                print(f"round {round_index + 1} {measure:8} {kind:14} {value:10.1f}", flush=True)
    print()
    nan = [float("nan")]
    single_rt = statistics.median(results.get(("pingpong", "single"), nan))
    print(f"{'executor':40} {'round trips/s':>14} {'vs single':>10} {'largest gap':>12}")
    for kind, label in KINDS.items():
        rts = results.get(("pingpong", kind), nan)
        gaps = results.get(("gap", kind), nan)
        rt = statistics.median(rts)
        print(
            f"{label:40} {rt:14.0f} {rt / single_rt:9.2f}x {statistics.median(gaps):10.0f} ms"
            f"   (round trips {min(rts):.0f}-{max(rts):.0f}; gaps {min(gaps):.0f}-{max(gaps):.0f} ms)"
        )
    singles = results.get(("pingpong", "single"), [])
    if singles:
        print("\nround by round, vs that round's SingleThreadedExecutor:")
        for kind, label in KINDS.items():
            ratios = [rt / one for rt, one in zip(results.get(("pingpong", kind), []), singles, strict=False)]
            listed = " ".join(f"{r:.2f}x" for r in ratios)
            print(f"{label:40} {listed}   (min {min(ratios):.2f}x)")


if __name__ == "__main__":
    main()
