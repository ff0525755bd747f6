"""The ``container`` command's signals before its session: held from Python's start, then taken.

The command's launchers (``bin/container``, ``lib/lifecycle_container/*``,
sh scripts) start Python with SIGINT and SIGTERM blocked; site's first
``.pth`` file blocks them in a ``container`` process Python started some
other way; the entry point takes them. ``container/_entry.py`` says why;
``tests/cli/test_signals.py`` sends signals at every moment of a start-up,
``tests/benchmarks/sweep_early_signals.py`` 200 times under load.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import site
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import pytest

from container import _ament
from container._ament import EXECUTABLES, PROJECT_PACKAGE, write_index
from container._entry import _command_word
from tests.container_support import REPO
from tests.signal_support import COMMAND, as_from_a_shell

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
    """Python on the command's file, as its launcher starts it: through the bootstrapper's
    re-exec of Python and the imports, to the entry point."""
    code, output = held_from_the_start([sys.executable, str(COMMAND), "run", str(DEMO)], signum)
    assert (code, output) == (128 + signum, f"container run: {signal.Signals(signum).name} received: exiting\n")


def test_a_signal_held_since_the_start_ends_a_client_command_quietly() -> None:
    code, output = held_from_the_start([sys.executable, "-m", "container", "list"], signal.SIGINT)
    assert (code, output) == (130, "")


# -- the launchers: sh scripts that start Python with the signals blocked ----------

#: Stands in for a virtualenv's interpreter: prints the signals it started
#: with blocked, and its arguments (without site: nothing blocks them on the way).
FAKE_PYTHON = f"""#!{sys.executable} -S
import json, signal, sys
print(json.dumps([sorted(int(s) for s in signal.pthread_sigmask(signal.SIG_BLOCK, [])), sys.argv[1:]]))
"""


def _executable(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    path.chmod(0o755)
    return path


def started(launcher: Path, *args: str, env: dict[str, str] | None = None) -> tuple[list[int], list[str]]:
    """What ``launcher`` started (a stand-in Python): the signals blocked at its start, its arguments."""
    result = subprocess.run([str(launcher), *args], capture_output=True, text=True, env=env, timeout=30)
    assert (result.returncode, result.stderr) == (0, ""), result.stderr
    blocked, argv = json.loads(result.stdout)
    return blocked, argv


@pytest.fixture
def venv(tmp_path: Path) -> Path:
    """A copy of this environment's launchers (``bin/container``, ``lib/lifecycle_container/*``)
    in a virtualenv whose ``bin/python`` is :data:`FAKE_PYTHON`."""
    if not (COMMAND.is_file() and "python=${script%/*}/python\n" in COMMAND.read_text()):
        pytest.skip(f"no launcher of the wheel's at {COMMAND} (a colcon install's has its interpreter written in)")
    root = tmp_path / "venv"
    _executable(root / "bin" / "python", FAKE_PYTHON)
    shutil.copy2(COMMAND, root / "bin" / "container")
    shutil.copytree(Path(sys.prefix) / "lib" / PROJECT_PACKAGE, root / "lib" / PROJECT_PACKAGE)
    return root


def test_the_command_starts_python_on_its_own_file_with_the_signals_held(venv: Path) -> None:
    command = venv / "bin" / "container"
    assert started(command, "run", "a b.yaml") == (HELD, [str(command), "run", "a b.yaml"])
    # Through a symlink elsewhere (~/bin/container): the virtualenv's Python still.
    link = venv.parent / "elsewhere" / "container"
    link.parent.mkdir()
    link.symlink_to(command)
    assert started(link, "list") == (HELD, [str(command), "list"])


def test_the_command_starts_python_plainly_where_env_cannot_block_signals(venv: Path, tmp_path: Path) -> None:
    """An env without --block-signal (coreutils before 8.31, busybox): the .pth file holds them then."""
    old_env = _executable(tmp_path / "old" / "env", '#!/bin/sh\necho "env: unrecognized option" >&2\nexit 125\n')
    path = {**os.environ, "PATH": f"{old_env.parent}{os.pathsep}{os.environ['PATH']}"}
    command = venv / "bin" / "container"
    assert started(command, "run", env=path) == ([], [str(command), "run"])
    # This environment's Python on its own command's file, as the launcher starts it.
    assert blocked_by_the_pth([sys.executable, str(COMMAND), "run"]) == [HELD]


@pytest.mark.parametrize("executable", sorted(EXECUTABLES))
def test_the_ament_executables_start_python_on_the_command_with_the_signals_held(venv: Path, executable: str) -> None:
    """What ros2 run and launch_ros start: Python straight on ``bin/container`` (dash, Debian's sh,
    would clear the mask if another sh script came between)."""
    launcher = venv / "lib" / PROJECT_PACKAGE / executable
    command = venv / "bin" / "container"
    assert started(launcher, "--ros-args", "-r", "__node:=c") == (
        HELD, [str(command), EXECUTABLES[executable], "--ros-args", "-r", "__node:=c"]
    )


def test_the_executables_container_index_writes_start_python_with_the_signals_held(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A colcon install's (``container index``, with the interpreter it runs under written in)."""
    python = _executable(tmp_path / "with space" / "python", FAKE_PYTHON)
    prefix = (tmp_path / "prefix").resolve()
    # As in a colcon install prefix: the container's own distribution installed there.
    monkeypatch.setattr(_ament, "installed_prefix", lambda distribution: prefix)
    report = write_index(prefix, [], python=str(python))
    assert PROJECT_PACKAGE in report.registered, report
    for executable in EXECUTABLES:
        launcher = tmp_path / "prefix" / "lib" / PROJECT_PACKAGE / executable
        assert started(launcher, "--ros-args") == (HELD, [str(launcher), "--ros-args"])


def test_the_command_is_named_container_wherever_it_is_started_from(tmp_path: Path) -> None:
    link = tmp_path / "container"
    link.symlink_to(COMMAND)
    result = subprocess.run([str(link), "--help"], capture_output=True, text=True, env=as_from_a_shell(), timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usage: container "), result.stdout


#: A command whose interpreter exit never ends (an atexit callback that sleeps
#: for ten minutes: registered first, it runs after everything else), with
#: the grace cut from 20 s to 2 s.
_HANGING_EXIT = (
    "import atexit, sys, time; atexit.register(time.sleep, 600); "
    "sys.argv = ['container', 'types']; import container.__main__ as entry; entry._EXIT_GRACE_S = 2.0; "
    "sys.exit(entry.main())"
)


def test_an_exit_that_never_ends_is_cut_off_with_every_threads_stack() -> None:
    began = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-c", _HANGING_EXIT], cwd=REPO, capture_output=True, text=True, timeout=90, check=False
    )
    took = time.monotonic() - began
    assert done.returncode == 1, done.stderr[-2000:]
    assert "Timeout (0:00:02)!" in done.stderr, done.stderr[-2000:]
    assert "(most recent call first)" in done.stderr, done.stderr[-2000:]
    assert 2.0 <= took < 30.0, took
