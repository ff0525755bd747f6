"""Shared test set-up: an isolated ROS domain, contexts, executors, processes.

Every test session picks a random ``ROS_DOMAIN_ID`` and keeps discovery on
this host, so concurrent runs never see each other. Child processes inherit
the same environment.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

os.environ["ROS_DOMAIN_ID"] = str(random.Random().randint(1, 101))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

from container._runtime import use_fast_discovery  # noqa: E402

use_fast_discovery()

import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402

from container import AsyncioExecutor  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture
def context() -> Iterator[Context]:
    """A fresh rclpy context, shut down after the test."""
    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.fixture
def executor(context: Context) -> Iterator[AsyncioExecutor]:
    """An AsyncioExecutor on ``context``, shut down after the test."""
    ex = AsyncioExecutor(context=context)
    try:
        yield ex
    finally:
        ex.shutdown(timeout_sec=5.0)


class ContainerProcess:
    """A ``container run`` child process whose output is read line by line."""

    def __init__(self, config: Path, *, args: tuple[str, ...] = ()) -> None:
        self.config = config
        self.lines: list[str] = []
        self._changed = threading.Condition()
        self.process = subprocess.Popen(
            [sys.executable, "-m", "container", "run", str(config), *args],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            bufsize=1,
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

    def wait_for_line(self, needle: str, *, timeout: float = 20.0, start: int = 0) -> str:
        """Block until a line containing ``needle`` appears; fail on timeout or exit."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                for line in self.lines[start:]:
                    if needle in line:
                        return line
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (self.process.poll() is not None and not self._reader.is_alive()):
                    output = "\n".join(self.lines[-40:])
                    raise AssertionError(f"no line with {needle!r} within {timeout} s:\n{output}")
                self._changed.wait(remaining)

    def stop(self, *, sig: int = signal.SIGTERM, timeout: float = 15.0) -> int:
        """Signal the process and wait for it; SIGKILL as a last resort."""
        if self.process.poll() is None:
            self.process.send_signal(sig)
        try:
            code = self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            raise AssertionError(f"container ignored signal {sig} for {timeout} s") from None
        self._reader.join(5.0)
        return code


@pytest.fixture
def run_container(tmp_path: Path) -> Iterator[Callable[..., ContainerProcess]]:
    """Start ``container run`` on YAML text; every process is stopped afterwards."""
    started: list[ContainerProcess] = []

    def start(config_text: str, *, args: tuple[str, ...] = (), ready: bool = True) -> ContainerProcess:
        path = tmp_path / f"container{len(started)}.yaml"
        path.write_text(config_text, encoding="utf-8")
        proc = ContainerProcess(path, args=args)
        started.append(proc)
        if ready:
            proc.wait_for_line("ready with")
        return proc

    yield start
    for proc in started:
        if proc.process.poll() is None:
            proc.process.kill()
            proc.process.wait()


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "shared: reads ../shared (skipped when absent)")
