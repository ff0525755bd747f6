"""LiDAR container benchmark: CPU of streaming an LD06 at 10 Hz, and scan latency.

Run: ``.venv/bin/python tests/benchmarks/bench_lidar.py [--seconds 10] [--warmup 3] [--polls 20,5]``

Every container is a real ``python -m container run`` process, measured one
after the other in the same run, each with a subscriber in this process on
the topic it publishes (a publisher nobody listens to costs less):

* **idle**: a container with no node (the floor: executor, services, DDS);
* **talker**: the demo ``lifecycle_container::Talker`` at 10 Hz (the peer: a
  node publishing at the same rate, with no device behind it);
* **lidar**: ``ldlidar::LdLidarNode`` reading an emulated LD06 (4,500 points/s,
  375 packets/s, 17.6 kB/s) at 10 Hz, once per ``--polls`` value of
  ``comm.poll_msec`` (20, the default: polled, plus a read when each
  revolution is due). The emulator runs in a separate process on a
  pseudo-terminal (writing three times per revolution, the last on its
  end, as it does by default), so its CPU is not
  counted in these rows (it is printed apart: the emulator's own cost);
* **lidar+emu**: ``examples/lidar.yaml`` as it is, emulator in the container
  (what ``container run examples/lidar.yaml`` costs with no hardware).

CPU: utime + stime of the container process from ``/proc/<pid>/stat`` over
``--seconds`` after the node is active plus ``--warmup``, as % of one core
(the ROS wheels' bootstrapper re-execs the interpreter, keeping the pid).

Latency (lidar scenario), measured from the emulator's side and DDS's: the
emulator process records the wall-clock time (``time.time_ns``, right after
``os.write`` returns) of every write holding a packet in which the angle
passes the back of the sensor (180 degrees), i.e. the packet that completes
a revolution. The subscriber takes
each LaserScan with its DDS ``source_timestamp`` (the wall-clock time the
publisher handed it to DDS, taken inside ``publish``) and ``received_timestamp``.
A scan is matched to the latest recorded wrap write before its publish; the
match is kept only if the scan's own end (the time of its last-measured ray,
``header.stamp`` or ``header.stamp + (n - 1) * time_increment`` whichever is
later: the device clock mapped to the host) lies within 30 ms of that
write, so a missed revolution can never be matched to the wrong one. Only the scans
published during the CPU window count (the steady state, after the device
clock mapping has settled). Printed: write -> publish (what the driver adds:
pty, asyncio wake-up, parsing, assembly, message build) and write ->
received (plus DDS to another process). Both processes read the same host
clock, so no clock offset enters.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # tests.benchmarks

from tests.benchmarks import cpus  # noqa: E402

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")

IDLE = """
container: {name: ComponentManager}
nodes: []
"""
TALKER = """
container: {name: ComponentManager}
nodes:
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: talker
    parameters: [{rate: 10.0}]
    autostart: true
"""
LIDAR = """
# The emulator's port is a pseudo-terminal, which the default device policy refuses
# unless the node started the emulator itself: named explicitly here.
container: {name: ComponentManager, devices: {serial: ["/dev/pts/*"]}}
nodes:
  - package: ldlidar
    plugin: ldlidar::LdLidarNode
    name: ldlidar
    parameters: [{comm: {serial_port: "%s", poll_msec: %d}, lidar: {model: LD06}}]
    autostart: true
"""


# -- the emulator process ------------------------------------------------------------
def run_emulator(link_dir: str, record: str) -> None:
    """Run an LD06 emulator that records when each revolution's last packet went out."""
    import numpy as np

    from ldlidar import Emulator

    class RecordingEmulator(Emulator):
        """Notes each write's time and bytes (cheaply: the emulator's CPU is measured);
        the revolutions are found in them at the end."""

        def __init__(self) -> None:
            super().__init__(model="LD06", link_dir=link_dir)
            self.writes: list[tuple[int, bytes] | None] = []

        def _write(self, data: bytes) -> None:
            dropped = self.bytes_dropped
            super()._write(data)
            # No reader (between containers) or a full pty: nothing to time.
            self.writes.append((time.time_ns(), data) if self.bytes_dropped == dropped else None)

        def wraps(self) -> list[tuple[int, int]]:
            found: list[tuple[int, int]] = []
            last_end: int | None = None
            for write in self.writes:
                if write is None:
                    last_end = None
                    continue
                written, data = write
                rows = np.frombuffer(data, dtype=np.uint8).reshape(-1, 47).astype(np.int64)
                # Angles past the back of the sensor, where the driver ends a revolution.
                start = ((rows[:, 4] | rows[:, 5] << 8) - 18000) % 36000
                end = ((rows[:, 42] | rows[:, 43] << 8) - 18000) % 36000
                before = np.concatenate(([last_end if last_end is not None else 0], end[:-1]))
                wrapped = (end < start) | (start < before - 18000)
                for k in np.flatnonzero(wrapped):
                    found.append((written, int(rows[k, 44] | rows[k, 45] << 8)))
                last_end = int(end[-1])
            return found

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for signum in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(signum, stop.set)
        emu = RecordingEmulator()
        async with emu:
            print(f"LINK {emu.link}", flush=True)
            await stop.wait()
        Path(record).write_text(json.dumps(emu.wraps()), encoding="utf-8")

    asyncio.run(main())


