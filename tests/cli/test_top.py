"""``container top``: a container's nodes by what they cost, from another process."""

from __future__ import annotations

import contextlib
import json
import os
import pty
import re
import select
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import pytest

from tests.container_support import REPO, ContainerProcess

#: A node burning 20 ms of thread CPU every 100 ms (0.2 of a core) beside two idle ones.
BURNING = """\
container:
  name: ComponentManager
nodes:
  - package: test_nodes
    plugin: test_nodes::Burner
    name: burner
    parameters:
      - burn_ms: 20.0
      - period: 0.1
  - package: test_nodes
    plugin: test_nodes::Idle
    name: idle_a
  - package: test_nodes
    plugin: test_nodes::Idle
    name: idle_b
"""


def top(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "container", "top", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.slow
def test_top_shows_the_burning_node_first_with_what_it_burns(
    run_container: Callable[..., ContainerProcess], see_plugin: Callable[..., None]
) -> None:
    see_plugin()
    run_container(BURNING)

    result = top("--json", "/ComponentManager")
    assert result.returncode == 0, result.stderr
    (load,) = json.loads(result.stdout)
    assert load["container"] == "/ComponentManager"
    names = [node["name"] for node in load["nodes"]]
    assert names[0] == "/burner", names
    burner = load["nodes"][0]
    timer = next(c for c in burner["callbacks"] if c["kind"] == "timer")
    # What it burned in this window: 20 ms of CPU per timer callback it ran.
    # The node's rate counts its other work too (the first window has its
    # constructor's thread call, and a loop callback): the timer's row is what
    # says how often it burned.
    burned = 0.020 * timer["rate"]
    assert timer["rate"] == pytest.approx(10, rel=0.3), timer
    assert burner["cpu"] == pytest.approx(burned, rel=0.2), [
        (c["kind"], c["rate"], c["cpu"]) for c in burner["callbacks"] if c["rate"]
    ]
    for idle in (node for node in load["nodes"] if node["name"] in ("/idle_a", "/idle_b")):
        assert idle["cpu"] < 0.01, idle
    assert {"/idle_a", "/idle_b", "/ComponentManager"} <= set(names)
    # A duration is wall time: never much below the 20 ms of CPU it burns, and
    # stretched by whatever else wants the CPUs meanwhile (up to 3x allowed).
    assert 0.016 <= timer["duration_p50"] <= 0.060, timer
    assert load["cpu"] >= load["callbacks_cpu"] > 0

    result = top("--once", "--node", "/burner")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0].startswith("container /ComponentManager  window ")
    header = next(index for index, line in enumerate(lines) if line.startswith("NODE "))
    assert header in (1, 2), "the heading, then the unattributed kinds' line if any is above 0.05%"
    assert lines[header].split() == [
        "NODE", "CPU%", "CB/S", "LATE_P99_MS", "DUR_P99_MS", "DROPPED", "STUCK", "CPU_TOTAL_S",
    ]  # fmt: skip
    assert lines[header + 1].split()[0] == "/burner"
    assert "callbacks of /burner (times in ms)" in lines
    assert any(line.startswith("timer Burner.__init__.λ") for line in lines), result.stdout

    result = top("--once", "--sort", "name", "/ComponentManager")
    lines = result.stdout.splitlines()
    header = next(index for index, line in enumerate(lines) if line.startswith("NODE "))
    rows = [line.split()[0] for line in lines[header + 1 :]]
    assert rows == sorted(rows)


