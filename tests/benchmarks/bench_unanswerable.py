"""A client that can never receive answers, against a talker in the same container.

Run: ``.venv/bin/python tests/benchmarks/bench_unanswerable.py [--requests 200] [--seconds 40] [--before REV]``

A ``container run`` child process hosts the demo talker at 20 Hz. This
process listens to it and, from a client whose response reader can never
match the services' volatile writers (keep-all, reliable, transient-local:
issue 44's), sends ``--requests`` requests to the container's
``list_nodes`` (or the talker's ``get_state``, ``--service get_state``),
spread evenly over the first half of ``--seconds``. What it reports, per
code under test: the talker's time lost over the window (the sum of each
gap's excess over the period), its largest gap, the container's log lines
about answers not sent, and how SIGINT ended it (exit status; whether it
said "threads left behind").

``--before REV`` runs the same against the container code of git revision
``REV`` (its ``container/`` package extracted to a scratch directory, with
this virtualenv's compiled engine and interfaces), side by side: each round
runs both, in turns. ``--cpus N`` pins everything to N CPUs.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import itertools
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.benchmarks

from tests.benchmarks import cpus

REPO = Path(__file__).resolve().parents[2]
PERIOD_S = 0.05
CONFIG = """
container:
  name: ComponentManager
nodes:
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: talker
    parameters: [{rate: 20.0}]
    autostart: true
"""
SERVICES = {
    "list_nodes": ("composition_interfaces.srv", "ListNodes", "/ComponentManager/_container/list_nodes"),
    "get_state": ("lifecycle_msgs.srv", "GetState", "/talker/get_state"),
}
#: What the code before and after says about an answer it could not send.
NOT_SENT = ("did not match", "was not sent", "will not receive response", "failed to send response")


def before_tree(rev: str, scratch: Path) -> Path:
    """The ``container`` package of ``rev``, with this virtualenv's compiled engine."""
    scratch.mkdir(parents=True)
    archive = subprocess.run(["git", "archive", rev, "container"], cwd=REPO, check=True, capture_output=True)
    subprocess.run(["tar", "-x", "-C", str(scratch)], input=archive.stdout, check=True)
    spec = importlib.util.find_spec("container.executor._fastpath")
    if spec is None or spec.origin is None:
        raise SystemExit("the compiled engine is not built: run .ci/setup")
    shutil.copy2(spec.origin, scratch / "container" / "executor" / Path(spec.origin).name)
    return scratch


#: Runs ``python -m container`` from a tree of code other than the editable install's
#: (whose finder would otherwise take ``container`` from this checkout).
_FROM_TREE = (
    "import runpy, sys; tree = sys.argv.pop(1); "
    "sys.meta_path[:] = [f for f in sys.meta_path if 'Redirecting' not in type(f).__name__]; "
    "sys.path.insert(0, tree); runpy.run_module('container', run_name='__main__', alter_sys=True)"
)


def trial(code: Path | None, *, requests: int, seconds: float, service: str, workdir: Path) -> dict[str, Any]:
    """One container, one attack; the talker's figures and the container's end."""
    import rclpy
    from rclpy.client import Client
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    config = workdir / "talker.yaml"
    config.write_text(CONFIG, encoding="utf-8")
    start_code = ["-m", "container"] if code is None else ["-c", _FROM_TREE, str(code)]
    proc = subprocess.Popen(
        [sys.executable, *start_code, "run", str(config)],
        cwd=workdir, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
    )  # fmt: skip
    lines: list[str] = []
    ready = threading.Event()
    never = threading.Event()  # waited on for time to pass (never set)

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line.rstrip("\n"))
            if "ready with" in line:
                ready.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    context = Context()
    rclpy.init(context=context)
    node = Node("unanswerable_bench", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    heard: list[float] = []
    node.create_subscription(String, "chatter", lambda message: heard.append(time.perf_counter()), 10)
    module, name, path = SERVICES[service]
    srv_type = getattr(importlib.import_module(module), name)
    client: Client[Any, Any] = node.create_client(
        srv_type, path,
        qos_profile=QoSProfile(
            history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        ),
    )  # fmt: skip
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        # Its own wait_for_service never returns true (rmw asks for its reader too): a
        # well-formed client of the same participant waits for the service.
        if not ready.wait(60.0) or not node.create_client(srv_type, path).wait_for_service(timeout_sec=30.0):
            raise SystemExit("the container did not come up:\n" + "\n".join(lines[-20:]))
        deadline = time.monotonic() + 10.0
        while len(heard) < 5 and time.monotonic() < deadline:
            never.wait(0.05)  # a poll of the listener, not a pause the figures rely on
        first = len(heard)
        start = time.perf_counter()
        spacing = seconds / 2 / max(requests, 1)
        for index in range(requests):
            client.call_async(srv_type.Request())
            pause = start + (index + 1) * spacing - time.perf_counter()
            if pause > 0:
                never.wait(pause)  # pacing the attack, as a peer would
        remaining = start + seconds - time.perf_counter()
        if remaining > 0:
            never.wait(remaining)
        window = heard[max(first - 1, 0) :]
        proc.send_signal(signal.SIGINT)
        code_at_exit = proc.wait(30.0)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
        reader.join(5.0)
    gaps = [later - earlier for earlier, later in itertools.pairwise(window)]
    return {
        "lost_s": sum(max(0.0, gap - PERIOD_S) for gap in gaps),
        "largest_ms": max(gaps, default=0.0) * 1000,
        "log_lines": sum(any(words in line for words in NOT_SENT) for line in lines),
        "exit": code_at_exit,
        "left_behind": any("threads left behind" in line for line in lines),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=200)
    parser.add_argument("--seconds", type=float, default=40.0)
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--service", choices=sorted(SERVICES), default="list_nodes")
    parser.add_argument("--before", metavar="REV", help="also run the container code of git revision REV")
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    print(cpus.header())
    half, whole = args.seconds / 2, args.seconds
    print(f"{args.requests} requests to {args.service} over {half:.0f} s, measured over {whole:.0f} s")
    with tempfile.TemporaryDirectory(prefix="bench-unanswerable-") as scratch:
        codes: dict[str, Path | None] = {"now": None}
        if args.before:
            codes[f"before ({args.before})"] = before_tree(args.before, Path(scratch) / "before")
        results: dict[str, list[dict[str, Any]]] = {label: [] for label in codes}
        for round_index in range(args.rounds):
            for label, code in codes.items():
                workdir = Path(scratch) / f"{round_index}-{len(results[label])}-{label.split()[0]}"
                workdir.mkdir(parents=True)
                results[label].append(
                    trial(code, requests=args.requests, seconds=args.seconds, service=args.service, workdir=workdir)
                )
    columns = ("talker time lost", 16), ("largest gap", 12), ("log lines", 9), ("SIGINT exit", 11), ("left behind", 11)
    print(f"\n{'code':24} " + " ".join(f"{title:>{width}}" for title, width in columns))
    for label, runs in results.items():
        lost = statistics.median(run["lost_s"] for run in runs)
        largest = statistics.median(run["largest_ms"] for run in runs)
        lines = statistics.median(run["log_lines"] for run in runs)
        exits = ",".join(str(run["exit"]) for run in runs)
        left = ",".join("yes" if run["left_behind"] else "no" for run in runs)
        print(f"{label:24} {lost:>14.2f} s {largest:>9.0f} ms {lines:>9.0f} {exits:>11} {left:>11}")


if __name__ == "__main__":
    main()
