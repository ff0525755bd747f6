"""``Deadline``: the process ends with a given status at a given moment, unless cancelled first.

Run in processes of their own, on each engine (a deadline that expires
ends the process it is in).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from container.executor._engine import VARIABLE

#: ``{arm}`` then ``{then}``, after rcl's logging is set up.
SCRIPT = """
import ctypes, sys, time
import rclpy
rclpy.init()
from container.executor import Deadline
deadline = Deadline({seconds}, code=7, logger="deadline_test", message="out of time: status 7")
{then}
print("carried on", flush=True)
sys.exit(3)
"""


def run(engine: str, *, seconds: float, then: str) -> tuple[int, str, float]:
    began = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT.format(seconds=seconds, then=then)],
        env={**os.environ, VARIABLE: engine}, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    return done.returncode, done.stdout + done.stderr, time.monotonic() - began


@pytest.mark.parametrize("engine", ["compiled", "python"])
def test_a_cancelled_deadline_leaves_the_process_alone(engine: str) -> None:
    code, output, _ = run(engine, seconds=0.3, then="deadline.cancel(); deadline.cancel(); time.sleep(0.6)")
    assert (code, output) == (3, "carried on\n")


@pytest.mark.parametrize("engine", ["compiled", "python"])
def test_an_expired_deadline_says_so_and_ends_the_process_with_its_status(engine: str) -> None:
    code, output, took = run(engine, seconds=0.3, then="time.sleep(30)")
    assert code == 7, output
    assert "[WARN]" in output and "[deadline_test]: out of time: status 7" in output, output
    assert "carried on" not in output
    assert took < 20, output


def test_the_compiled_deadline_ends_a_process_whose_gil_is_held_for_good() -> None:
    # What it exists for: a destructor deep in rcl that never returns, the GIL held.
    code, output, took = run("compiled", seconds=0.3, then="ctypes.PyDLL(None).sleep(3600)")
    assert code == 7, output
    assert "out of time: status 7" in output, output
    assert took < 20, output


def test_a_deadline_refuses_a_time_it_cannot_keep() -> None:
    from container.executor import Deadline

    with pytest.raises(ValueError, match="seconds from 0 to 1e9"):
        Deadline(-1.0, code=1, logger="x", message="never")
