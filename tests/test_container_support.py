"""The tests' own child processes: what they leave behind when a test process dies."""

from __future__ import annotations

import os
import select
import shutil
import subprocess
import sys

import pytest

from tests.container_support import REPO

_DIES = """
import os
from tests.container_support import LoggedProcess
child = LoggedProcess(["sh", "-c", "echo started; exec sleep 300"])
child.wait_for_line("started")  # past setpriv's prctl: this process's end now signals it
print(child.process.pid, flush=True)
os._exit(3)  # as pytest-timeout's thread method ends a stuck test process
"""


@pytest.mark.skipif(shutil.which("setpriv") is None, reason="setpriv (util-linux) is not installed")
def test_a_child_ends_when_the_test_process_ends_without_teardown() -> None:
    """No fixture's teardown runs after ``os._exit``; the child must end anyway."""
    done = subprocess.run(
        [sys.executable, "-c", _DIES], capture_output=True, text=True, timeout=30, check=False, cwd=REPO
    )
    assert done.returncode == 3, done.stderr[-2000:]
    pid = int(done.stdout.split()[0])
    try:
        handle = os.pidfd_open(pid)
    except ProcessLookupError:
        return  # gone already
    try:
        readable, _, _ = select.select([handle], [], [], 10.0)
    finally:
        os.close(handle)
    assert readable, f"the child {pid} outlived its test process by 10 s"
