"""Child processes for tests, their output read line by line: any command, or ``container run``.

Lives outside ``conftest.py`` so test modules can import it by a name that no
other directory's ``conftest`` shadows.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


class LoggedProcess:
    """``command`` as a child process; stdout and stderr read line by line into :attr:`lines`."""

    def __init__(
        self, command: Sequence[str], *, env: Mapping[str, str] | None = None, name: str = ""
    ) -> None:
        self.name = name or os.path.basename(command[0])
        self.lines: list[str] = []
        self._changed = threading.Condition()
        self.process = subprocess.Popen(
            [*_ends_with_this_process(), *command],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            bufsize=1,
            env=None if env is None else dict(env),
            # Its own process group, so that a wrapper (ip netns exec) and
            # what it runs get a signal together.
            start_new_session=True,
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            with self._changed:
                self.lines.append(line.rstrip("\n"))
                self._changed.notify_all()
        with self._changed:
            self._changed.notify_all()

    def output(self, last: int = 60) -> str:
        return "\n".join(f"{self.name}| {line}" for line in self.lines[-last:])

    def wait_for_line(self, needle: str, *, timeout: float = 20.0, start: int = 0) -> str:
        """Block until a line containing ``needle`` appears (from line ``start`` on); fail on timeout or exit."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                for line in self.lines[start:]:
                    if needle in line:
                        return line
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (self.process.poll() is not None and not self._reader.is_alive()):
                    raise AssertionError(f"no line with {needle!r} within {timeout} s:\n{self.output()}")
                self._changed.wait(remaining)

    def stacks(self, *, timeout: float = 3.0) -> str:
        """The output once a container asked for its threads' stacks (SIGUSR1) has written them.

        For a failure's message: where a process that should have ended is.
        """
        if self.process.poll() is not None:
            return self.output()
        start = len(self.lines)
        self.process.send_signal(signal.SIGUSR1)
        with contextlib.suppress(AssertionError):
            self.wait_for_line("(most recent call first)", timeout=timeout, start=start)
            # The rest of the dump: its lines come at once; read until they pause.
            deadline = time.monotonic() + timeout
            with self._changed:
                while self._changed.wait(0.5) and time.monotonic() < deadline:
                    pass
        dumped = self.output(last=len(self.lines) - start + 60)
        native = native_stacks(self.process.pid)
        return f"{dumped}\n{native}" if native else dumped

    def stop(self, *, sig: int = signal.SIGTERM, timeout: float = 15.0) -> int:
        """Signal the process group and wait; SIGKILL as a last resort (then fail)."""
        if self.process.poll() is None:
            os.killpg(self.process.pid, sig)
        try:
            code = self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            stacks = self.stacks()
            self.close()
            raise AssertionError(f"{self.name} ignored signal {sig} for {timeout} s:\n{stacks}") from None
        self.close()
        return code

    def close(self) -> None:
        """Kill the process group if it still runs, and release the pipe."""
        if self.process.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()
        self._reader.join(5.0)
        if self.process.stdout is not None:
            self.process.stdout.close()


class ContainerProcess(LoggedProcess):
    """A ``container run`` child process on the container file ``config``."""

    def __init__(self, config: Path, *, args: tuple[str, ...] = ()) -> None:
        self.config = config
        super().__init__([sys.executable, "-m", "container", "run", str(config), *args], name="container")


def _ends_with_this_process() -> list[str]:
    """A prefix that has the child sent SIGTERM when this process ends, however it ends.

    pytest-timeout's thread method ends a stuck test process with ``os._exit``:
    no fixture's teardown runs, and a container it had started stayed on the
    test's ROS domain (a ``/ComponentManager`` the next run's component tests
    found). ``setpriv --pdeathsig`` sets ``PR_SET_PDEATHSIG``, kept across
    exec; the signal comes when the *thread* that started the child ends, so
    only the main thread's children get it (a helper thread's end is not the
    test's).
    """
    setpriv = shutil.which("setpriv")
    if setpriv is None or threading.current_thread() is not threading.main_thread():
        return []
    return [setpriv, "--pdeathsig", "TERM", "--"]


def native_stacks(pid: int, *, timeout: float = 30.0, frames: int = 25) -> str:
    """Every thread's C stack of ``pid`` (gdb attached for a moment), or nothing without gdb.

    For where a process hangs outside Python: Fast DDS's own threads, or
    the main thread in the interpreter's teardown, where the SIGUSR1 dump
    shows only "Garbage-collecting" and no Python frame.
    """
    gdb = shutil.which("gdb")
    if gdb is None:
        return ""
    try:
        done = subprocess.run(
            [gdb, "-p", str(pid), "-batch", "-nx", "-ex", "set pagination off",
             "-ex", f"thread apply all bt {frames}"],
            capture_output=True, text=True, timeout=timeout, check=False,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"native stacks: gdb failed: {exc}"
    lines = [line for line in done.stdout.splitlines() if line.startswith(("Thread ", "#"))]
    return "native stacks (gdb):\n" + "\n".join(lines[-400:])
