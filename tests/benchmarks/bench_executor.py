"""Executor benchmark: AsyncioExecutor against rclpy's executors, side by side.

Run: ``.venv/bin/python tests/benchmarks/bench_executor.py [--rounds 3] [--seconds 2]``

``--pythons .venvs/jazzy-3.11/bin/python .venv/bin/python`` runs every
measurement under each interpreter (each a set-up virtualenv), the
interpreters taking turns too: Python against Python, side by side, each
with its own rclpy peers.

``--engines compiled,python`` runs the AsyncioExecutor on each of its
engines (``CONTAINER_EXECUTOR_ENGINE``, each in its own child process, as
every contender): the Python engine's kinds (``asyncio-async@python``,
``asyncio-plain@python``) run right after their compiled siblings, and
their rates are printed over the compiled engine's too.

Three measurements, each executor in a fresh process, the executors taking
turns round after round so that drift on a shared machine hits all alike:

* **ping-pong**: node A publishes ``ping``, node B's callback publishes
  ``pong``, A's callback publishes the next ping; round trips per second.
* **gap**: node A runs a plain callback that blocks 1 s every 0.5 s while node
  B runs a 20 Hz timer; the largest gap between B's timer callbacks.
* **load**: ten nodes, each a 100 Hz timer publishing and a subscription;
  percent of one core the process uses.
* **services**: a client calls a service of another node in the same
  process, and each response's done-callback makes the next call; round
  trips per second.

Besides rclpy's three executors, ``floor`` is a bare loop on rclpy's wait set
with no executor at all (see :class:`BareLoop`): what any executor built on
rclpy's Python API can at best approach. For the load only, ``deadline``
goes further (see :class:`DeadlineLoop`): no rcl wait at all, the least a
Python loop over rclpy's timers and publishers spends; the load's CPU is
printed as a ratio to the floor's, round by round.

Printed as medians and as ratios to each of rclpy's three executors.
"""

from __future__ import annotations

import argparse
import contextlib
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
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.benchmarks

from tests.benchmarks import cpus

KINDS = {
    "asyncio-async": "AsyncioExecutor, async def callbacks",
    "asyncio-plain": "AsyncioExecutor, plain callbacks",
    "single": "rclpy SingleThreadedExecutor",
    "multi": "rclpy MultiThreadedExecutor",
    "events": "rclpy experimental EventsExecutor",
    "floor": "no executor: one bare rcl wait loop",
    "deadline": "no rcl wait: epoll to each deadline",
}

#: How long one ``spin_until_future_complete`` of the EventsExecutor may
#: last (see :func:`_spin_until`): a finite deadline, far beyond any run.
EVENTS_SPIN_S = 3600.0

#: ``off`` builds the AsyncioExecutor with ``accounting=False`` (bench_accounting.py).
ACCOUNTING_VARIABLE = "BENCH_ACCOUNTING"

#: The AsyncioExecutor's engines (see container/executor/_engine.py); a kind
#: ``asyncio-...@python`` is the AsyncioExecutor on the Python engine.
ENGINES = ("compiled", "python")
ENGINE_VARIABLE = "CONTAINER_EXECUTOR_ENGINE"
#: How the Python engine's kinds are named in the tables.
ENGINE_KINDS = {
    "asyncio-async@python": "Python engine, async def callbacks",
    "asyncio-plain@python": "Python engine, plain callbacks",
}

#: The floor has no callback groups, no isolation: ping-pong and load only.
FLOORLESS = {"gap", "services"}
#: Kinds that run one measurement only.
ONLY = {"deadline": "load"}


class _Stick:
    """What the measuring sticks below share with an executor: nodes added, a spin, a stop."""

    def __init__(self) -> None:
        self._nodes: list[Any] = []
        self._stop = False

    def add_node(self, node: Any) -> None:
        self._nodes.append(node)

    def shutdown(self, timeout_sec: float | None = None) -> None:
        self._stop = True


