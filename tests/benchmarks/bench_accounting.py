"""What the executor's accounting costs: the executor benchmarks with it on and off, side by side.

Run: ``.venv/bin/python tests/benchmarks/bench_accounting.py [--rounds 3] [--turns 5] [--seconds 3] [--cpus 1]``

The per-node accounting (``container.executor.Accounting``) is always on in
a container; its budget is 3%. With it on, a window is closed every second
(``Accounting.sample``, as a container's load reporter does). This runs,
for ``async def`` and plain callbacks:

* ``pingpong``, ``services``: bench_executor.py's chains (one message
  bounced between two nodes' subscriptions; each service call made from
  the previous response's done-callback), round trips per second: the
  loop's compiled chain and the worker threads' plain calls;
* ``streams``: a byte bounced between two nodes' asyncio tasks over a socket
  pair (asyncio streams): each round trip two transports' reads (readers a
  node registered, metered by the loop) and two task steps (metered by the
  task factory), the tasks started from the nodes' callbacks; the process's
  CPU per round trip (us: what the work costs, where the round trips per
  second, printed beside it, move by 20% from turn to turn with the wake-up
  latencies of a shared machine);
* three loads of ten nodes, each publishing at 100 Hz to the next one's
  subscription, the process's CPU:
* ``load``: from a ROS timer (bench_executor.py's);
* ``taskload``: from an asyncio task each node starts from its callback,
  ``await asyncio.sleep(0.01)`` between messages (its steps and its sleeps'
  timers metered as the node's);
* ``threadload``: from a thread each node starts from its callback,
  sleeping 10 ms between messages (each thread's CPU clock read every
  window).

Each round is one process: a rate or a load's CPU differs by up to 2x
from one process to the next on this VM (where the threads land, how the
host schedules them; ping-pong's rate from 21,700 to 38,100 round trips/s
between processes in one run), far more than 3%. So in each round the same
nodes move between two executors, accounting on and off, for ``--seconds``
each, alternating ``--turns`` (5) times, first on, then off first; a round's
figure is the median of its on/off ratios, the run's the median of its
rounds'.

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
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.benchmarks

from tests.benchmarks import cpus
from tests.benchmarks.bench_executor import load_nodes, sample_every_second

#: measure -> (what it prints, whether more is better).
MEASURES = {
    "pingpong": ("round trips/s", True),
    "services": ("service calls/s", True),
    "streams": ("streams CPU us/trip", False),
    "load": ("load CPU %", False),
    "taskload": ("task load CPU %", False),
    "threadload": ("thread load CPU %", False),
}
#: Round trips of a chain of callbacks, counted.
CHAINS = ("pingpong", "services")
KINDS = ("asyncio-async", "asyncio-plain")
#: Turns of each state per process (``--turns``).
TURNS = 5


def _stream_nodes(kind: str, stop: threading.Event) -> tuple[list[Any], list[int], Callable[[], None]]:
    """Two nodes bouncing a byte over a socket pair (asyncio streams), each from a task it starts
    from its first timer callback after ``rearm`` (``async def``: on the loop; plain: through
    ``executor.create_task``), on a new socket pair each time; the round trips counted; ``rearm``."""
    import asyncio
    import socket

    from rclpy.node import Node

    pinger, echoer = Node("bench_streams_ping"), Node("bench_streams_echo")
    count = [0]
    pair: list[socket.socket] = []
    armed = [False, False]

    async def echo() -> None:
        reader, writer = await asyncio.open_connection(sock=pair[1])
        while not stop.is_set():
            writer.write(await reader.readexactly(1))

    async def ping() -> None:
        reader, writer = await asyncio.open_connection(sock=pair[0])
        while not stop.is_set():
            writer.write(b"x")
            await reader.readexactly(1)
            count[0] += 1

    for index, (node, run) in enumerate(((echoer, echo), (pinger, ping))):

        def start(index: int = index, node: Any = node, run: Any = run) -> None:
            if armed[index]:
                return
            armed[index] = True
            if kind == "asyncio-async":
                asyncio.get_running_loop().create_task(run())
            else:
                node.executor.create_task(run())

        async def start_async(start: Any = start) -> None:
            start()

        # rclpy 9 annotates timer callbacks as plain; the executors run async ones.
        node.create_timer(0.01, start_async if kind == "asyncio-async" else start)  # type: ignore[arg-type, unused-ignore]

    def rearm() -> None:
        pair[:] = socket.socketpair()
        armed[:] = [False, False]

    return [echoer, pinger], count, rearm


def _chain_nodes(kind: str, variant: str) -> tuple[list[Any], list[int], Callable[[], None]]:
    """bench_executor.py's ``pingpong`` (a message bounced between two nodes' subscriptions) or
    ``services`` (each call made from the previous response's done-callback), started by a timer
    callback of the first node after each ``rearm``; the round trips counted.

    Each turn's chain carries the turn's number (the message's data; the call's done-callback
    holds it): what was in flight when the last executor stopped ends where it arrives, so one
    chain runs per turn."""
    from rclpy.client import Client
    from rclpy.node import Node
    from std_msgs.msg import Int64
    from std_srvs.srv import Trigger

    first, second = Node(f"bench_{variant}_a"), Node(f"bench_{variant}_b")
    count = [0]
    turn = [0]
    armed = [False]
    is_async = kind == "asyncio-async"
    kick: Callable[[], None]
    if variant == "pingpong":
        ping = first.create_publisher(Int64, "bench_ping", 10)
        pong = second.create_publisher(Int64, "bench_pong", 10)

        def echo(msg: Int64) -> None:
            pong.publish(msg)

        def got(msg: Int64) -> None:
            if msg.data == turn[0]:
                count[0] += 1
                ping.publish(msg)

        async def echo_async(msg: Int64) -> None:
            echo(msg)

        async def got_async(msg: Int64) -> None:
            got(msg)

        second.create_subscription(Int64, "bench_ping", echo_async if is_async else echo, 10)  # type: ignore[arg-type]
        first.create_subscription(Int64, "bench_pong", got_async if is_async else got, 10)  # type: ignore[arg-type]

        def kick() -> None:
            if ping.get_subscription_count() and pong.get_subscription_count():
                armed[0] = True
                ping.publish(Int64(data=turn[0]))

    else:

        def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            response.success = True
            return response

        async def answer_async(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            return answer(request, response)

        second.create_service(Trigger, "bench_trigger", answer_async if is_async else answer)
        client: Client[Any, Any] = first.create_client(Trigger, "bench_trigger")

        def call(number: int) -> None:
            client.call_async(Trigger.Request()).add_done_callback(lambda _: answered(number))

        def answered(number: int) -> None:
            if number == turn[0]:
                count[0] += 1
                call(number)

        def kick() -> None:
            if client.service_is_ready():
                armed[0] = True
                call(turn[0])

    def start() -> None:
        if not armed[0]:
            kick()

    async def start_async() -> None:
        start()

    first.create_timer(0.01, start_async if is_async else start)  # type: ignore[arg-type, unused-ignore]

    def rearm() -> None:
        turn[0] += 1
        armed[0] = False

    return [first, second], count, rearm


def _source_nodes(kind: str, variant: str, stop: threading.Event) -> tuple[list[Any], list[int], Callable[[], None]]:
    """Ten nodes that publish at 100 Hz to the next one's subscription from a task or a thread each
    starts from its first timer callback after :func:`rearm`; what they received; ``rearm``."""
    import asyncio

    from rclpy.node import Node
    from std_msgs.msg import Int64

    nodes = [Node(f"bench_{variant}_{i}") for i in range(10)]
    received = [0]
    is_async = kind == "asyncio-async"
    armed: list[bool] = [False] * len(nodes)

    def got(msg: Int64) -> None:
        received[0] += 1

    async def got_async(msg: Int64) -> None:
        got(msg)

    for i, node in enumerate(nodes):
        pub = node.create_publisher(Int64, f"{variant}_{i}", 10)
        node.create_subscription(Int64, f"{variant}_{(i + 1) % 10}", got_async if is_async else got, 10)  # type: ignore[arg-type]

        async def in_task(pub: Any = pub) -> None:
            while not stop.is_set():
                await asyncio.sleep(0.01)
                pub.publish(Int64(data=1))

        def in_thread(pub: Any = pub) -> None:
            while not stop.wait(0.01):
                pub.publish(Int64(data=1))

        def start(i: int = i, node: Any = node, in_task: Any = in_task, in_thread: Any = in_thread) -> None:
            if armed[i]:
                return
            armed[i] = True
            if variant == "threadload":
                threading.Thread(target=in_thread, daemon=True).start()
            elif is_async:
                asyncio.get_running_loop().create_task(in_task())
            else:
                node.executor.create_task(in_task())

        async def start_async(start: Any = start) -> None:
            start()

        node.create_timer(0.01, start_async if is_async else start)  # type: ignore[arg-type, unused-ignore]

    def rearm() -> None:
        armed[:] = [False] * len(nodes)

    return nodes, received, rearm


def _in_one_process(kind: str, seconds: float, variant: str, turns: int) -> list[tuple[float, float]]:
    """Under executors with the accounting on and off, taking turns in this process, ``(on, off)``
    pairs of: round trips per second (``pingpong``, ``services``: :func:`_chain_nodes`), a ten-node
    load's CPU % (``load``: bench_executor's; ``taskload``, ``threadload``: see
    :func:`_source_nodes`), or the CPU per round trip of ``streams`` (us, :func:`_stream_nodes`)."""
    import rclpy

    from container import AsyncioExecutor

    rclpy.init()
    stop = threading.Event()
    rearm: Callable[[], None] = lambda: None  # noqa: E731
    if variant == "load":
        nodes, received = load_nodes(kind)
    elif variant == "streams":
        nodes, received, rearm = _stream_nodes(kind, stop)
    elif variant in CHAINS:
        nodes, received, rearm = _chain_nodes(kind, variant)
    else:
        nodes, received, rearm = _source_nodes(kind, variant, stop)

    def turn(accounting: bool) -> float:
        executor = AsyncioExecutor(accounting=accounting)
        stop_sampling = sample_every_second(executor)
        stop.clear()
        rearm()
        for node in nodes:
            executor.add_node(node)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        settled = received[0] + 1000
        deadline = time.monotonic() + 30.0
        while received[0] < settled and time.monotonic() < deadline:
            time.sleep(0.05)
        cpu0, wall0, count0 = time.process_time(), time.perf_counter(), received[0]
        time.sleep(seconds)
        wall, cpu, count = time.perf_counter() - wall0, time.process_time() - cpu0, received[0] - count0
        if variant in CHAINS:
            value = count / wall
            state = "on" if accounting else "off"
            per_trip = 1e6 * cpu / max(count, 1)
            sys.stderr.write(f"{variant} accounting {state}: {per_trip:.1f} us of CPU per round trip\n")
        elif variant == "streams":
            sys.stderr.write(f"streams accounting {'on' if accounting else 'off'}: {count / wall:.0f} round trips/s\n")
            value = 1e6 * cpu / max(count, 1)
        else:
            value = 100.0 * cpu / wall
        stop.set()  # the turn's tasks and threads end (the tasks with the executor, at the latest)
        executor.shutdown(timeout_sec=2.0)
        stop_sampling()
        spinner.join(5.0)
        for node in nodes:
            executor.remove_node(node)
        return value

    pairs = []
    for index in range(turns):
        first = index % 2 == 0
        a = turn(first)
        b = turn(not first)
        pairs.append((a, b) if first else (b, a))
    return pairs


def _one_process_round(kind: str, seconds: float, variant: str, turns: int) -> tuple[float, float, float]:
    """One process of :func:`_in_one_process`: median on, median off, median of the on/off ratios."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(random.randint(1, 200))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    out = subprocess.run(
        [sys.executable, __file__, "--load-child", kind, str(seconds), variant, str(turns)],
        env=env, capture_output=True, text=True, timeout=turns * 2 * (seconds + 35) + 60, check=False,
    )
    rates: dict[str, list[float]] = {"on": [], "off": []}
    for line in out.stderr.splitlines():  # streams: the round trips per second of each turn
        if line.startswith("streams accounting "):
            state, _, rate = line.removeprefix("streams accounting ").partition(": ")
            rates[state].append(float(rate.split()[0]))
    if rates["on"] and rates["off"]:
        on_rate, off_rate = statistics.median(rates["on"]), statistics.median(rates["off"])
        print(f"  {kind} streams round trips/s: on {on_rate:.0f} off {off_rate:.0f}", flush=True)
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
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--only", choices=sorted(MEASURES), help="run one measurement")
    parser.add_argument("--turns", type=int, default=TURNS, help="turns of each state in a round's process")
    child = ("KIND", "SECONDS", "VARIANT", "TURNS")
    parser.add_argument("--load-child", nargs=4, metavar=child, help=argparse.SUPPRESS)
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    if args.load_child:
        kind, seconds, variant, turns = args.load_child
        print(json.dumps(_in_one_process(kind, float(seconds), variant, int(turns))), flush=True)
        os._exit(0)
    print(cpus.header(), flush=True)
    measures = [args.only] if args.only else list(MEASURES)
    results: dict[tuple[str, str, str], list[float]] = {}
    for round_index in range(args.rounds):
        for measure in measures:
            for kind in KINDS:
                on, off, pair_ratio = _one_process_round(kind, args.seconds, measure, args.turns)
                for state, value in (("on", on), ("off", off), ("ratio", pair_ratio)):
                    results.setdefault((measure, kind, state), []).append(value)
                line = f"round {round_index + 1} {measure:10} {kind:14} on {on:9.1f} off {off:9.1f}"
                line += f" on/off {pair_ratio:.3f}"
                print(line, flush=True)
    print(f"\n{'measure':20} {'callbacks':14} {'on':>10} {'off':>10} {'on/off':>8} {'by round':>20}  within 3%")
    for measure in measures:
        title, more_is_better = MEASURES[measure]
        for kind in KINDS:
            ons, offs = results[(measure, kind, "on")], results[(measure, kind, "off")]
            # Each round's own ratio (on and off in one process), their median.
            by_round = results[(measure, kind, "ratio")]
            ratio = statistics.median(by_round)
            within = ratio >= 0.97 if more_is_better else ratio <= 1.03
            print(
                f"{title:20} {kind.removeprefix('asyncio-'):14} {statistics.median(ons):10.1f}"
                f" {statistics.median(offs):10.1f} {ratio:7.3f}x {min(by_round):8.3f}-{max(by_round):.3f}x"
                f"  {'yes' if within else 'NO'}"
            )


if __name__ == "__main__":
    main()