# -- measuring ---------------------------------------------------------------------------------
def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS  # utime, stime


@dataclass
class Container:
    process: subprocess.Popen[str]
    lines: list[str] = field(default_factory=list)
    ready: threading.Event = field(default_factory=threading.Event)

    @classmethod
    def start(cls, config: Path) -> Container:
        process = subprocess.Popen(
            [sys.executable, "-m", "container", "run", str(config)],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        container = cls(process)
        threading.Thread(target=container._read, daemon=True).start()
        if not container.ready.wait(30):
            container.stop()
            raise SystemExit("container not ready within 30 s:\n" + "\n".join(container.lines))
        return container

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append(line.rstrip())
            if "ready with" in line:
                self.ready.set()

    def stop(self) -> None:
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(15)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


class Listener:
    """A subscriber in this process, recording what arrives with DDS's timestamps."""

    def __init__(self, topic: str, kind: str) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("bench_listener", context=self.context)
        self.records: list[tuple[int, int, float, float]] = []
        self.window: list[tuple[int, int, float, float]] = []
        # rclpy hands (message, message info) to a two-argument callback;
        # rclpy 7's annotation only knows the one-argument kind.
        if kind == "scan":
            from sensor_msgs.msg import LaserScan

            self.node.create_subscription(LaserScan, topic, self._scan, 10)  # type: ignore[arg-type, unused-ignore]
        else:
            from std_msgs.msg import String

            self.node.create_subscription(String, topic, self._other, 10)  # type: ignore[arg-type, unused-ignore]
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _scan(self, msg: Any, info: Any) -> None:
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        # Ray 0 is measured first or last depending on the direction: the end is the later.
        end = max(stamp, stamp + (len(msg.ranges) - 1) * msg.time_increment)
        self.records.append((info["source_timestamp"], info["received_timestamp"], end, msg.scan_time))

    def _other(self, msg: Any, info: Any) -> None:
        self.records.append((info["source_timestamp"], info["received_timestamp"], 0.0, 0.0))

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            while self.context.ok():
                self.executor.spin_once(timeout_sec=0.1)
        except ExternalShutdownException:
            pass  # close() shut the context down: the end of the window

    def close(self) -> None:
        from rclpy.utilities import try_shutdown

        try_shutdown(context=self.context)
        self.thread.join(5)
        self.executor.shutdown(1)
        self.node.destroy_node()


def wait_for(predicate: Any, limit: float, what: str) -> None:
    deadline = time.monotonic() + limit
    while not predicate():
        if time.monotonic() > deadline:
            raise SystemExit(f"timed out waiting for {what}")
        time.sleep(0.05)


def measure(config: Path, *, topic: str, kind: str, warmup: float, seconds: float) -> tuple[float, Listener]:
    """CPU % of one core of a container running ``config``; the listener stays open."""
    listener = Listener(topic, kind)
    container = Container.start(config)
    try:
        if kind != "none":
            wait_for(lambda: len(listener.records) >= 3, 20, f"messages on {topic}")
        time.sleep(warmup)
        pid = container.process.pid
        first = len(listener.records)
        cpu0, wall0 = cpu_seconds(pid), time.monotonic()
        time.sleep(seconds)
        cpu1, wall1 = cpu_seconds(pid), time.monotonic()
        # Latency, too, is the steady state's: what arrived in the window.
        listener.window = listener.records[first:]
    finally:
        container.stop()
    if container.process.returncode != 0:
        print("\n".join(container.lines[-20:]), file=sys.stderr)
    return 100 * (cpu1 - cpu0) / (wall1 - wall0), listener


def latencies(
    wraps: list[tuple[int, int]], records: list[tuple[int, int, float, float]]
) -> tuple[list[float], list[float], int]:
    """Milliseconds write -> publish and write -> receive, and how many scans were unmatched."""
    writes = sorted(w for w, _ in wraps)
    to_publish: list[float] = []
    to_receive: list[float] = []
    unmatched = 0
    import bisect

    for source, received, end, _scan_time in records:
        k = bisect.bisect_right(writes, source) - 1
        if k < 0 or abs(writes[k] / 1e9 - end) > 0.03:
            unmatched += 1
            continue
        to_publish.append((source - writes[k]) / 1e6)
        to_receive.append((received - writes[k]) / 1e6)
    return to_publish, to_receive, unmatched


def summary(values: list[float]) -> str:
    if not values:
        return "n/a"
    ordered = sorted(values)
    p95 = ordered[min(len(ordered) - 1, round(0.95 * (len(ordered) - 1)))]
    return f"median {statistics.median(ordered):6.2f}  p95 {p95:6.2f}  max {ordered[-1]:6.2f} ms"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="CPU measurement window")
    parser.add_argument("--warmup", type=float, default=3.0, help="seconds after the first message")
    parser.add_argument(
        "--polls", default="20,5", help="comm.poll_msec values to measure the LiDAR with (comma-separated)"
    )
    parser.add_argument("--emulator", nargs=2, metavar=("LINK_DIR", "RECORD"), help=argparse.SUPPRESS)
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    if args.emulator:
        run_emulator(*args.emulator)
        return

    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 200)))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    from container._runtime import use_fast_discovery

    use_fast_discovery()
    print(f"command: {shlex.join([sys.executable, *sys.argv])}")
    print(f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.2f}; {args.warmup:g} s warm-up, {args.seconds:g} s window")
    print(cpus.header())

    rows: list[tuple[str, float]] = []
    latency: list[tuple[str, list[tuple[int, int, float, float]]]] = []
    with tempfile.TemporaryDirectory(prefix="bench-lidar-") as tmp:
        work = Path(tmp)

        def config(name: str, text: str) -> Path:
            path = work / f"{name}.yaml"
            path.write_text(text, encoding="utf-8")
            return path

        def run(name: str, path: Path, topic: str, kind: str) -> list[tuple[int, int, float, float]]:
            cpu, listener = measure(path, topic=topic, kind=kind, warmup=args.warmup, seconds=args.seconds)
            listener.close()
            rows.append((name, cpu))
            return listener.window

        run("idle container (no node)", config("idle", IDLE), "/chatter", "none")
        run("container + demo Talker, 10 Hz", config("talker", TALKER), "/chatter", "string")

        record = work / "wraps.json"
        emulator = subprocess.Popen(
            [sys.executable, __file__, "--emulator", str(work), str(record)],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert emulator.stdout is not None
        link = emulator.stdout.readline().split()[-1]
        emu_cpu0, emu_wall0 = cpu_seconds(emulator.pid), time.monotonic()
        for poll in (int(value) for value in args.polls.split(",")):
            name = f"container + LD06 LiDAR, comm.poll_msec {poll}"
            records = run(name, config(f"lidar{poll}", LIDAR % (link, poll)), "/ldlidar/scan", "scan")
            latency.append((name, records))
        emu_cpu = 100 * (cpu_seconds(emulator.pid) - emu_cpu0) / (time.monotonic() - emu_wall0)
        emulator.send_signal(signal.SIGTERM)
        emulator.wait(10)
        wraps = [(int(w), int(d)) for w, d in json.loads(record.read_text(encoding="utf-8"))]

        example = (REPO / "examples" / "lidar.yaml").read_text(encoding="utf-8")
        run("examples/lidar.yaml as is (emulator inside)", config("example", example), "/ldlidar/scan", "scan")

    talker = rows[1][1]
    print()
    print(f"{'scenario':46} {'CPU % of one core':>18} {'/ talker':>9}")
    for name, value in rows:
        print(f"{name:46} {value:18.1f} {value / talker:9.1f}")
    print(f"{'LD06 emulator, its own process (no row above)':46} {emu_cpu:18.1f}")
    print(f"(CPU is counted in {1000 / CLOCK_TICKS:g} ms ticks: +-{100 / CLOCK_TICKS / args.seconds:.1f} %)")
    for name, records in latency:
        to_publish, to_receive, unmatched = latencies(wraps, records)
        print()
        print(f"{name}: latency over the {len(records)} scans of the window ({unmatched} unmatched)")
        print(f"  revolution's last byte written -> LaserScan published: {summary(to_publish)}")
        print(f"  revolution's last byte written -> received elsewhere:  {summary(to_receive)}")


if __name__ == "__main__":
    main()