class BareLoop(_Stick):
    """The least any executor on rclpy's wait set can do: what sets the ceiling.

    One thread, one wait set built once (re-adding the handles before each
    wait, as rcl requires), take and call; no callback groups, no isolation,
    no error handling. Not an executor to use: a measuring stick.
    """

    def spin(self) -> None:
        from rclpy.utilities import get_default_context

        from container._compat import WaitSet

        subs = [sub for node in self._nodes for sub in node.subscriptions]
        timers = [timer for node in self._nodes for timer in node.timers]
        by_sub = {sub.handle.pointer: sub for sub in subs}
        by_timer = {timer.handle.pointer: timer for timer in timers}
        wait_set = WaitSet(len(subs), 0, len(timers), 0, 0, 0, get_default_context().handle)
        while not self._stop:
            wait_set.clear_entities()
            for sub in subs:
                wait_set.add_subscription(sub.handle)
            for timer in timers:
                wait_set.add_timer(timer.handle)
            wait_set.wait(100_000_000)
            for pointer in wait_set.get_ready_entities("timer"):
                timer = by_timer[pointer]
                timer.handle.call_timer()
                timer.callback()
            for pointer in wait_set.get_ready_entities("subscription"):
                sub = by_sub[pointer]
                taken = sub.handle.take_message(sub.msg_type, False)
                if taken is not None:
                    sub.callback(taken[0])


class DeadlineLoop(_Stick):
    """Less than any executor can do for the load: no rcl wait set at all.

    One thread sleeps in ``epoll`` until the soonest timer's deadline
    (kept in a heap, each timer's next one asked of rcl after its call),
    calls that rcl timer and its callback, then takes what its publish
    delivered in process (synchronously, as Fast DDS does, reported by the
    compiled notifier) with the compiled ``Taker`` and calls the
    subscriptions' callbacks. No callback groups, no asyncio, no guard
    conditions, nothing from other processes: a measuring stick for
    waiting outside ``rcl_wait``, the direction issue 31 part 3 asked to be
    measured, not an executor.
    """

    def spin(self) -> None:
        import heapq
        import select

        from rclpy.guard_condition import GuardCondition

        from container.executor._fastpath import SUBSCRIPTION, Notifier, Taker

        guard = GuardCondition(None, None)  # the notifier's, never waited on here
        notifier = Notifier(guard=guard.handle)
        takes = {}
        for sub in (sub for node in self._nodes for sub in node.subscriptions):
            notifier.watch(sub.handle, SUBSCRIPTION)
            takes[sub.handle.pointer] = (Taker(subscription=sub.handle, message_type=sub.msg_type), sub.callback)
        timers = [timer for node in self._nodes for timer in node.timers]
        now = time.monotonic_ns
        heap = [(now() + timer.handle.time_until_next_call(), index) for index, timer in enumerate(timers)]
        heapq.heapify(heap)
        poll = select.epoll().poll
        while not self._stop:
            due, index = heap[0]
            left = due - now()
            if left > 0:
                poll(min(left, 100_000_000) / 1e9)
                continue
            timer = timers[index]
            timer.handle.call_timer()
            timer.callback()
            for pointer, count in notifier.ready():
                taker, callback = takes[pointer]
                for _ in range(count):
                    message = taker.take()
                    if message is None:
                        break
                    callback(message)
            heapq.heapreplace(heap, (now() + timer.handle.time_until_next_call(), index))
        notifier.close()
        for taker, _ in takes.values():
            taker.close()
        guard.destroy()


def _base(kind: str) -> str:
    """The kind without its engine: ``asyncio-async`` of ``asyncio-async@python``."""
    return kind.partition("@")[0]


def _label(kind: str) -> str:
    return ENGINE_KINDS.get(kind) or KINDS[kind]


def _with_engines(kinds: list[str], engines: list[str]) -> list[str]:
    """``kinds`` with the AsyncioExecutor's on each of ``engines``: its compiled kinds
    where ``compiled`` is one, its Python engine's right after them where ``python`` is."""
    out: list[str] = []
    for kind in kinds:
        if not kind.startswith("asyncio"):
            out.append(kind)
            continue
        if "compiled" in engines:
            out.append(kind)
        if "python" in engines:
            out.append(f"{kind}@python")
    return out


def _engine_env(kind: str) -> dict[str, str]:
    """The engine a kind's child runs on: every AsyncioExecutor kind says which (none leaks in)."""
    if not kind.startswith("asyncio"):
        return {}
    return {ENGINE_VARIABLE: kind.partition("@")[2] or "compiled"}


