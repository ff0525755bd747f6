"""Ten demo talkers: one container against ten rclpy processes, side by side.

Run from the repository root::

    python tests/benchmarks/bench_memory.py [--nodes 10] [--rounds 1]

For each layout it starts the processes, watches from outside (this process
asks every talker's ``get_state`` service) until all of them are active,
lets them run a moment, then sums their PSS from ``/proc/<pid>/smaps_rollup``
(PSS splits shared pages between the processes that share them, so the sum
is what the layout really costs). The separate processes run what users run
today: one rclpy lifecycle talker per process, brought up by itself.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random().randint(120, 200)))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from container._runtime import use_fast_discovery  # noqa: E402
from tests.benchmarks import cpus  # noqa: E402
from tests.benchmarks.container_client import pss_and_rss  # noqa: E402

use_fast_discovery()

import rclpy  # noqa: E402
from lifecycle_msgs.msg import State  # noqa: E402
from lifecycle_msgs.srv import GetState  # noqa: E402
from rclpy.client import Client  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402
from rclpy.utilities import try_shutdown  # noqa: E402

from container import AsyncioExecutor  # noqa: E402

#: One plain rclpy lifecycle talker per process, as users write it today:
#: the same publisher, timer and parameters as lifecycle_container::Talker.
STANDALONE = '''
import sys
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from std_msgs.msg import String


class Talker(LifecycleNode):
    def __init__(self, name):
        super().__init__(name)
        self.declare_parameter("rate", 2.0)
        self.declare_parameter("message", "Hello World")
        self.publisher = None
        self.count = 0

    def on_configure(self, state):
        self.publisher = self.create_lifecycle_publisher(String, "chatter", 10)
        self.create_timer(1.0 / self.get_parameter("rate").value, self.publish)
        return TransitionCallbackReturn.SUCCESS

    def publish(self):
        if self.publisher is not None and self.publisher.is_activated:
            self.count += 1
            self.publisher.publish(String(data=f"Hello World: {self.count}"))


rclpy.init()
node = Talker(sys.argv[1])
node.trigger_configure()
node.trigger_activate()
try:
    rclpy.spin(node, executor=SingleThreadedExecutor())
except (KeyboardInterrupt, ExternalShutdownException):
    pass
'''


@dataclass
class Result:
    layout: str
    processes: int
    pss_kb: int
    rss_kb: int
    seconds_to_active: float


async def wait_all_active(node: Node, names: list[str], *, timeout: float) -> None:
    """Ask every ``/name/get_state`` until all answer ``active``."""
    clients: dict[str, Client[Any, Any]] = {name: node.create_client(GetState, f"/{name}/get_state") for name in names}
    pending = set(names)
    deadline = time.monotonic() + timeout
    try:
        while pending:
            if time.monotonic() > deadline:
                raise TimeoutError(f"not active after {timeout} s: {sorted(pending)}")
            asked = {
                name: clients[name].call_async(GetState.Request())
                for name in sorted(pending)
                if clients[name].service_is_ready()
            }
            for name, future in asked.items():
                # The executor runs this coroutine adapted to rclpy futures.
                response = await future
                assert response is not None
                if response.current_state.id == State.PRIMARY_STATE_ACTIVE:
                    pending.discard(name)
            if pending:
                # No graph event in rclpy: look again shortly.
                await asyncio.sleep(0.01)
    finally:
        for client in clients.values():
            node.destroy_client(client)


def measure(
    layout: str, commands: list[list[str]], names: list[str], node: Node, executor: AsyncioExecutor
) -> Result:
    start = time.monotonic()
    processes = [
        subprocess.Popen(command, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for command in commands
    ]
    try:
        errors: list[BaseException] = []

        async def watch() -> None:
            try:
                await wait_all_active(node, names, timeout=120.0)
            except BaseException as exc:
                errors.append(exc)

        executor.spin_until_future_complete(watch())
        if errors:
            raise errors[0]
        elapsed = time.monotonic() - start
        # Let them publish for a while so that steady-state pages are in.
        executor.spin_until_future_complete(asyncio.sleep(3.0))
        pss = rss = 0
        for process in processes:
            process_pss, process_rss = pss_and_rss(process.pid)
            pss += process_pss
            rss += process_rss
        return Result(layout, len(processes), pss, rss, elapsed)
    finally:
        for process in processes:
            process.send_signal(signal.SIGINT)
        for process in processes:
            try:
                process.wait(15)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--nodes", type=int, default=10)
    parser.add_argument("--rounds", type=int, default=1, help="repeat both layouts, alternating")
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    print(cpus.header(), flush=True)
    names = [f"talker{i}" for i in range(args.nodes)]

    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "ten.yaml"
        config.write_text(
            "nodes:\n"
            + "".join(
                f"  - {{package: lifecycle_container, plugin: lifecycle_container::Talker, "
                f"name: {name}, autostart: true}}\n"
                for name in names
            ),
            encoding="utf-8",
        )
        standalone = Path(tmp) / "talker.py"
        standalone.write_text(STANDALONE, encoding="utf-8")
        container_cmd = [[sys.executable, "-m", "container", "run", str(config)]]
        separate_cmds = [[sys.executable, str(standalone), name] for name in names]

        context = Context()
        rclpy.init(args=[], context=context, signal_handler_options=SignalHandlerOptions.NO)
        node = Node("_bench_memory_observer", context=context)
        executor = AsyncioExecutor(context=context)
        executor.add_node(node)
        results: list[Result] = []
        try:
            for _ in range(args.rounds):
                results.append(measure("one container", container_cmd, names, node, executor))
                results.append(measure("separate processes", separate_cmds, names, node, executor))
        finally:
            executor.shutdown()
            node.destroy_node()
            try_shutdown(context=context)

    print(f"{args.nodes} demo talkers, ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}")
    print(f"{'layout':<20} {'procs':>5} {'PSS MiB':>9} {'RSS MiB':>9} {'all active s':>13}")
    for result in results:
        print(
            f"{result.layout:<20} {result.processes:>5} {result.pss_kb / 1024:>9.1f} "
            f"{result.rss_kb / 1024:>9.1f} {result.seconds_to_active:>13.2f}"
        )
    for one, many in zip(results[::2], results[1::2], strict=True):
        print(
            f"ratio separate/container: PSS {many.pss_kb / one.pss_kb:.1f}x, "
            f"time to all active {many.seconds_to_active / one.seconds_to_active:.1f}x"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
