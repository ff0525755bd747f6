"""Start-up and scale: N nodes from a file, a container against plain rclpy, side by side.

Run from the repository root::

    .venv/bin/python tests/benchmarks/bench_startup.py [--nodes 100] [--rounds 3] [--mixes idle demo]

Each round, for each node mix, the two peers run one after the other:

* ``container``: ``container run FILE`` with N nodes (``autostart: true``),
  timed from the process's start to its log line ``Container ... ready with
  N node(s)``;
* ``rclpy``: one plain Python process that creates the *same node classes*
  with the same names and parameters and calls ``trigger_configure()`` and
  ``trigger_activate()`` on each, timed from its start to its last
  activation. It never spins: nothing of its nodes runs (no timer, no
  message, no service), which is the floor a container that serves its
  nodes while it loads them is compared to (the ratio printed);
* ``rclpy+spin``: the same, with a ``SingleThreadedExecutor`` spinning on
  a thread and each node added to it once created, as a plain rclpy process
  that serves its nodes does. Shown for reference: Fast DDS creates an
  endpoint more slowly while a waiting wait set holds many others, which is
  why the container constructs a file's nodes before it serves them.

Both peers and the container import with a bytecode cache, as an installed
package does (the first round, which writes it, is a warm-up and not
counted); ``PYTHONDONTWRITEBYTECODE`` is dropped for the runs.

Mixes: ``idle`` is N ``bench_startup::Idle`` nodes (a
:class:`container.LifecycleNode` that declares two parameters and creates
nothing else); ``demo`` is ``lifecycle_container::Talker`` and ``Listener``
alternating, the talkers at 2 Hz on one ``chatter`` topic heard by every
listener, which logs each message: with 50 of each, 5,000 log lines a
second once all are up, which the container runs while it loads the rest
(the rclpy peer runs none of it). ``--empty`` also times an empty container.

Also read from ``/proc``: the container's threads when it is ready and
again ``--settle`` seconds later (idle worker threads exit), and the rclpy
peer's at its end; and the container's shutdown, from a SIGINT sent then
to its exit (its nodes going down their lifecycle and destroyed). ``--pythons`` runs everything under several
interpreters (each a set-up virtualenv's, e.g. a git worktree's ``.venv``):
the code before and after a change, side by side.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # tests.benchmarks

from tests.benchmarks import cpus  # noqa: E402

#: The idle node type, installed as a plugin distribution of its own.
NODES_MODULE = '''
from container import LifecycleNode, hookimpl


class Idle(LifecycleNode):
    """A lifecycle node with two parameters and nothing else."""

    def __init__(self, node_name="idle", **kwargs):
        super().__init__(node_name, **kwargs)
        self.declare_parameter("rate", 2.0)
        self.declare_parameter("message", "Hello World")


@hookimpl
def register_node_types(register):
    register(Idle)
'''

#: The rclpy peer: the same classes, created and brought up in one process.
PEER = r'''
import os, sys
import rclpy
from rclpy.parameter import Parameter

mix, count, spin = sys.argv[1], int(sys.argv[2]), sys.argv[3] == "spin"
if mix == "idle":
    from bench_startup_nodes import Idle
    classes = [Idle]
else:
    from container.demo import Listener, Talker
    classes = [Talker, Listener]
rclpy.init()
if spin:
    import threading
    from rclpy.executors import SingleThreadedExecutor
    executor = SingleThreadedExecutor()
    threading.Thread(target=executor.spin, daemon=True).start()
# What the container gives every node it loads.
overrides = [Parameter("start_type_description_service", value=False)]
nodes = []
for i in range(count):
    node = classes[i % len(classes)](f"n{i}", parameter_overrides=overrides)
    if spin:
        executor.add_node(node)
    node.trigger_configure()
    node.trigger_activate()
    nodes.append(node)
print("ready", len(os.listdir(f"/proc/{os.getpid()}/task")), flush=True)
sys.stdin.read()
os._exit(0)  # a spinning executor's thread would hold up the exit
'''

_MIX_TYPES = {
    "idle": ["bench_startup::Idle"],
    "demo": ["lifecycle_container::Talker", "lifecycle_container::Listener"],
}


@dataclass
class Sample:
    seconds: list[float] = field(default_factory=list)
    #: Per round, the container's time over this peer's, measured back to back.
    ratios: list[float] = field(default_factory=list)
    threads_ready: list[int] = field(default_factory=list)
    threads_settled: list[int] = field(default_factory=list)
    #: The container's: from SIGINT (once settled) to its exit.
    shutdown: list[float] = field(default_factory=list)


def write_site(root: Path) -> Path:
    """A plugin distribution ``bench-startup`` holding :data:`NODES_MODULE`."""
    site = root / "site"
    info = site / "bench_startup-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: bench-startup\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[container.plugins]\nbench_startup = bench_startup_nodes\n")
    (site / "bench_startup_nodes.py").write_text(NODES_MODULE)
    (root / "peer.py").write_text(PEER)
    return site


def write_config(root: Path, mix: str, count: int) -> Path:
    types = _MIX_TYPES[mix]
    lines = ["nodes:\n"]
    for i in range(count):
        package, _ = types[i % len(types)].split("::")
        lines.append(
            f"  - {{package: {package}, plugin: {types[i % len(types)]}, name: n{i}, autostart: true}}\n"
        )
    path = root / f"{mix}-{count}.yaml"
    path.write_text("".join(lines) if count else "nodes: []\n")
    return path


def threads_of(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/task"))


def drain(stream: object, ready: threading.Event, marker: str, tail: list[bytes]) -> None:
    """Read ``stream`` to its end in large chunks; set ``ready`` at ``marker``;
    keep the last few kB in ``tail``."""
    read = stream.read1  # type: ignore[attr-defined]
    needle = marker.encode()
    while True:
        chunk = read(1 << 16)
        if not chunk:
            return
        tail[0] = (tail[0] + chunk)[-4096:]
        if not ready.is_set() and needle in tail[0]:
            ready.set()


def run_container(python: str, config: Path, env: dict[str, str], settle: float) -> tuple[float, int, int, float]:
    """Ready (s from start), threads at ready and ``settle`` s later, and shutdown (s from SIGINT to exit)."""
    ready = threading.Event()
    start = time.monotonic()
    process = subprocess.Popen(
        [python, "-m", "container", "run", str(config)],
        cwd=REPO,
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    tail = [b""]
    reader = threading.Thread(target=drain, args=(process.stdout, ready, " ready with ", tail), daemon=True)
    reader.start()
    try:
        while not ready.wait(0.002):
            if process.poll() is not None:
                reader.join(5)
                output = tail[0].decode(errors="replace")
                raise RuntimeError(f"container exited with {process.returncode} before it was ready:\n{output}")
            if time.monotonic() - start > 300:
                raise TimeoutError("container not ready within 300 s")
        elapsed = time.monotonic() - start
        at_ready = threads_of(process.pid)
        time.sleep(settle)
        settled = threads_of(process.pid)
        stopped = time.monotonic()
        process.send_signal(signal.SIGINT)
        process.wait(60)
        return elapsed, at_ready, settled, time.monotonic() - stopped
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(60)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        reader.join(5)


def run_peer(
    python: str, peer: Path, mix: str, count: int, env: dict[str, str], *, spin: bool
) -> tuple[float, int]:
    start = time.monotonic()
    process = subprocess.Popen(
        [python, str(peer), mix, str(count), "spin" if spin else "plain"],
        cwd=REPO,
        env=env,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert process.stdout is not None and process.stdin is not None
    line = process.stdout.readline()
    elapsed = time.monotonic() - start
    process.stdin.close()
    process.wait(60)
    if not line.startswith("ready"):
        raise RuntimeError(f"rclpy peer failed (exit {process.returncode})")
    return elapsed, int(line.split()[1])


def median(values: Sequence[float]) -> float:
    return statistics.median(values) if values else float("nan")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--mixes", nargs="+", choices=sorted(_MIX_TYPES), default=["idle", "demo"])
    parser.add_argument("--empty", action="store_true", help="also time an empty container")
    parser.add_argument(
        "--settle", type=float, default=6.0, help="seconds after ready before threads are counted again"
    )
    parser.add_argument(
        "--pythons", nargs="+", default=[sys.executable], metavar="PYTHON",
        help="interpreters to run under, side by side (each a set-up virtualenv's)",
    )
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    print(cpus.header(), flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        site = write_site(root)
        env = dict(os.environ)
        env.setdefault("ROS_DOMAIN_ID", str(random.Random().randint(120, 200)))
        env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(site), env.get("PYTHONPATH", "")) if p)
        env["PYTHONUNBUFFERED"] = "1"
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        configs = {mix: write_config(root, mix, args.nodes) for mix in args.mixes}
        empty = write_config(root, "idle", 0)
        results: dict[tuple[str, str, str], Sample] = {}
        for python in args.pythons:  # warm-up: writes the bytecode caches
            run_container(python, configs[args.mixes[0]], env, 0.0)
            run_peer(python, root / "peer.py", args.mixes[0], args.nodes, env, spin=False)
        for round_ in range(1, args.rounds + 1):
            for mix in args.mixes:
                for python in args.pythons:
                    seconds, ready, settled, shutdown = run_container(python, configs[mix], env, args.settle)
                    sample = results.setdefault((python, mix, "container"), Sample())
                    sample.seconds.append(seconds)
                    sample.threads_ready.append(ready)
                    sample.threads_settled.append(settled)
                    sample.shutdown.append(shutdown)
                    line = [f"round {round_} {mix:5} {python}: container {seconds:.2f} s "
                            f"({ready} threads, {settled} after {args.settle:g} s; shutdown {shutdown:.2f} s)"]
                    for peer_name, spin in (("rclpy", False), ("rclpy+spin", True)):
                        peer_seconds, peer_threads = run_peer(
                            python, root / "peer.py", mix, args.nodes, env, spin=spin
                        )
                        peer = results.setdefault((python, mix, peer_name), Sample())
                        peer.seconds.append(peer_seconds)
                        peer.ratios.append(seconds / peer_seconds)
                        peer.threads_ready.append(peer_threads)
                        line.append(f"{peer_name} {peer_seconds:.2f} s ({seconds / peer_seconds:.2f}x)")
                    print(", ".join(line), flush=True)
            if args.empty:
                for python in args.pythons:
                    seconds, ready, settled, shutdown = run_container(python, empty, env, min(args.settle, 1.0))
                    sample = results.setdefault((python, "empty", "container"), Sample())
                    sample.seconds.append(seconds)
                    sample.threads_ready.append(ready)
                    sample.threads_settled.append(settled)
                    sample.shutdown.append(shutdown)
                    print(f"round {round_} empty {python}: ready in {seconds:.2f} s ({ready} threads)", flush=True)
    print(
        f"\nmedians of {args.rounds} round(s), {args.nodes} nodes; ready: from process start; "
        "ratios: the median of each round's ratio (container and peer run back to back)"
    )
    print(
        "| python | mix | container | rclpy | **ratio** | rclpy+spin | ratio | "
        "threads at ready | threads settled | rclpy threads | container shutdown |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for python in args.pythons:
        for mix in [*args.mixes, *(["empty"] if args.empty else [])]:
            box = results[(python, mix, "container")]
            container_s = median(box.seconds)
            if mix == "empty":
                print(f"| {python} | {mix} | {container_s:.2f} s | | | | | "
                      f"{median(box.threads_ready):.0f} | {median(box.threads_settled):.0f} | | "
                      f"{median(box.shutdown):.2f} s |")
                continue
            plain = results[(python, mix, "rclpy")]
            spun = results[(python, mix, "rclpy+spin")]
            plain_s, spun_s = median(plain.seconds), median(spun.seconds)
            print(
                f"| {python} | {mix} | {container_s:.2f} s | {plain_s:.2f} s | **{median(plain.ratios):.2f}x** | "
                f"{spun_s:.2f} s | {median(spun.ratios):.2f}x | "
                f"{median(box.threads_ready):.0f} | {median(box.threads_settled):.0f} | "
                f"{median(plain.threads_ready):.0f} | {median(box.shutdown):.2f} s |"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
