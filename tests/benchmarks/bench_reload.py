"""From a saved edit to the new code running: ``container run --reload`` against restarting the container.

Run: ``.venv/bin/python tests/benchmarks/bench_reload.py [--rounds 5] [--cpus 1]``

Issue 48. A plugin (``reload-probe``, installed with ``pip install
--editable`` into a prefix of the benchmark's own) has a greeter publishing
``<word> ...`` on ``/greeting`` at 20 Hz; beside it in the same container a
demo talker publishes on ``/chatter`` at 10 Hz. Each round saves the
plugin's source with a new word and measures, from the save to the first
message carrying it (its DDS source timestamp), how long the new code took
to run, and the longest silence of the talker (between two of its
messages' source timestamps) around it:

* ``reload``: one ``container run --reload`` for all rounds; the save is all.
* ``restart``: what a plugin author does without it, on the same file: stop
  the container (SIGINT) and start it again (its file autostarts the nodes,
  so nothing is driven by hand; discovery by the observer included).

Printed: medians over ``--rounds`` (range), and restart over reload.
"""

from __future__ import annotations

import argparse
import itertools
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # tests.benchmarks

from tests.benchmarks import cpus  # noqa: E402
from tests.install_support import install_reload_probe  # noqa: E402

PLUGIN = '''\
from typing import Any

from std_msgs.msg import String

from container import LifecycleNode, hookimpl

WORD = "{word}"


class Greeter(LifecycleNode):
    def __init__(self, node_name: str = "greeter", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._publisher = self.create_publisher(String, "greeting", 10)
        self.create_timer(0.05, lambda: self._publisher.publish(String(data=WORD)))


@hookimpl
def register_node_types(register):
    register(Greeter)
'''

CONFIG = """\
container:
  name: ComponentManager
nodes:
  - package: reload_probe
    plugin: reload_probe::Greeter
    name: greeter
    autostart: true
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: talker
    parameters:
      - rate: 10.0
    autostart: true
"""

#: Seconds to wait for one round's new code before giving up on the round.
ROUND_TIMEOUT = 60.0