def _executor(kind: str) -> Any:
    if kind == "floor":
        return BareLoop()
    if kind == "deadline":
        return DeadlineLoop()
    if kind.startswith("asyncio"):
        from container import AsyncioExecutor

        # bench_accounting.py measures the executor with its accounting off too.
        executor = AsyncioExecutor(accounting=os.environ.get(ACCOUNTING_VARIABLE, "on") != "off")
        sample_every_second(executor)
        return executor
    if kind == "events":
        from rclpy.experimental.events_executor import EventsExecutor

        return EventsExecutor()
    from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

    return SingleThreadedExecutor() if kind == "single" else MultiThreadedExecutor()


def sample_every_second(executor: Any) -> Callable[[], None]:
    """Close an accounting window every second while ``executor`` lives, as a container's
    load reporter does (``container._load``): what that costs is part of the accounting's cost.

    Returns what stops it: an executor shut down may live on a while (reference
    cycles), and its windows would go on being closed in the next executor's turn."""
    accounting = getattr(executor, "accounting", None)
    stopped = threading.Event()
    if accounting is None:
        return stopped.set
    import weakref

    alive = weakref.ref(accounting)

    def sample() -> None:
        while not stopped.is_set() and (held := alive()) is not None:
            held.sample()
            del held
            stopped.wait(1.0)

    threading.Thread(target=sample, name="sampler", daemon=True).start()
    return stopped.set


def _spin_until(
    executor: Any, done: threading.Event, limit: float, *, kick: Callable[[], None] | None = None
) -> None:
    """Spin ``executor`` on a helper thread until ``done`` is set, whatever its kind.

    The spin runs on a helper thread; this one runs ``kick`` and ends the
    spin.

    rclpy's EventsExecutor is spun until a future completes, with a finite
    timeout, rather than by ``spin()``: in the PyPI wheels (Jazzy 7.1.5;
    built against glibc 2.14's symbols, so ``std::condition_variable``
    waits on the steady clock through ``pthread_cond_timedwait`` on the
    system clock), ``spin()`` waits until ``steady_clock::time_point::max()``,
    whose conversion to the system clock overflows: every wait returns at
    once, the spinning thread loops at 90-100% of a core holding its event
    queue's lock, and no other thread gets it in. Its timers then never fire
    (their thread cannot queue them) and a call from another thread hangs.
    With a finite deadline its waits work (a 100 Hz timer: 200 firings in
    2 s, 2% of a core). A build against a newer glibc
    (``pthread_cond_clockwait``), as ROS's own packages are, has no such
    overflow; this is what its ``spin()`` does there.
    """
    stop: Any = None
    if type(executor).__name__ == "EventsExecutor":
        from rclpy.task import Future

        stop = Future()

        def spin() -> None:
            with contextlib.suppress(Exception):
                executor.spin_until_future_complete(stop, timeout_sec=EVENTS_SPIN_S)

        spinner = threading.Thread(target=spin, name="spin", daemon=True)
    else:
        spinner = threading.Thread(target=executor.spin, name="spin", daemon=True)
    spinner.start()
    if kick is not None:
        kick()
    done.wait(limit)
    done.set()
    if stop is not None:
        stop.set_result(None)
    threading.Thread(target=executor.shutdown, args=(0.5,), daemon=True).start()
    spinner.join(2.0)


def _chain_rate(
    executor: Any,
    count: list[int],
    done: threading.Event,
    seconds: float,
    *,
    start: Callable[[], None] | None = None,
    resend: Callable[[], None] | None = None,
) -> float:
    """Spin ``executor``; how fast a chain of callbacks raises ``count`` over
    ``seconds``, once it has counted 100 (warm-up). ``done`` is set at the end.

    Measured from this thread, not a timer: ``start`` kicks the chain once the spin runs, ``resend`` kicks it
    again every 2 s until it counts (a lost first kick).
    """
    rate: list[float] = []

    def measure() -> None:
        if start is not None:
            start()
        kicked = time.monotonic()
        deadline = kicked + 30.0
        while count[0] < 100 and time.monotonic() < deadline:
            if resend is not None and time.monotonic() - kicked > 2.0:
                resend()
                kicked = time.monotonic()
            time.sleep(0.01)
        first, t0 = count[0], time.perf_counter()
        time.sleep(seconds)
        rate.append((count[0] - first) / (time.perf_counter() - t0))
        done.set()

    _spin_until(executor, done, seconds + 40.0, kick=measure)
    return rate[0] if rate else float("nan")


