"""Subscribers beside a busy ``async def`` publisher: plain against ``async def``, DDS against intra-process.

Run: ``.venv/bin/python tests/benchmarks/bench_busy.py [--rounds 3] [--seconds 3]``

Two nodes of one process on one :class:`~container.AsyncioExecutor`: node
A's asyncio task publishes one reused 1080p rgb8 ``sensor_msgs/Image``
(6.2 MB) as fast as it can, ``publish`` then ``await asyncio.sleep(0)``, so
the loop's thread is never idle; node B's subscription (keep-last 10)
counts what arrives. B's callback is plain (it runs on a worker thread of
its callback group, which must get the GIL from the busy loop thread) or
``async def`` (it runs on the loop thread). Paths: ``dds`` (no
intra-process: rclpy serialises, Fast DDS delivers) and ``intra`` (both
nodes with ``use_intra_process_comms``: one copy per message).

Frames per second are frames B's callback received; latency is from the
moment A stamped a frame just before ``publish`` to the start of B's
callback (median and 95th percentile of the window). Every trial runs in a
fresh process, the cells taking turns round after round; printed as
medians and as ratios: intra-process over DDS for each subscriber, and the
plain subscriber's latency over the ``async def`` one's.
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

PATHS = ("dds", "intra")
SUBSCRIBERS = ("plain", "async")


def trial(path: str, subscriber: str, seconds: float) -> dict[str, float]:
    """One measurement in this process: frames per second and latency."""
    import array
    import asyncio

    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import Image

    from container import AsyncioExecutor
    from container.intra import enable_intra_process

    context = Context()
    rclpy.init(context=context)
    executor = AsyncioExecutor(context=context)
    image = Image(height=1080, width=1920, encoding="rgb8", step=1920 * 3)
    image.data = array.array("B", os.urandom(1920 * 1080 * 3))
    qos = QoSProfile(depth=10)
    a, b = Node("busy_publisher", context=context), Node("busy_subscriber", context=context)
    if path == "intra":
        enable_intra_process(a)
        enable_intra_process(b)
    publisher = a.create_publisher(Image, "frames", qos)
    latencies: list[float] = []
    measuring = threading.Event()
    done = threading.Event()

    def note(msg: Image) -> None:
        if measuring.is_set():
            now = time.perf_counter_ns()
            latencies.append((now - (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)) / 1e6)

    async def note_async(msg: Image) -> None:
        note(msg)

    callback: Any = note if subscriber == "plain" else note_async  # rclpy's annotation knows no coroutines
    b.create_subscription(Image, "frames", callback, qos)
    for node in (a, b):
        executor.add_node(node)

    async def pump() -> None:
        stamp = image.header.stamp
        while not done.is_set():
            now = time.perf_counter_ns()
            stamp.sec, stamp.nanosec = divmod(now, 1_000_000_000)
            publisher.publish(image)
            await asyncio.sleep(0)

    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    deadline = time.monotonic() + 20
    while publisher.get_subscription_count() < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    executor.create_task(pump())
    time.sleep(0.5)  # warm up
    start_cpu, start = time.process_time(), time.monotonic()
    measuring.set()
    time.sleep(seconds)
    measuring.clear()
    end_cpu, end = time.process_time(), time.monotonic()
    received = list(latencies)
    done.set()
    executor.shutdown(1.0)
    spinner.join(5.0)
    for node in (a, b):
        node.destroy_node()
    rclpy.shutdown(context=context)
    received.sort()
    return {
        "rate": len(received) / (end - start),
        "median": statistics.median(received) if received else float("nan"),
        "p95": received[int(0.95 * (len(received) - 1))] if received else float("nan"),
        "cpu": 100 * (end_cpu - start_cpu) / (end - start),
    }


def _run_trial(path: str, subscriber: str, seconds: float) -> dict[str, float]:
    output = subprocess.run(
        [sys.executable, __file__, "--trial", path, subscriber, str(seconds)],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
        env={**os.environ, "ROS_DOMAIN_ID": str(random.randint(1, 200))},
    ).stdout
    result: dict[str, float] = json.loads(output.strip().splitlines()[-1])
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--trial", nargs=3, metavar=("PATH", "SUBSCRIBER", "SECONDS"), help=argparse.SUPPRESS)
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    if args.trial:
        path, subscriber, seconds = args.trial
        print(json.dumps(trial(path, subscriber, float(seconds))), flush=True)
        return
    print(cpus.header(), flush=True)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    cells = [(path, subscriber) for subscriber in SUBSCRIBERS for path in PATHS]
    results: dict[tuple[str, str], list[dict[str, float]]] = {cell: [] for cell in cells}
    for round_ in range(1, args.rounds + 1):
        for cell in cells if round_ % 2 else reversed(cells):
            result = _run_trial(*cell, args.seconds)
            results[cell].append(result)
            print(
                f"round {round_}: {cell[1]:5} {cell[0]:5} {result['rate']:7.1f} frames/s "
                f"latency median {result['median']:6.2f} ms p95 {result['p95']:6.2f} ms CPU {result['cpu']:5.1f}%",
                flush=True,
            )

    def median(cell: tuple[str, str], key: str) -> float:
        return statistics.median(r[key] for r in results[cell])

    print()
    print("| subscriber | path | frames/s (median) | range | intra over DDS | latency median | p95 | CPU, % |")
    print("|---|---|---|---|---|---|---|---|")
    for subscriber in SUBSCRIBERS:
        for path in PATHS:
            cell = (path, subscriber)
            rates = [r["rate"] for r in results[cell]]
            ratio = (
                f"**{median(cell, 'rate') / median(('dds', subscriber), 'rate'):.1f}x**" if path == "intra" else "-"
            )
            print(
                f"| {subscriber} | {path} | {median(cell, 'rate'):,.0f} | {min(rates):,.0f}-{max(rates):,.0f} | "
                f"{ratio} | {median(cell, 'median'):.2f} ms | {median(cell, 'p95'):.2f} ms | "
                f"{median(cell, 'cpu'):.0f} |"
            )
    plain, asynchronous = median(("intra", "plain"), "median"), median(("intra", "async"), "median")
    print()
    print(f"intra-process latency, plain over async def: **{plain / asynchronous:.2f}x** (median)")


if __name__ == "__main__":
    main()
