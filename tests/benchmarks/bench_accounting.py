"""What the executor's accounting costs: the same work with it on and off, side by side.

Run: ``.venv/bin/python tests/benchmarks/bench_accounting.py [--pairs 12] [--seconds 2] [--cpus 1]
[--only MEASURE] [--kinds KIND ...] [--null] [--per-process PAIRS]``

The per-node accounting (``container.executor.Accounting``) is always on in
a container; its budget is 3%. With it on, a window is closed every second
(``Accounting.sample``, as a container's load reporter does). This runs,
for ``async def`` and plain callbacks:

* ``pingpong``, ``services``: bench_executor.py's chains (one message
  bounced between two nodes' subscriptions; each service call made from
  the previous response's done-callback): the loop's compiled chain and
  the worker threads' plain calls;
* ``streams``: a byte bounced between two nodes' asyncio tasks over a socket
  pair (asyncio streams): each round trip two transports' reads (readers a
  node registered, metered by the loop) and two task steps (metered by the
  task factory), the tasks started from the nodes' callbacks;
* three loads of ten nodes, each publishing at 100 Hz to the next one's
  subscription:
* ``load``: from a ROS timer (bench_executor.py's);
* ``taskload``: from an asyncio task each node starts from its callback,
  ``await asyncio.sleep(0.01)`` between messages (its steps and its sleeps'
  timers metered as the node's);
* ``threadload``: from a thread each node starts from its callback,
  sleeping 10 ms between messages (each thread's CPU clock read every
  window).

Each is measured as what it costs: the process's CPU per unit of work
(a round trip, a message), in microseconds.

The method. On this VM the same work's CPU moves by a fifth from one
second to the next, and by up to 2x from one process to the next (where
the threads land): far more than 3%, and no number of turns in one process
at a time brought it down (the earlier method: 3 rounds of 5 turns each
way, 22 minutes, medians scattered 5-10%). So two processes of the same
nodes run at once, one with the accounting on and one off, and swap at
every turn (a crossover): what the host does at a moment it does to both,
and what one process is slower by for good it is slower by on and off
alike; a pair of turns gives ``sqrt((A_on / B_off) * (B_on / A_off))``, in
which both cancel. Printed: the geometric mean of ``--pairs`` such
estimates with a 95% bootstrap interval. ``--null`` runs the same with the
accounting off on both sides: the method's own error, which reads 1.00.
"""

from __future__ import annotations

import argparse
import contextlib
import math
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
    "pingpong": "ping-pong round trip",
    "services": "service call",
    "streams": "streams round trip",
    "load": "load message",
    "taskload": "task load message",
    "threadload": "thread load message",
}
#: Round trips of a chain of callbacks, counted.
CHAINS = ("pingpong", "services")
KINDS = ("asyncio-async", "asyncio-plain")
#: Pairs of turns for each measure and kind (``--pairs``).
PAIRS = 12
#: Tries of a turn whose work does not settle.
TRIES = 3
#: The accounting's budget: CPU per unit of work on/off.
BUDGET = 1.03


def _stale(kind: str, node: Any) -> bool:
    """Whether an ``async def`` callback runs on the last turn's loop, which is shutting down (a
    task it started would end with it, and the turn's own callback would find the node armed)."""
    import asyncio

    return kind == "asyncio-async" and asyncio.get_running_loop() is not node.executor.loop


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
            if armed[index] or _stale(kind, node):
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
        for end in pair:  # the last turn's tasks, if any still wait, end with their pair
            end.close()
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
            if armed[i] or _stale(kind, node):
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


