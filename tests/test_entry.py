"""The ``container`` command's signals before its session: held from site's first ``.pth``, then taken.

``container/_entry.py`` says why; ``tests/cli/test_signals.py`` sends signals
at every moment of a start-up, ``tests/benchmarks/sweep_early_signals.py``
200 times under load.
"""

from __future__ import annotations

import json
import signal
import site
import subprocess
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import pytest

from container._entry import _command_word
from tests.container_support import REPO
from tests.signal_support import CONSOLE_SCRIPT, as_from_a_shell

PTH = REPO / "container" / "interfaces" / "00_lifecycle_container.pth"
DEMO = REPO / "examples" / "demo.yaml"
BIN = Path(sys.executable).parent

#: Runs the ``.pth`` file's line for each ``sys.orig_argv`` given (a JSON list on
#: stdin) in a fresh interpreter without site, and prints what it blocked.
PROBE = """
import json, signal, sys
line = [l for l in open(sys.argv[1]) if l.startswith("import ")][0]
for argv in json.loads(sys.stdin.read()):
    signal.pthread_sigmask(signal.SIG_SETMASK, [])
    sys.orig_argv = argv
    exec(line, {})
    print(sorted(int(s) for s in signal.pthread_sigmask(signal.SIG_BLOCK, [])))
"""


def blocked_by_the_pth(*argvs: Sequence[str]) -> list[list[int]]:
    result = subprocess.run(
        [sys.executable, "-S", "-c", PROBE, str(PTH)],
        input=json.dumps([list(argv) for argv in argvs]),
        capture_output=True,
        text=True,
        check=True,
    )
    assert result.stderr == ""
    return [json.loads(line) for line in result.stdout.splitlines()]


HELD = [int(signal.SIGINT), int(signal.SIGTERM)]


def test_the_pth_file_holds_the_signals_of_the_container_command() -> None:
    assert blocked_by_the_pth(
        [sys.executable, "-m", "container", "run", "demo.yaml"],
        [sys.executable, str(BIN / "container"), "list"],
        [sys.executable, str(BIN / ".." / "bin" / "container")],
    ) == [HELD, HELD, HELD]


def test_the_pth_file_leaves_every_other_process_alone() -> None:
    """A process that held the signals and never took them could not be interrupted."""
    assert blocked_by_the_pth(
        [sys.executable],
        [sys.executable, "-c", "print('container')"],
        [sys.executable, "-m", "pytest", "-k", "container"],
        [sys.executable, "-m", "container.cli"],
        [sys.executable, "/elsewhere/container", "run"],
        [sys.executable, "tests/container"],
        [sys.executable, str(BIN / "ros2"), "run", "lifecycle_container", "component_container"],
    ) == [[]] * 7


def test_the_installed_pth_file_is_the_repositorys() -> None:
    installed = [Path(d) / PTH.name for d in site.getsitepackages() if (Path(d) / PTH.name).is_file()]
    if not installed:
        pytest.skip(f"{PTH.name} not installed here: no site-packages site reads holds it (a colcon install)")
    assert installed[0].read_text() == PTH.read_text()


def test_the_command_word_is_found_outside_ros_arguments() -> None:
    assert _command_word(["run", "demo.yaml"]) == "run"
    assert _command_word(["--ros-args", "-r", "__node:=x", "--", "manager", "-p", "a:=1"]) == "manager"
    assert _command_word(["--ros-args", "-r", "run:=x"]) is None
    assert _command_word(["-h"]) is None


@contextmanager
def held(*signums: int) -> Iterator[None]:
    """Block ``signums`` in this thread meanwhile: a child started now starts with them held."""
    signal.pthread_sigmask(signal.SIG_BLOCK, signums)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, signums)


def held_from_the_start(command: Sequence[str], signum: int) -> tuple[int, str]:
    """Start ``command`` with ``signum`` blocked and pending from its first instruction (as from a
    shell: Python is re-executed on the way)."""
    with held(signum):
        process = subprocess.Popen(
            list(command), cwd=REPO, env=as_from_a_shell(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
    process.send_signal(signum)  # pending: blocked in the child until the entry point takes it
    output, _ = process.communicate(timeout=30)
    return process.returncode, output


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_held_since_the_start_ends_a_server_with_one_line(signum: int) -> None:
    """Through the bootstrapper's re-exec of Python and the imports, to the entry point."""
    code, output = held_from_the_start([str(CONSOLE_SCRIPT), "run", str(DEMO)], signum)
    assert (code, output) == (128 + signum, f"container run: {signal.Signals(signum).name} received: exiting\n")


def test_a_signal_held_since_the_start_ends_a_client_command_quietly() -> None:
    code, output = held_from_the_start([sys.executable, "-m", "container", "list"], signal.SIGINT)
    assert (code, output) == (130, "")
