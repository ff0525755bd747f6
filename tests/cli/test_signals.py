"""Signals to a ``container run`` process, as a terminal and ``ros2 launch`` send them.

Ctrl-C under ``ros2 launch`` reaches the container twice (the terminal's
SIGINT to the process group, then launch's own) 0-30 ms apart: the
repetition must not cut the orderly shutdown short. Launch's escalation
(SIGTERM after ``sigterm_timeout``) and a third signal end it at once. A
signal during start-up ends it quietly, whenever it comes.

Each test drives several processes at once: a container costs about half a
second to start, and CI's time is short.
"""

from __future__ import annotations

import functools
import signal
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from tests.container_support import REPO, LoggedProcess
from tests.waiting import wait_until

pytestmark = pytest.mark.slow

DEMO = REPO / "examples" / "demo.yaml"
READY = "ready with"
RECEIVED = "SIGINT received: shutting down"
ABSORBED = "SIGINT again: already shutting down; a third signal exits at once"


@pytest.fixture
def spawn() -> Iterator[list[LoggedProcess]]:
    """The processes :func:`start` starts; all killed after the test."""
    started: list[LoggedProcess] = []
    yield started
    for process in started:
        process.close()


def start(started: list[LoggedProcess], *args: str) -> LoggedProcess:
    process = LoggedProcess([sys.executable, "-m", "container", *args], name="container")
    started.append(process)
    return process


def exit_code(process: LoggedProcess, *, timeout: float = 15.0) -> int:
    try:
        return process.process.wait(timeout)
    except Exception:
        raise AssertionError(f"still running {timeout} s after the signals:\n{process.output()}") from None


def finished_output(process: LoggedProcess) -> str:
    """All the output of an exited process (its reader has read to the end)."""
    process.close()
    return process.output(last=len(process.lines))


def many_nodes(directory: Path) -> Path:
    """A container file with a dozen active nodes: slow enough to start, and to stop,
    that a signal sent on a line of the container's lands while it still does."""
    path = directory / "many.yaml"
    path.write_text(
        "nodes:\n"
        + "".join(
            f"  - {{package: lifecycle_container, plugin: lifecycle_container::Talker, name: talker{i},"
            " autostart: true}\n"
            for i in range(12)
        )
    )
    return path


def catches(pid: int, signum: int) -> bool:
    """Whether the process has a handler of its own for ``signum`` (``SigCgt`` in /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) >> (signum - 1) & 1)
    return False


def test_a_repeated_sigint_is_absorbed_and_the_nodes_unload(spawn: list[LoggedProcess]) -> None:
    gaps = (0.0, 0.01, 0.03, 0.3)
    processes = [start(spawn, "run", str(DEMO)) for _ in gaps]
    for process in processes:
        process.wait_for_line(READY)
    began = time.monotonic()
    for process in processes:
        process.process.send_signal(signal.SIGINT)
    for gap, process in zip(gaps, processes, strict=True):
        # The stimulus, not a synchronisation: the second signal's delay.
        time.sleep(max(0.0, began + gap - time.monotonic()))
        process.process.send_signal(signal.SIGINT)
    for gap, process in zip(gaps, processes, strict=True):
        code = exit_code(process)
        output = finished_output(process)
        assert code == 0, f"second SIGINT after {gap * 1000:g} ms:\n{output}"
        assert "Unloaded '/talker'" in output, output
        assert "Unloaded '/listener'" in output, output
        assert "Traceback" not in output, output


#: A node whose deactivate awaits for a minute: the orderly shutdown lasts
#: until a signal cuts it short, however fast the machine.
HOLDING = """
container: {unload_timeout: 60.0}
nodes:
  - {package: tests_faults, plugin: tests_faults::FaultyAsync, name: holding, autostart: true,
     parameters: [{fault: await, where: deactivate, transition_timeout: 60.0}]}
"""


def test_sigterm_after_sigint_and_a_third_sigint_exit_at_once(
    spawn: list[LoggedProcess], tmp_path: Path, see_plugin: Callable[..., None]
) -> None:
    see_plugin(distribution="tests-faults", module="tests.fault_plugin")
    config = tmp_path / "holding.yaml"
    config.write_text(HOLDING, encoding="utf-8")
    escalated, third = start(spawn, "run", str(config)), start(spawn, "run", str(config))
    for process in (escalated, third):
        process.wait_for_line(READY)
        process.process.send_signal(signal.SIGINT)
    for process in (escalated, third):
        process.wait_for_line("misbehaving: await in deactivate")  # shutting down, held there
    escalated.process.send_signal(signal.SIGTERM)
    third.process.send_signal(signal.SIGINT)
    third.wait_for_line(ABSORBED)
    third.process.send_signal(signal.SIGINT)

    code = exit_code(escalated)
    output = finished_output(escalated)
    assert code == 143, output
    assert "SIGTERM after SIGINT: exiting at once" in output, output
    code = exit_code(third)
    output = finished_output(third)
    assert code == 130, output
    assert "SIGINT a third time: exiting at once" in output, output
    for process in (escalated, third):
        assert "Traceback" not in finished_output(process)


def test_a_signal_during_start_up_exits_quietly(spawn: list[LoggedProcess], tmp_path: Path) -> None:
    many = many_nodes(tmp_path)
    imports_sigint = start(spawn, "run", str(DEMO))
    imports_sigterm = start(spawn, "run", str(DEMO))
    loading = start(spawn, "run", str(many))
    for process, signum in ((imports_sigint, signal.SIGINT), (imports_sigterm, signal.SIGTERM)):
        # As soon as the command has its handlers (Python catches SIGINT
        # from its own start, SIGTERM only once we do): while it imports.
        wait_until(
            functools.partial(catches, process.process.pid, signal.SIGTERM),
            "the command's signal handlers",
            timeout=10,
        )
        process.process.send_signal(signum)
        assert process.lines == [], process.output()
    loading.wait_for_line("Loaded ")
    loading.process.send_signal(signal.SIGINT)

    for process, expected in ((imports_sigint, 130), (imports_sigterm, 143), (loading, 130)):
        code = exit_code(process)
        output = finished_output(process)
        assert code == expected, output
        assert "Traceback" not in output, output
    assert READY not in finished_output(loading)