def _serve(kind: str, variant: str) -> None:
    """A child's side: build the nodes, then answer the parent's lines on stdin.

    ``turn on|off``: the nodes move to a new executor with the accounting on
    or off, and ``ready`` is answered once their work has settled (200 more
    units of it and half a second at least); ``mark``: this process's CPU
    clock and the units of work so far; ``end``: the turn's executor shut
    down (its tasks and threads ended); ``quit``."""
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
    executor: Any = None
    spinner: threading.Thread | None = None
    stop_sampling: Callable[[], None] = lambda: None  # noqa: E731

    def answer(text: str) -> None:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()

    for line in sys.stdin:
        command = line.split()
        if command[0] == "turn":
            executor = AsyncioExecutor(accounting=command[1] == "on")
            stop_sampling = sample_every_second(executor)
            stop.clear()
            rearm()
            for node in nodes:
                executor.add_node(node)
            spinner = threading.Thread(target=executor.spin, daemon=True)
            spinner.start()
            settled, soonest = received[0] + 200, time.monotonic() + 0.5
            deadline = time.monotonic() + 30.0
            while (received[0] < settled or time.monotonic() < soonest) and time.monotonic() < deadline:
                time.sleep(0.02)
            answer("ready" if received[0] >= settled else "stalled")
        elif command[0] == "mark":
            answer(f"mark {time.process_time_ns()} {received[0]}")
        elif command[0] == "end":
            stop.set()  # the turn's tasks and threads end (the tasks with the executor, at the latest)
            executor.shutdown(timeout_sec=2.0)
            stop_sampling()
            if spinner is not None:
                spinner.join(5.0)
            for node in nodes:
                executor.remove_node(node)
            executor = None
            answer("ended")
        elif command[0] == "quit":
            break


class _Child:
    """One child process of :func:`_serve`, in a ROS domain of its own (the two children's
    nodes have the same names and topics)."""

    def __init__(self, kind: str, variant: str, domain: int) -> None:
        env = dict(os.environ)
        env["ROS_DOMAIN_ID"] = str(domain)
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        self.process = subprocess.Popen(
            [sys.executable, __file__, "--serve", kind, variant],
            env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1,
        )  # fmt: skip

    def send(self, command: str) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write(command + "\n")
        self.process.stdin.flush()

    def reply(self) -> str:
        assert self.process.stdout is not None
        line: str = self.process.stdout.readline()
        if not line:
            raise RuntimeError(f"a benchmark child ended (status {self.process.wait()})")
        return line.strip()

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.send("quit")
        try:
            self.process.wait(20)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


def _ask_all(children: list[_Child], command: str) -> list[str]:
    """``command`` to every child at once (their answers then come from one moment), and their replies."""
    for child in children:
        child.send(command)
    return [child.reply() for child in children]


def _crossover(
    kind: str, variant: str, seconds: float, pairs: int, *, null: bool = False, per_process: int = 0
) -> tuple[list[float], list[float], list[float]]:
    """Two processes of the same nodes run at once, one with the accounting on and one off, and
    swap at every turn; each turn's figure is a process's CPU per unit of work (round trip or
    message) over ``seconds``. Returns the pairs' on/off estimates, and the turns' CPU per unit
    with the accounting on and off (us).

    What the host does to one process at a moment it does to the other (they share the
    moment), and what one process is slower by for good (where its threads landed) it is
    slower by on and off alike: a pair of turns ``t`` (A on, B off) and ``t + 1`` (A off,
    B on) gives ``sqrt((A_t / B_t) * (B_t+1 / A_t+1))``, where both cancel.

    ``null``: the accounting off in both (what the method reads when nothing differs: 1.0, give
    or take its own error).

    ``per_process``: after that many pairs, two new processes take over (0: the same two
    throughout). What makes one process's accounting dearer than another's for good (where
    its memory and threads landed) cancels in neither a pair nor the mean of one pair of
    processes; new ones sample it, and the interval then covers it."""
    domains = random.sample(range(1, 200), 2)
    children = [_Child(kind, variant, domain) for domain in domains]
    estimates: list[float] = []
    on_costs: list[float] = []
    off_costs: list[float] = []
    try:
        for index in range(pairs):
            if per_process > 0 and index > 0 and index % per_process == 0:
                for child in children:
                    child.close()
                children = [_Child(kind, variant, domain) for domain in domains]
            per_turn: list[tuple[float, float]] = []
            a_on_first = index % 2 == 0
            for a_on in (a_on_first, not a_on_first):
                states = ("on", "off") if a_on else ("off", "on")
                for attempt in range(1, TRIES + 1):
                    for child, state in zip(children, states, strict=True):
                        child.send(f"turn {'off' if null else state}")
                    if all(reply == "ready" for reply in [child.reply() for child in children]):
                        break
                    # Seen about once in 50 turns of streams until the executor held its tasks
                    # (docs/benchmarks.md, "What the accounting costs"): said, and made again.
                    sys.stderr.write(f"  {variant} ({kind}): a turn's work did not settle in 30 s (try {attempt})\n")
                    _ask_all(children, "end")
                else:
                    raise RuntimeError(f"{variant} ({kind}): a turn's work did not settle in {TRIES} tries")
                first = _ask_all(children, "mark")
                time.sleep(seconds)
                costs = []
                for before, after in zip(first, _ask_all(children, "mark"), strict=True):
                    (_, cpu0, units0), (_, cpu1, units1) = before.split(), after.split()
                    costs.append((int(cpu1) - int(cpu0)) / 1000 / max(int(units1) - int(units0), 1))
                _ask_all(children, "end")
                on, off = (costs[0], costs[1]) if a_on else (costs[1], costs[0])
                on_costs.append(on)
                off_costs.append(off)
                per_turn.append((on, off))
            (on1, off1), (on2, off2) = per_turn
            estimates.append(math.sqrt((on1 / off1) * (on2 / off2)))
            sys.stderr.write(f"  pair {index + 1}: on/off {estimates[-1]:.3f}\n")
    finally:
        for child in children:
            child.close()
    return estimates, on_costs, off_costs