def ping_pong(kind: str, seconds: float) -> float:
    """Round trips per second of one message bounced between two nodes.

    Counted by a helper thread over a window of ``seconds`` (the callbacks do
    nothing but count and publish the message they got): one chain, started
    by a single ping published before the spin once both topics are matched
    (publishing from another thread while the EventsExecutor spins can
    deadlock it, seen here; a lost first ping is sent again after 2 s).
    """
    import rclpy
    from rclpy.node import Node
    from std_msgs.msg import Int64

    rclpy.init()
    a, b = Node("bench_a"), Node("bench_b")
    ping = a.create_publisher(Int64, "ping", 10)
    pong = b.create_publisher(Int64, "pong", 10)
    count = [0]

    def echo(msg: Int64) -> None:
        pong.publish(msg)

    def got(msg: Int64) -> None:
        count[0] += 1
        ping.publish(msg)

    async def echo_async(msg: Int64) -> None:
        pong.publish(msg)

    async def got_async(msg: Int64) -> None:
        count[0] += 1
        ping.publish(msg)

    is_async = kind == "asyncio-async"
    b.create_subscription(Int64, "ping", echo_async if is_async else echo, 10)  # type: ignore[arg-type]  # rclpy types only plain callbacks
    a.create_subscription(Int64, "pong", got_async if is_async else got, 10)  # type: ignore[arg-type]
    executor = _executor(kind)
    executor.add_node(a)
    executor.add_node(b)
    deadline = time.monotonic() + 30.0
    while (ping.get_subscription_count() < 1 or pong.get_subscription_count() < 1) and time.monotonic() < deadline:
        time.sleep(0.01)
    ping.publish(Int64(data=0))
    return _chain_rate(executor, count, threading.Event(), seconds, resend=lambda: ping.publish(Int64(data=0)))


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


def load(kind: str, seconds: float) -> float:
    """Percent of one core used by ten nodes, each a 100 Hz timer publishing and a subscription.

    The messages received per second go to stderr (1,000 when nothing is
    dropped): an executor that cannot keep up shows it there.
    """
    import rclpy

    rclpy.init()
    nodes, received = load_nodes(kind)
    executor = _executor(kind)
    for node in nodes:
        executor.add_node(node)
    done = threading.Event()
    result: list[float] = []

    def measure() -> None:
        # Discovery and warm-up: messages flow for a second before measuring.
        deadline = time.monotonic() + 30.0
        while received[0] < 1000 and time.monotonic() < deadline:
            time.sleep(0.05)
        cpu0, wall0, count0 = time.process_time(), time.perf_counter(), received[0]
        time.sleep(seconds)
        cpu1, wall1, count1 = time.process_time(), time.perf_counter(), received[0]
        result.append(100.0 * (cpu1 - cpu0) / (wall1 - wall0))
        sys.stderr.write(f"messages/s {(count1 - count0) / (wall1 - wall0):.0f}\n")
        done.set()

    threading.Thread(target=measure, daemon=True).start()
    _spin_until(executor, done, seconds + 60.0)
    return result[0] if result else float("nan")


def load_nodes(kind: str, *, count: int = 10) -> tuple[list[Any], list[int]]:
    """The nodes of :func:`load` (rclpy initialised), and the counts their callbacks raise:
    messages received, timer firings.

    ``count`` nodes, each firing every ``count`` ms: 1,000 firings and 1,000
    messages a second in all, whatever the count (bench_scale.py's curve).
    """
    from rclpy.node import Node
    from std_msgs.msg import Int64

    nodes = [Node(f"bench_load_{i}") for i in range(count)]
    received = [0, 0]
    is_async = kind == "asyncio-async"
    for i, node in enumerate(nodes):
        pub = node.create_publisher(Int64, f"load_{i}", 10)

        def fire(pub: Any = pub) -> None:
            received[1] += 1
            pub.publish(Int64(data=1))

        def got(msg: Int64) -> None:
            received[0] += 1

        async def fire_async(pub: Any = pub) -> None:
            fire(pub)

        async def got_async(msg: Int64) -> None:
            got(msg)

        # rclpy 9 annotates timer callbacks as plain; the executors run async ones.
        node.create_timer(count / 1000, fire_async if is_async else fire)  # type: ignore[arg-type, unused-ignore]
        node.create_subscription(Int64, f"load_{(i + 1) % count}", got_async if is_async else got, 10)  # type: ignore[arg-type]
    return nodes, received