class _Terminal:
    """``container top`` live, on a real pseudo-terminal of 160 columns: keys in, the screen out."""

    def __init__(self, *args: str) -> None:
        self._master, slave = pty.openpty()
        env = dict(os.environ, COLUMNS="160", LINES="60", TERM="xterm")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "container", "top", *args],
            cwd=REPO, stdin=slave, stdout=slave, stderr=slave, env=env, close_fds=True,
        )
        os.close(slave)
        self._seen = ""

    def wait_for(self, pattern: str, *, timeout: float = 20.0) -> str:
        """The screen text since the last match, up to the first match of ``pattern``."""
        deadline = time.monotonic() + timeout
        while True:
            found = re.search(pattern, self._seen)
            if found is not None:
                text, self._seen = self._seen[: found.end()], self._seen[found.end():]
                return text
            left = deadline - time.monotonic()
            assert left > 0, f"no {pattern!r} on the screen within {timeout} s; last: {self._seen[-2000:]}"
            ready, _, _ = select.select([self._master], [], [], left)
            if ready:
                try:
                    data = os.read(self._master, 65536)
                except OSError:  # the process ended
                    data = b""
                if not data:
                    raise AssertionError(f"top ended before {pattern!r}; last: {self._seen[-2000:]}")
                # Escape sequences out: what is left is the text drawn.
                self._seen += re.sub(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b[()][A-Z0-9]", "", data.decode(errors="replace"))

    def press(self, keys: str) -> None:
        os.write(self._master, keys.encode())

    def close(self, *, timeout: float = 10.0) -> int | None:
        """Its exit code once it ends (the screen drained meanwhile: a full pty would block it), or
        ``None``: killed after ``timeout``."""
        if self._master < 0:
            return self.process.poll()
        deadline = time.monotonic() + timeout
        try:
            while self.process.poll() is None and time.monotonic() < deadline:
                ready, _, _ = select.select([self._master], [], [], 0.1)
                if ready:
                    with contextlib.suppress(OSError):  # the process ended
                        os.read(self._master, 65536)
            return self.process.poll()
        finally:
            if self.process.poll() is None:
                self.process.kill()
            self.process.wait(timeout=10)
            os.close(self._master)
            self._master = -1


@pytest.mark.slow
def test_top_live_sorts_opens_a_node_and_quits_on_a_terminal(
    run_container: Callable[..., ContainerProcess], see_plugin: Callable[..., None]
) -> None:
    see_plugin()
    run_container(BURNING)
    terminal = _Terminal("/ComponentManager")
    try:
        screen = terminal.wait_for(r"/burner.*\n(?:.*\n)*.*/idle_[ab]")
        assert "CPU% *" in screen  # sorted by CPU: the burner above the idle nodes
        terminal.press("n")  # by name
        screen = terminal.wait_for(r"NODE \*(?:.*\n)*.*/ComponentManager(?:.*\n)*.*/burner(?:.*\n)*.*/idle_a")
        terminal.press("j")  # the second row, /burner
        terminal.press("\r")
        screen = terminal.wait_for(r"/burner \(callbacks, times in ms\)(?:.*\n)*.*timer Burner")
        assert "GROUP" in screen
        terminal.press("\x1b")
        terminal.wait_for(r"nodes")
        terminal.press("q")
        assert terminal.close() == 0
    finally:
        terminal.close(timeout=0)


def test_top_without_a_container_says_so_and_exits_1() -> None:
    result = top("--once", "--timeout", "1", "/no_such_container")
    assert result.returncode == 1
    assert result.stderr.strip() == "no load report from container /no_such_container within 1 s"


# -- an operator's terminal: names, widths, the last minute ----------------------------------


def _window(**nodes: list[dict[str, Any]]) -> Any:
    """A ``ContainerLoad`` message of one window: the given nodes' callbacks (kind, name, group, cpu)."""
    from lifecycle_container_interfaces.msg import CallbackLoad, ContainerLoad, NodeLoad, UnattributedLoad

    built = []
    for name, callbacks in nodes.items():
        rows = [
            CallbackLoad(node=f"/{name}", group=row.get("group", "default"), kind=row["kind"], name=row["name"],
                         cpu=row.get("cpu", 0.0), rate=10.0, lateness_p99=0.0012, lateness_max=0.25,
                         duration_p99=0.0207, duration_max=1234.5, runs_total=row.get("runs", 10))
            for row in callbacks
        ]  # fmt: skip
        built.append(NodeLoad(name=f"/{name}", cpu=sum(row.cpu for row in rows), rate=10.0, callbacks=rows))
    return ContainerLoad(
        container="/ComponentManager", period=1.0, cpu=0.42, callbacks_cpu=0.2, executor_cpu=0.02, loop_idle=0.9,
        nodes=built, nodes_cpu=0.39, unattributed_cpu=0.006,
        unattributed=[UnattributedLoad(kind="middleware threads", cpu=0.005), UnattributedLoad(kind="tasks", cpu=0.001),
                      UnattributedLoad(kind="native threads", cpu=0.0)],
    )  # fmt: skip


#: What rclpy names its own callbacks of a lifecycle node with a publisher (QoS events, services).
_RCLPY_NAMED: list[dict[str, Any]] = [
    {"kind": "waitable", "name": "eventhandler callback PublisherEventCallbacks.create_event_handlers.<locals>."
                                 "<lambda>"},
    {"kind": "service", "name": "service '/fast/change_state' callback LifecycleNodeMixin.__on_change_state"},
    {"kind": "service", "name": "service '/fast/describe_parameters' callback ParameterService._describe_parameters"
                                "_callback"},
    {"kind": "timer", "name": "timer callback Fast.__init__.<locals>.tick", "cpu": 0.2},
    {"kind": "task", "name": "asyncio tasks", "group": "asyncio", "cpu": 0.15},
    {"kind": "thread", "name": "threads it started (1 running)", "group": "threads", "cpu": 0.04},
]  # fmt: skip


def test_long_callback_names_are_shortened_for_a_person_and_whole_in_json() -> None:
    from container.cli._top import NAME_WIDTH, as_dict, short_name

    assert short_name(_RCLPY_NAMED[0]["name"]) == "QoS event PublisherEventCallbacks…λ"
    rclpy_default = (
        "eventhandler callback PublisherEventCallbacks.create_event_handlers.<locals>."
        "_default_incompatible_qos_callback"
    )
    assert short_name(rclpy_default) == "QoS event default_incompatible_qos"
    assert short_name("timer callback Fast.__init__.<locals>.tick") == "timer Fast.__init__.tick"
    assert short_name("subscription '/scan' callback Node._on_scan") == "subscription '/scan' Node._on_scan"
    long_service = "service '/fast/describe_parameters' callback ParameterService._describe_parameters_callback"
    assert short_name(long_service) == "service '/fast/describe_parameters'"
    assert short_name("asyncio tasks") == "asyncio tasks"
    for row in _RCLPY_NAMED:
        assert len(short_name(row["name"])) <= NAME_WIDTH, row
    window = _window(fast=_RCLPY_NAMED)
    names = [callback["name"] for callback in as_dict(window)["nodes"][0]["callbacks"]]
    assert names == [row["name"] for row in _RCLPY_NAMED], "--json keeps the full names"


def test_the_callbacks_view_fits_120_columns() -> None:
    from container.cli._top import plain_table

    text = plain_table(_window(fast=_RCLPY_NAMED), node="/fast")
    lines = text.splitlines()
    assert lines[0].startswith("container /ComponentManager  window 1.00 s  cpu 42.0%  nodes 39.0%  executor 2.0%")
    assert lines[1] == "unattributed: middleware threads 0.5%  tasks 0.1%", "the kinds above 0.05%, largest first"
    assert max(len(line) for line in lines) <= 120, "\n".join(line for line in lines if len(line) > 120)
    callbacks = lines[lines.index("callbacks of /fast (times in ms)") + 1 :]
    assert callbacks[0].split() == [
        "CALLBACK", "GROUP", "CPU%", "CB/S", "LATE_P99", "LATE_MAX", "DUR_P99", "DUR_MAX", "DROP", "STUCK",
    ]  # fmt: skip
    row = next(line for line in callbacks if line.startswith("timer "))
    assert row.split()[-8:] == ["20.0", "10.0", "1.200", "250.0", "20.70", "1234500", "0", "-"], row
    thread = next(line for line in callbacks if line.startswith("threads it started"))
    assert thread.split().count("-") == 5, "a thread's row has CPU only: no times, nothing stuck"


def test_the_callbacks_view_leaves_out_those_that_never_ran() -> None:
    from container.cli._top import plain_table

    never = [{"kind": "service", "name": f"service '/fast/s{index}' callback S.s", "runs": 0} for index in range(20)]
    lines = plain_table(_window(fast=_RCLPY_NAMED + never), node="/fast").splitlines()
    assert not [line for line in lines if line.startswith("service '/fast/s")]
    assert lines[-1] == "and 20 callback(s) that never ran (--json lists every one)"


def test_service_names_are_written_one_way(executor: Any, host: Callable[..., Any]) -> None:
    """rclpy keeps a service's name as given: ``~/change_state`` expanded, ``describe_parameters``
    relative; the accounting names both by their full names, as ``ros2 service list`` does."""
    from rclpy.node import Node

    from container.executor import describe

    node = host(Node, "fast", namespace="/ns")
    names = sorted(describe(service) for service in node.services)
    assert names and all(name.startswith("service '/ns/fast/") for name in names), names


def test_the_live_view_draws_each_nodes_last_minute() -> None:
    from container.cli._top import SPARK_WIDTH, History, _View

    history = History()
    start = 1000.0
    for second in range(60):  # the busy node ramps up; the idle one stays idle
        history.add(_window(busy=[{"kind": "timer", "name": "timer callback t", "cpu": second / 100}],
                            idle=[{"kind": "timer", "name": "timer callback t"}]), start + second)  # fmt: skip
    now = start + 59.5
    busy = history.spark("/ComponentManager", "/busy", now, scale=history.peak("/ComponentManager"))
    idle = history.spark("/ComponentManager", "/idle", now, scale=history.peak("/ComponentManager"))
    assert len(busy) == len(idle) == SPARK_WIDTH
    assert busy[0] in "▁▂" and busy[-1] == "█" and list(busy) == sorted(busy), busy
    assert set(idle) == {"▁"}, idle
    from rich.console import Console

    console = Console(width=120, record=True, color_system=None)
    console.print(
        _View().render([_window(busy=[{"kind": "timer", "name": "timer callback t", "cpu": 0.5}])], history, now=now)
    )
    screen = console.export_text()
    assert "CPU_LAST_MIN" in screen and busy[-5:] in screen, screen
