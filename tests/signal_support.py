"""A signal sent to a starting ``container`` process at a set moment, and what became of it.

Shared by ``tests/cli/test_signals.py`` and the full sweep
(``tests/benchmarks/sweep_early_signals.py``).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from tests.container_support import REPO

__all__ = ["BOOTSTRAPPED", "COMMAND", "SignalTry", "as_from_a_shell", "signal_at", "signals_as_from_a_terminal"]

#: The environment's ``container`` command, as a terminal and ``ros2 launch`` run it:
#: a sh script that starts Python on itself with SIGINT and SIGTERM blocked
#: (``container/interfaces/container.in``), through the ROS wheels' bootstrapper,
#: which re-executes Python.
COMMAND = Path(sys.executable).parent / "container"

#: The ROS wheels' bootstrapper's guard: set in a process it re-executed
#: (this one), inherited by its children, which then run without re-executing.
BOOTSTRAPPED = "_ROS_WHEELS_BOOTSTRAP_COMPLETE"


def signals_as_from_a_terminal() -> None:
    """Let this process's children start with SIGINT and SIGTERM at their default action, as a
    terminal starts a command.

    A non-interactive shell starts a command it puts in the background
    (``cmd &``, as a CI runner or ``.ci/run`` may start the suite) with SIGINT
    ignored; an ignored signal stays ignored across ``exec``, so every child
    of the suite would inherit it, and a SIGINT reaching the launcher's shell
    before Python runs would be thrown away: not what a terminal or
    ``ros2 launch`` does. A signal this process handles in Python is reset to
    its default action in a child. Main thread only (:func:`signal.signal`).
    """
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if signal.getsignal(signal.SIGTERM) is signal.SIG_IGN:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def as_from_a_shell() -> dict[str, str]:
    """This process's environment without the bootstrapper's guard: a child re-executes Python,
    as one started from a terminal or by ``ros2 launch`` does."""
    return {name: value for name, value in os.environ.items() if name != BOOTSTRAPPED}


@dataclass
class SignalTry:
    """One process, one signal ``delay`` seconds after its start."""

    delay: float
    signum: int
    #: The exit status (``-N``: killed by signal N); ``None``: still running at the deadline.
    status: int | None
    #: From the signal to the exit, in seconds (``None``: still running).
    to_exit: float | None
    output: str

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def traceback(self) -> bool:
        return any(mark in self.output for mark in ("Traceback", "KeyboardInterrupt", "Fatal Python error"))

    @property
    def in_interpreter_start(self) -> bool:
        """A traceback from the first interpreter's own start, before site reads any ``.pth`` file of ours.

        CPython installs its SIGINT handler (``KeyboardInterrupt``) a few
        milliseconds before site processes the first ``.pth`` file; only a
        Python started with the signals blocked (the command's launcher,
        where env can block them) is safe there (``container/_entry.py``).
        """
        return "Fatal Python error: init_" in self.output and str(REPO) not in self.output

    @property
    def ignored(self) -> bool:
        return "Exception ignored" in self.output

    @property
    def killed_before_python(self) -> bool:
        """Ended by the signal's default action, silently, before Python ran any code of ours
        (in the launcher's shell, before its ``exec``)."""
        return self.status == -self.signum and not self.output.strip()

    @property
    def deadline(self) -> bool:
        """Ended by the start-up's deadline, not by its orderly stop."""
        return "without a clean shutdown" in self.output

    @property
    def after_ready(self) -> bool:
        """The container said it was ready before the signal: the ordinary stop, status 0."""
        return "ready with" in self.output

    @property
    def expected_status(self) -> int:
        return 0 if self.after_ready else 128 + self.signum

    @property
    def signal_lines(self) -> int:
        return sum(1 for line in self.output.splitlines() if self.name in line)

    def problems(self) -> list[str]:
        """What went wrong: empty for exactly one line and ``128 + signal`` (0 once the container
        said it was ready), or a silent kill before Python."""
        found = []
        if self.traceback:
            found.append("traceback in the interpreter's start" if self.in_interpreter_start else "traceback")
        if self.ignored:
            found.append("ignored")
        if self.status is None:
            found.append("still running")
        elif not self.killed_before_python and not self.traceback:
            if self.status != self.expected_status:
                found.append(f"status {self.status}")
            if self.signal_lines != 1:
                found.append(f"{self.signal_lines} lines naming {self.name}")
        return found

    def describe(self) -> str:
        problems = ", ".join(self.problems()) or "fine"
        return f"{self.name} at {self.delay * 1000:.0f} ms: {problems} (status {self.status})\n{self.output}"


def signal_at(command: Sequence[str], delay: float, signum: int, *, deadline: float = 3.0) -> SignalTry:
    """Start ``command``, send it ``signum`` ``delay`` seconds later, wait up to ``deadline`` s for its end.

    The process starts as from a shell (:func:`as_from_a_shell`). The delay
    is the stimulus, slept on purpose; the end is waited on. A process still
    running at the deadline is killed (its group).
    """
    process = subprocess.Popen(
        list(command),
        cwd=REPO,
        env=as_from_a_shell(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    started = time.monotonic()
    stdout = process.stdout
    assert stdout is not None
    chunks: list[str] = []
    reader = threading.Thread(target=lambda: chunks.append(stdout.read()), daemon=True)
    reader.start()
    time.sleep(max(0.0, started + delay - time.monotonic()))
    process.send_signal(signum)
    sent = time.monotonic()
    status: int | None
    to_exit: float | None
    try:
        status = process.wait(deadline)
        to_exit = time.monotonic() - sent
    except subprocess.TimeoutExpired:
        status, to_exit = None, None
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    reader.join(10.0)
    stdout.close()
    return SignalTry(delay, signum, status, to_exit, "".join(chunks))
