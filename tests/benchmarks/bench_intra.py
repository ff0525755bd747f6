"""Intra-process benchmark: DDS against intra-process delivery, side by side.

Run: ``.venv/bin/python tests/benchmarks/bench_intra.py [--rounds 3] [--seconds 3]``

Two nodes of one process on one :class:`~container.AsyncioExecutor` (what a
container is) bounce a payload back and forth with ``async def`` callbacks:
A publishes it, B's callback publishes it back, A's callback publishes it
again. Every trial runs in a fresh process; the paths take turns round
after round, so that drift on a shared machine hits all alike.

Payloads: a 1920x1080 rgb8 ``sensor_msgs/Image`` (6.2 MB), a 1-million-point
``PointCloud2`` (x, y, z, intensity: 16 MB) and a small ``std_msgs/Int64``.
Paths:

* ``dds``: neither node has intra-process; every hop is serialised by rclpy
  and goes through Fast DDS;
* ``copy``: both nodes have intra-process, ``publisher.publish(msg)``: each
  hop copies the message once (the safe default);
* ``zero-copy``: both nodes have intra-process, ``hand_over(publisher,
  msg)``: each hop hands the object itself over;
* ``copy+outside``: as ``copy``, with a subscriber in another process that
  takes every message over DDS (what ``ros2 topic hz`` does), so every hop
  is also serialised and written.

Frames per second count hops (messages received); CPU is the process's
(every thread) over the same window, in % of one core and per message.
``--stream`` instead publishes images and clouds one way from a thread as
fast as it can and counts what arrives (the method behind the issue's
47-48 frames/s over DDS); messages beyond the keep-last depth are dropped.
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

PATHS = ("dds", "copy", "zero-copy", "copy+outside")
PAYLOADS = ("image", "cloud", "small")
TITLES = {
    "image": "1080p rgb8 Image (6.2 MB)",
    "cloud": "PointCloud2, 1 M points (16 MB)",
    "small": "std_msgs/Int64 ping-pong",
}


def _payload(kind: str) -> Any:
    import array

    from sensor_msgs.msg import Image, PointCloud2, PointField
    from std_msgs.msg import Int64

    if kind == "image":
        image = Image(height=1080, width=1920, encoding="rgb8", step=1920 * 3)
        image.data = array.array("B", os.urandom(1920 * 1080 * 3))
        return image
    if kind == "cloud":
        points = 1_000_000
        cloud = PointCloud2(height=1, width=points, point_step=16, row_step=16 * points, is_dense=True)
        cloud.fields = [
            PointField(name=name, offset=4 * index, datatype=PointField.FLOAT32, count=1)
            for index, name in enumerate(("x", "y", "z", "intensity"))
        ]
        cloud.data = array.array("B", os.urandom(16 * points))
        return cloud
    return Int64(data=0)


def trial(path: str, payload: str, seconds: float, *, stream: bool = False) -> dict[str, float]:
    """One measurement in this process: messages received per second, and CPU."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.qos import QoSProfile

    from container import AsyncioExecutor
    from container.intra import copy_message, enable_intra_process, hand_over

    context = Context()
    rclpy.init(context=context)
    executor = AsyncioExecutor(context=context)
    message = _payload(payload)
    kind = type(message)
    qos = QoSProfile(depth=10)
    a, b = Node("bench_a", context=context), Node("bench_b", context=context)
    if path != "dds":
        enable_intra_process(a)
        enable_intra_process(b)
    to_b = a.create_publisher(kind, "to_b", qos)
    to_a = b.create_publisher(kind, "to_a", qos)

    def publish(publisher: Any, msg: Any) -> None:
        publisher.publish(msg)

    send = hand_over if path == "zero-copy" else publish
    received = 0
    done = threading.Event()

    async def on_b(msg: Any) -> None:
        nonlocal received
        received += 1
        if not stream and not done.is_set():
            send(to_a, msg)

    async def on_a(msg: Any) -> None:
        nonlocal received
        received += 1
        if not done.is_set():
            send(to_b, msg)

    callbacks: Any = (on_b, on_a)  # rclpy's annotation knows no coroutines
    b.create_subscription(kind, "to_b", callbacks[0], qos)
    a.create_subscription(kind, "to_a", callbacks[1], qos)
    outside: subprocess.Popen[str] | None = None
    if path == "copy+outside":
        outside = subprocess.Popen(
            [sys.executable, __file__, "--outside", payload],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
    for node in (a, b):
        executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    wanted = 2 if outside is not None else 1
    deadline = time.monotonic() + 20
    while (to_b.get_subscription_count() < wanted or to_a.get_subscription_count() < wanted) and (
        time.monotonic() < deadline
    ):
        time.sleep(0.01)
    time.sleep(0.3)
    sent = 0

    def camera() -> None:
        """Publish frames as fast as possible, as a camera driver's thread would.

        The zero-copy path hands over a new message each time, around one of
        a few buffers (a driver's buffer pool); the others publish one
        message again and again.
        """
        nonlocal sent
        pool = [copy_message(message) for _ in range(4)]
        while not done.is_set():
            if path == "zero-copy":
                frame = pool[sent % 4]
                fresh: Any = object.__new__(kind)
                for slot in kind.__slots__:
                    object.__setattr__(fresh, slot, getattr(frame, slot))
                hand_over(to_b, fresh)
            else:
                to_b.publish(message)
            sent += 1

    if stream:
        threading.Thread(target=camera, daemon=True).start()
    else:
        send(to_b, message)
    time.sleep(0.5)  # warm up
    start_received, start_sent, start_cpu, start = received, sent, time.process_time(), time.monotonic()
    time.sleep(seconds)
    end_received, end_sent, end_cpu, end = received, sent, time.process_time(), time.monotonic()
    done.set()
    executor.shutdown(1.0)
    spinner.join(5.0)
    for node in (a, b):
        node.destroy_node()
    rclpy.shutdown(context=context)
    result = {
        "rate": (end_received - start_received) / (end - start),
        "sent": (end_sent - start_sent) / (end - start),
        "cpu": 100 * (end_cpu - start_cpu) / (end - start),
        "total": float(received),
    }
    if outside is not None:
        try:
            counted, _ = outside.communicate("", timeout=20)
        except subprocess.TimeoutExpired:
            outside.kill()
            counted, _ = outside.communicate()
        result["outside"] = float(counted.strip() or 0)
    return result


def outside_subscriber(payload: str) -> None:
    """Count the messages on both topics over DDS, as ``ros2 topic hz`` would, until stdin closes."""
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile

    rclpy.init()
    node = Node("bench_outside")
    kind = type(_payload(payload))
    count = 0

    def on_message(_msg: Any) -> None:
        nonlocal count
        count += 1

    for topic in ("to_a", "to_b"):
        node.create_subscription(kind, topic, on_message, QoSProfile(depth=10))
    closed = threading.Event()
    def until_stdin_closes() -> None:
        sys.stdin.read()
        closed.set()

    threading.Thread(target=until_stdin_closes, daemon=True).start()
    while not closed.is_set():
        rclpy.spin_once(node, timeout_sec=0.1)
    print(count, flush=True)


def _run_trial(path: str, payload: str, seconds: float, *, stream: bool) -> dict[str, float]:
    output = subprocess.run(
        [sys.executable, __file__, "--trial", path, payload, str(seconds), *(["--stream"] if stream else [])],
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
    parser.add_argument("--payloads", nargs="*", default=list(PAYLOADS), choices=PAYLOADS)
    parser.add_argument("--paths", nargs="*", default=list(PATHS), choices=PATHS)
    parser.add_argument(
        "--stream",
        action="store_true",
        help="payloads one way, published as fast as possible (received per second), not bounced",
    )
    parser.add_argument("--trial", nargs=3, metavar=("PATH", "PAYLOAD", "SECONDS"), help=argparse.SUPPRESS)
    parser.add_argument("--outside", metavar="PAYLOAD", help=argparse.SUPPRESS)
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    if args.outside:
        outside_subscriber(args.outside)
        return
    if args.trial:
        path, payload, seconds = args.trial
        print(json.dumps(trial(path, payload, float(seconds), stream=args.stream)), flush=True)
        return
    print(cpus.header(), flush=True)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    results: dict[tuple[str, str], list[dict[str, float]]] = {}
    for round_ in range(1, args.rounds + 1):
        for payload in args.payloads:
            for path in args.paths:
                if path == "copy+outside" and payload == "small":
                    continue
                result = _run_trial(path, payload, args.seconds, stream=args.stream and payload != "small")
                results.setdefault((payload, path), []).append(result)
                extra = (
                    f", outside process got {result['outside']:.0f} of {result['total']:.0f}"
                    if "outside" in result
                    else ""
                )
                print(
                    f"round {round_}: {payload:5} {path:12} {result['rate']:10.1f} msg/s "
                    f"CPU {result['cpu']:5.1f}%{extra}",
                    flush=True,
                )
    print()
    for payload in args.payloads:
        dds = results.get((payload, "dds"))
        base = statistics.median(r["rate"] for r in dds) if dds else None
        print(f"{TITLES[payload]}")
        print("| path | msg/s (median) | range | vs DDS | CPU, % of a core | CPU per msg |")
        print("|---|---|---|---|---|---|")
        for path in args.paths:
            runs = results.get((payload, path))
            if not runs:
                continue
            rates = [r["rate"] for r in runs]
            rate = statistics.median(rates)
            cpu = statistics.median(r["cpu"] for r in runs)
            ratio = f"**{rate / base:.1f}x**" if base else "-"
            per = 10 * cpu / rate if rate else float("nan")
            print(
                f"| {path} | {rate:,.0f} | {min(rates):,.0f}-{max(rates):,.0f} | {ratio} | "
                f"{cpu:.0f} | {per:.3f} ms |"
            )
        print()


if __name__ == "__main__":
    main()
