"""Signals to a ``container run`` process, as a terminal and ``ros2 launch`` send them.

Ctrl-C under ``ros2 launch`` reaches the container twice (the terminal's
SIGINT to the process group, then launch's own) 0-30 ms apart: the
repetition must not cut the orderly shutdown short. Launch's escalation
(SIGTERM after ``sigterm_timeout``) and a third signal end it at once. A
signal during start-up, whenever it comes (while Python starts, imports,
discovers plugins, starts rcl, loads nodes), ends it within a second with
one line and 130/143; a client command, quietly. The full sweep, 200 tries
under load, is ``tests/benchmarks/sweep_early_signals.py``.

Each test drives several processes at once: a container costs about half a
second to start, and CI's time is short.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from tests.container_support import REPO, LoggedProcess
from tests.signal_support import COMMAND, as_from_a_shell, signal_at

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
        raise AssertionError(f"still running {timeout} s after the signals:\n{process.stacks()}") from None


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
    escalated = start(spawn, "run", str(config))
    third = LoggedProcess(
        [sys.executable, "-m", "container", "run", str(config)],
        env={**os.environ, "ROS_LOG_DIR": str(tmp_path / "log")},
        name="container",
    )
    spawn.append(third)
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
    # What the operator asked for: a warning, not an error; in the log file
    # too, though the process ends at once.
    assert "[WARN]" in third.wait_for_line("SIGINT a third time: exiting at once"), output
    (log_file,) = (tmp_path / "log").glob("*.log")
    assert "SIGINT a third time: exiting at once" in log_file.read_text(), log_file.read_text()
    for process in (escalated, third):
        assert "Traceback" not in finished_output(process)


#: Whether the launcher starts Python with the signals blocked here (coreutils' env 8.31 or later).
ENV_BLOCKS_SIGNALS = subprocess.run(["env", "--block-signal=INT", "true"], capture_output=True).returncode == 0

#: Moments of the start-up, in seconds after the process starts: 0 to 480 ms.
MOMENTS = [step * 0.02 for step in range(25)]


def test_a_signal_at_any_moment_of_start_up_ends_it_with_one_line() -> None:
    """Before, during and after the re-exec of Python, its imports, plugin
    discovery, rcl's start, the container node, the first loads: SIGINT and
    SIGTERM by turns. The command, as a terminal runs it. One after the
    other, 5-10 s in all."""
    tries = [
        signal_at(
            [str(COMMAND), "run", str(DEMO)], moment, signal.SIGINT if step % 2 == 0 else signal.SIGTERM
        )
        for step, moment in enumerate(MOMENTS)
    ]
    # The first interpreter's own start (CPython's SIGINT handler, a few ms
    # before site reads the first .pth file) is before any code of ours: only
    # the launcher's env, where it can block signals, covers it.
    wrong = [t for t in tries if t.problems() and not (t.in_interpreter_start and not ENV_BLOCKS_SIGNALS)]
    assert wrong == [], "\n\n".join(t.describe() for t in wrong)
    slow = [t for t in tries if t.to_exit is not None and t.to_exit > 1.5]  # a loaded CI machine's margin
    assert slow == [], "\n\n".join(f"{t.to_exit:.2f} s: {t.describe()}" for t in slow)


def test_a_signal_while_the_nodes_load_stops_them_with_one_line(spawn: list[LoggedProcess], tmp_path: Path) -> None:
    loading = start(spawn, "run", str(many_nodes(tmp_path)))
    loading.wait_for_line("Loaded ")
    loading.process.send_signal(signal.SIGINT)
    code = exit_code(loading)
    output = finished_output(loading)
    assert code == 130, output
    (said,) = [line for line in output.splitlines() if "SIGINT" in line]
    assert said.endswith(RECEIVED), output
    assert "Traceback" not in output, output
    assert READY not in output, output


@pytest.mark.parametrize("command", [("list", "--spin-time", "60"), ("top", "/nobody"), ("types",)])
def test_a_client_command_cut_short_while_it_starts_is_quiet(command: tuple[str, ...]) -> None:
    # ``types`` is done in 0.34 s on Python 3.11 here: a signal at 300 ms can
    # come once its whole answer is written, as it exits. That answer, then,
    # and the signal's end or the command's own, with nothing said of it.
    whole = None
    if command == ("types",):
        whole = subprocess.run(
            [str(COMMAND), *command], cwd=REPO, env=as_from_a_shell(), stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True, timeout=30, check=True,
        ).stdout
    for moment, signum in ((0.1, signal.SIGINT), (0.3, signal.SIGTERM)):
        cut = signal_at([str(COMMAND), *command], moment, signum)
        if cut.killed_before_python:
            continue
        if whole and cut.output == whole:
            assert cut.status in (0, -signum, 128 + signum), cut.describe()
            continue
        assert (cut.status, cut.output) == (128 + signum, ""), cut.describe()


def test_sigusr1_writes_every_threads_stack_and_the_container_serves_on(spawn: list[LoggedProcess]) -> None:
    """Where a container that does not end, or stops answering, is: ``kill -USR1``."""
    process = start(spawn, "run", str(DEMO))
    process.wait_for_line(READY)
    output = process.stacks()
    assert "(most recent call first)" in output, output
    assert "Thread 0x" in output or "Current thread 0x" in output, output
    assert 'File "' in output and "container" in output, output
    assert process.process.poll() is None, "SIGUSR1 ended the container"
    process.process.send_signal(signal.SIGINT)
    assert exit_code(process) == 0, finished_output(process)