class Observer:
    """The benchmark's own node: every message on ``/greeting`` and ``/chatter`` with its source timestamp."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import String

        rclpy.init()
        self.node = rclpy.create_node("reload_bench_observer")
        self.greetings: list[tuple[str, float]] = []
        self.chatter: list[float] = []
        self._changed = threading.Condition()
        # rclpy hands the message info to a callback of two parameters (Jazzy's annotation says one).
        self.node.create_subscription(String, "/greeting", self._greeting, 100)  # type: ignore[arg-type, unused-ignore]
        self.node.create_subscription(String, "/chatter", self._chatter, 100)  # type: ignore[arg-type, unused-ignore]
        self._executor = SingleThreadedExecutor()
        self._executor.add_node(self.node)
        threading.Thread(target=self._executor.spin, daemon=True).start()

    def _greeting(self, message: Any, info: dict[str, Any]) -> None:
        with self._changed:
            self.greetings.append((message.data, info["source_timestamp"] / 1e9))
            self._changed.notify_all()

    def _chatter(self, message: Any, info: dict[str, Any]) -> None:
        with self._changed:
            self.chatter.append(info["source_timestamp"] / 1e9)
            self._changed.notify_all()

    def first(self, word: str, *, timeout: float) -> float | None:
        """The source timestamp of the first greeting saying ``word`` (``None``: not within ``timeout``)."""
        with self._changed:
            found = self._changed.wait_for(
                lambda: next((stamp for said, stamp in self.greetings if said == word), None), timeout
            )
        return found

    def longest_silence(self, since: float, until: float, *, timeout: float) -> float:
        """The talker's longest gap between two messages around [since, until]: from its last message
        before ``since`` to its first after ``until`` (waited for), every gap between."""
        with self._changed:
            if not self._changed.wait_for(lambda: any(stamp > until for stamp in self.chatter), timeout):
                raise SystemExit("the talker was not heard again")
            stamps = sorted(self.chatter)
        start = max((i for i, stamp in enumerate(stamps) if stamp <= since), default=0)
        end = min(i for i, stamp in enumerate(stamps) if stamp > until)
        return max(b - a for a, b in itertools.pairwise(stamps[start : end + 1]))

    def close(self) -> None:
        import rclpy

        self._executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown()


class Container:
    """``container run`` as a child process, its output kept for waiting on a line."""

    def __init__(self, config: Path, *, reload: bool, env: dict[str, str]) -> None:
        command = [sys.executable, "-m", "container", "run", str(config), *(["--reload"] if reload else [])]
        self.process = subprocess.Popen(
            command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
        )
        self.lines: list[str] = []
        self._changed = threading.Condition()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            with self._changed:
                self.lines.append(line)
                self._changed.notify_all()

    def wait_for(self, needle: str, *, timeout: float = 60.0) -> None:
        with self._changed:
            if not self._changed.wait_for(lambda: any(needle in line for line in self.lines), timeout):
                raise SystemExit(f"the container never said {needle!r}:\n{''.join(self.lines[-20:])}")

    def stop(self) -> None:
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGINT)
        self.process.wait(60.0)


def run_mode(
    mode: str, rounds: int, source: Path, config: Path, env: dict[str, str], observer: Observer
) -> list[tuple[float, float]]:
    """(seconds from save to new code, the talker's longest silence) for each round of ``mode``."""
    results: list[tuple[float, float]] = []
    container = Container(config, reload=mode == "reload", env=env)
    try:
        if mode == "reload":
            container.wait_for("Reloading on change: watching reload-probe")
        if observer.first("w0", timeout=ROUND_TIMEOUT) is None:
            raise SystemExit(f"{mode}: the greeter was never heard")
        for index in range(1, rounds + 1):
            word = f"{mode}{index}"
            source.write_text(PLUGIN.format(word=word), encoding="utf-8")
            saved = time.time()
            if mode == "restart":
                container.stop()
                container = Container(config, reload=False, env=env)
            heard = observer.first(word, timeout=ROUND_TIMEOUT)
            if heard is None:
                raise SystemExit(f"{mode}: '{word}' never heard:\n{''.join(container.lines[-20:])}")
            results.append((heard - saved, observer.longest_silence(saved, heard, timeout=ROUND_TIMEOUT)))
    finally:
        container.stop()
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5, help="saves per mode (default: %(default)s)")
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 200)))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    print(f"# bench_reload: {args.rounds} saves per mode; {cpus.header()}", flush=True)
    with tempfile.TemporaryDirectory(prefix="bench-reload-") as directory:
        source, paths = install_reload_probe(Path(directory), PLUGIN.format(word="w0"))
        pythonpath = os.pathsep.join([*paths, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
        config = Path(directory) / "container.yaml"
        config.write_text(CONFIG, encoding="utf-8")
        env = dict(os.environ) | {"PYTHONPATH": pythonpath}
        observer = Observer()
        try:
            figures = {
                mode: run_mode(mode, args.rounds, source, config, env, observer) for mode in ("reload", "restart")
            }
        finally:
            observer.close()
    medians: dict[str, tuple[float, float]] = {}
    print(f"{'':10} {'save -> new code running (s)':>36} {'talker silent for (s)':>32}")
    for mode, results in figures.items():
        latency = [result[0] for result in results]
        silence = [result[1] for result in results]
        medians[mode] = (statistics.median(latency), statistics.median(silence))
        print(
            f"{mode:10} {medians[mode][0]:12.3f} ({min(latency):.3f}-{max(latency):.3f}){'':10}"
            f"{medians[mode][1]:10.3f} ({min(silence):.3f}-{max(silence):.3f})"
        )
    print(
        f"restart over reload: {medians['restart'][0] / medians['reload'][0]:.1f}x the wait for the new code, "
        f"{medians['restart'][1] / medians['reload'][1]:.1f}x the talker's silence"
    )


if __name__ == "__main__":
    main()