def _geometric_mean(values: list[float]) -> float:
    return math.exp(statistics.fmean(math.log(value) for value in values))


def _interval(values: list[float], *, draws: int = 4000) -> tuple[float, float]:
    """A 95% bootstrap interval of the geometric mean of ``values``."""
    rng = random.Random(1)
    means = sorted(_geometric_mean(rng.choices(values, k=len(values))) for _ in range(draws))
    return means[int(0.025 * draws)], means[int(0.975 * draws) - 1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=PAIRS, help="pairs of turns for each measure and kind")
    parser.add_argument("--seconds", type=float, default=2.0, help="each turn's window")
    parser.add_argument("--only", choices=sorted(MEASURES), help="run one measurement")
    parser.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS))
    parser.add_argument("--null", action="store_true", help="the accounting off on both sides: the method's own error")
    parser.add_argument(
        "--per-process", type=int, default=0, metavar="PAIRS",
        help="two new processes after every PAIRS pairs (0: the same two throughout)",
    )  # fmt: skip
    parser.add_argument("--serve", nargs=2, metavar=("KIND", "VARIANT"), help=argparse.SUPPRESS)
    cpus.add_option(parser)
    args = parser.parse_args()
    if args.serve:
        _serve(*args.serve)
        os._exit(0)
    cpus.pin(parser, args.cpus)
    print(cpus.header(), flush=True)
    measures = [args.only] if args.only else list(MEASURES)
    rows = []
    for measure in measures:
        for kind in args.kinds:
            estimates, on, off = _crossover(
                kind, measure, args.seconds, args.pairs, null=args.null, per_process=args.per_process
            )
            low, high = _interval(estimates)
            ratio = _geometric_mean(estimates)
            rows.append((measure, kind, statistics.median(on), statistics.median(off), ratio, low, high))
            print(f"{measure:10} {kind:14} on/off {rows[-1][4]:.3f} (95% {low:.3f}-{high:.3f})", flush=True)
    print(f"\n{'CPU per':22} {'callbacks':9} {'on us':>8} {'off us':>8} {'on/off':>8} {'95% interval':>14}  within 3%")
    for measure, kind, on_cost, off_cost, ratio, low, high in rows:
        # Within for sure, within by the estimate but not by all the interval, or not.
        within = "yes" if high <= BUDGET else "by estimate" if ratio <= BUDGET else "NO"
        print(
            f"{MEASURES[measure]:22} {kind.removeprefix('asyncio-'):9} {on_cost:8.1f} {off_cost:8.1f}"
            f" {ratio:7.3f}x {low:6.3f}-{high:.3f}x  {within}"
        )


if __name__ == "__main__":
    main()