def services(kind: str, seconds: float) -> float:
    """Round trips per second of service calls, each made from the previous
    response's done-callback (a client and a service in two nodes of one
    process; the first call is made from the measuring thread, not a timer)."""
    import rclpy
    from rclpy.client import Client
    from rclpy.node import Node
    from rclpy.task import Future
    from std_srvs.srv import Trigger

    rclpy.init()
    server, caller = Node("bench_server"), Node("bench_caller")

    def answer(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success = True
        return response

    async def answer_async(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return answer(request, response)

    server.create_service(Trigger, "bench_trigger", answer_async if kind == "asyncio-async" else answer)
    client: Client[Any, Any] = caller.create_client(Trigger, "bench_trigger")
    executor = _executor(kind)
    executor.add_node(server)
    executor.add_node(caller)
    if not client.wait_for_service(timeout_sec=30.0):
        return float("nan")
    count = [0]
    done = threading.Event()

    def answered(_: Future[Any]) -> None:
        count[0] += 1
        if not done.is_set():
            client.call_async(Trigger.Request()).add_done_callback(answered)

    def start() -> None:
        client.call_async(Trigger.Request()).add_done_callback(answered)

    return _chain_rate(executor, count, done, seconds, start=start)


MEASURES: dict[str, Callable[[str, float], float]] = {
    "pingpong": ping_pong,
    "gap": timer_gap,
    "load": load,
    "services": services,
}


def _child(measure: str, kind: str, seconds: float) -> None:
    if kind.startswith("asyncio"):
        try:
            from container.executor import _engine
        except ImportError:  # code from before the engines (--pythons): compiled only
            engine = "compiled"
        else:
            engine = _engine.ENGINE
        if (kind.partition("@")[2] or "compiled") != engine:
            sys.exit(f"{kind} asked for, the executor runs on the {engine} engine")
    value = MEASURES[measure](_base(kind), seconds)
    print(json.dumps({"value": value}), flush=True)
    os._exit(0)  # rclpy's MultiThreadedExecutor may leave threads behind


def _run_child(
    measure: str, kind: str, seconds: float, python: str, *, env_extra: dict[str, str] | None = None
) -> tuple[float, str]:
    """Run one measurement in a fresh process of ``python``: its value and its note (stderr's last line)."""
    env = dict(os.environ) | (env_extra or {})
    env["ROS_DOMAIN_ID"] = str(random.randint(1, 200))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    cmd = [python, __file__, "--child", measure, kind, str(seconds)]
    try:
        out = subprocess.run(
            cmd, env=env, capture_output=True, text=True, timeout=seconds + 90, check=False
        )
    except subprocess.TimeoutExpired:
        return float("nan"), "timed out"
    note = next((line for line in reversed(out.stderr.splitlines()) if line.startswith("messages/s")), "")
    for line in out.stdout.splitlines():
        if line.startswith("{"):
            return float(json.loads(line)["value"]), note
    sys.stderr.write(out.stderr[-2000:])
    return float("nan"), "failed"


def _running_order(kinds: list[str], round_index: int) -> list[str]:
    """The order one round runs ``kinds`` in: each of this project's kinds right
    beside the EventsExecutor (the machine drifts within seconds, so a ratio
    is fairest between neighbours), and reversed every other round so that
    neither runs first every time."""
    paired = ["asyncio-async", "asyncio-async@python", "events", "asyncio-plain", "asyncio-plain@python"]
    order = [kind for kind in paired if kind in kinds] + [kind for kind in kinds if kind not in paired]
    return order if round_index % 2 == 0 else order[::-1]


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def _ratio(mine: float, other: float) -> float:
    """``mine / other``; nan when the peer got nothing through (rclpy's
    MultiThreadedExecutor can end a ping-pong window at 0 round trips)."""
    return mine / other if other else float("nan")


def _x(ratio: float) -> str:
    """A ratio as printed: two decimals, none once it is in the hundreds."""
    return f"{ratio:.2f}x" if not ratio >= 100 else f"{ratio:.0f}x"


def _python_label(python: str) -> str:
    """``3.12``: the version of the interpreter at ``python``."""
    out = subprocess.run(
        [python, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"],
        capture_output=True, text=True, check=True,
    )
    return out.stdout.strip()


Results = dict[tuple[str, str], list[float]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--only", choices=sorted(MEASURES), help="run one measurement")
    parser.add_argument("--kinds", nargs="+", choices=sorted(KINDS), default=list(KINDS))
    parser.add_argument(
        "--engines", type=_engine_list, default=["compiled"], metavar="ENGINE[,ENGINE]",
        help="the AsyncioExecutor's engines to measure, side by side: compiled (the default), python, or both",
    )
    parser.add_argument(
        "--pythons", nargs="+", default=[sys.executable], metavar="PYTHON",
        help="interpreters to measure under, side by side (each a set-up virtualenv's): two "
        "virtualenvs of one Python compare two versions of the code (a git worktree's .venv)",
    )
    parser.add_argument("--child", nargs=3, metavar=("MEASURE", "KIND", "SECONDS"))
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    if args.child:
        _child(args.child[0], args.child[1], float(args.child[2]))
    print(cpus.header(), flush=True)
    kinds = _with_engines([kind for kind in KINDS if kind in args.kinds], args.engines)
    pythons: dict[str, str] = {}
    for python in args.pythons:
        label = _python_label(python)
        # Two virtualenvs of one Python (two versions of the code) by their paths.
        pythons[f"{label} {python}" if any(label == other.split()[0] for other in pythons) else label] = python
    if len(set(map(lambda label: label.split()[0], pythons))) < len(pythons):
        pythons = {f"{label.split()[0]} {python}": python for label, python in pythons.items()}
    results: dict[str, Results] = {label: {} for label in pythons}
    for round_index in range(args.rounds):
        for measure in [args.only] if args.only else MEASURES:
            labels = list(pythons) if round_index % 2 == 0 else list(pythons)[::-1]
            for label in labels:
                for kind in _running_order(kinds, round_index):
                    if (measure in FLOORLESS and kind == "floor") or ONLY.get(kind, measure) != measure:
                        continue
                    seconds = args.seconds if measure == "pingpong" else max(args.seconds, 3.0)
                    value, note = _run_child(measure, kind, seconds, pythons[label], env_extra=_engine_env(kind))
                    results[label].setdefault((measure, kind), []).append(value)
                    where = f"python {label} " if len(pythons) > 1 else ""
                    print(f"round {round_index + 1} {where}{measure:8} {kind:20} {value:10.1f}  {note}", flush=True)
    for label in pythons:
        if len(pythons) > 1:
            print(f"\n===== Python {label} ({pythons[label]})")
        _report(results[label], kinds)
    if len(pythons) > 1:
        _compare(results, kinds)


def _engine_list(text: str) -> list[str]:
    engines = [engine.strip() for engine in text.split(",") if engine.strip()]
    unknown = sorted(set(engines) - set(ENGINES))
    if unknown or not engines:
        raise argparse.ArgumentTypeError(f"engines are a comma-separated list of {', '.join(ENGINES)}")
    return engines


def _report_engines(results: Results, kinds: list[str]) -> None:
    """Each Python engine kind's rates over its compiled sibling's, round by round (same round)."""
    pairs = [(kind, _base(kind)) for kind in kinds if "@" in kind and _base(kind) in kinds]
    if not pairs:
        return
    print("\nPython engine over the compiled engine, round by round (same round; load: CPU):")
    for measure in MEASURES:
        for mine, compiled in pairs:
            ratios = [
                _ratio(a, b)
                for a, b in zip(results.get((measure, mine), []), results.get((measure, compiled), []), strict=False)
            ]
            if ratios:
                listed = " ".join(_x(r) for r in ratios)
                print(f"  {measure:8} {_label(mine):38} {listed}   (median {_x(_median(ratios))})")


def _report(results: Results, kinds: list[str]) -> None:
    print()
    rt = {kind: results.get(("pingpong", kind), []) for kind in kinds}
    print(
        f"{'executor':38} {'round trips/s':>13} {'vs single':>9} {'vs multi':>9} {'vs events':>9}"
        f" {'20 Hz gap':>10} {'load CPU':>9}"
    )
    single, multi, events = (_median(rt.get(peer, [])) for peer in ("single", "multi", "events"))
    for kind in kinds:
        mine = _median(rt[kind])
        gap = _median(results.get(("gap", kind), []))
        cpu = _median(results.get(("load", kind), []))
        print(
            f"{_label(kind):38} {mine:13.0f} {_x(_ratio(mine, single)):>9} {_x(_ratio(mine, multi)):>9}"
            f" {_x(_ratio(mine, events)):>9}"
            f" {gap:7.0f} ms {cpu:8.1f}%"
        )
    calls = {kind: results.get(("services", kind), []) for kind in kinds}
    if any(calls.values()):
        print(f"\n{'service calls':38} {'round trips/s':>13} {'vs single':>9} {'vs multi':>9} {'vs events':>9}")
        peers = [_median(calls.get(peer, [])) for peer in ("single", "multi", "events")]
        for kind in kinds:
            if calls[kind]:
                mine = _median(calls[kind])
                listed = " ".join(f"{_x(_ratio(mine, peer)):>9}" for peer in peers)
                print(f"{_label(kind):38} {mine:13.0f} {listed}")
    _report_engines(results, kinds)
    loads = {kind: results.get(("load", kind), []) for kind in kinds}
    floors = loads.get("floor", [])
    if floors:
        print("\nload CPU, round by round, over the floor's (same round):")
        for kind in kinds:
            ratios = [_ratio(mine, floor) for mine, floor in zip(loads[kind], floors, strict=False)]
            if kind == "floor" or not ratios:
                continue
            listed = " ".join(_x(r) for r in ratios)
            print(f"{_label(kind):38} {listed}   (median {_x(_median(ratios))}, min {_x(min(ratios))})")
    for title, values in (("round trips", rt), ("service calls", calls)):
        if not any(values.values()):
            continue
        print(f"\n{title}, round by round (same round's peer):")
        for peer in ("single", "multi", "events"):
            peers = values.get(peer, [])
            if not peers:
                continue
            for kind in kinds:
                ratios = [_ratio(mine, other) for mine, other in zip(values[kind], peers, strict=False)]
                if kind == peer or not ratios:
                    continue
                listed = " ".join(_x(r) for r in ratios)
                print(
                    f"{_label(kind):38} vs {peer:6} {listed}"
                    f"   (median {_x(_median(ratios))}, min {_x(min(ratios))})"
                )


def _compare(results: dict[str, Results], kinds: list[str]) -> None:
    """Each Python's ratios to its own peers, side by side, and one Python's rates over another's."""
    labels = list(results)
    print("\n===== Pythons side by side: ping-pong ratio to the same Python's peer (median of rounds)")
    print(f"{'executor':38} " + " ".join(f"{label + ' vs ' + peer:>16}" for peer in ("single", "events")
                                          for label in labels))
    for kind in kinds:
        cells = []
        for peer in ("single", "events"):
            for label in labels:
                mine = results[label].get(("pingpong", kind), [])
                other = results[label].get(("pingpong", peer), [])
                ratios = [_ratio(a, b) for a, b in zip(mine, other, strict=False)]
                cells.append(f"{_x(_median(ratios)) if ratios else '-':>16}")
        print(f"{_label(kind):38} " + " ".join(cells))
    base = labels[0]
    for label in labels[1:]:
        print(f"\nrates under Python {label} over {base} (medians):")
        for (measure, kind), values in sorted(results[label].items()):
            before = results[base].get((measure, kind), [])
            if before and values:
                print(f"  {measure:8} {_label(kind):38} {_x(_ratio(_median(values), _median(before)))}")


if __name__ == "__main__":
    main()
