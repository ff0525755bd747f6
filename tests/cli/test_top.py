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
    # What it burned in this window: 20 ms of CPU per callback it ran.
    burned = 0.020 * burner["rate"]
    assert burner["rate"] == pytest.approx(10, rel=0.3)
    assert burner["cpu"] == pytest.approx(burned, rel=0.2), burner
    for idle in (node for node in load["nodes"] if node["name"] in ("/idle_a", "/idle_b")):
        assert idle["cpu"] < 0.01, idle
    assert {"/idle_a", "/idle_b", "/ComponentManager"} <= set(names)
    timer = next(c for c in burner["callbacks"] if c["kind"] == "timer")
    # A duration is wall time: never much below the 20 ms of CPU it burns, and
    # stretched by whatever else wants the CPUs meanwhile (up to 3x allowed).
    assert 0.016 <= timer["duration_p50"] <= 0.060, timer
    assert load["cpu"] >= load["callbacks_cpu"] > 0

    result = top("--once", "--node", "/burner")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0].startswith("container /ComponentManager  window ")
    assert lines[1].split() == ["NODE", "CPU%", "CB/S", "LATE_P99_MS", "DUR_P99_MS", "DROPPED", "STUCK", "CPU_TOTAL_S"]
    assert lines[2].split()[0] == "/burner"
    assert "callbacks of /burner" in lines
    assert any(line.startswith("timer callback Burner.") for line in lines), result.stdout

    result = top("--once", "--sort", "name", "/ComponentManager")
    rows = [line.split()[0] for line in result.stdout.splitlines()[2:]]
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
        screen = terminal.wait_for(r"/burner \(callbacks\)(?:.*\n)*.*timer callback Burner")
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
