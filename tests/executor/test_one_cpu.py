"""The executor on one CPU: no thread spins for another, and everything still runs.

With one CPU, a thread that stays awake for another's hand-over (see
``fastpath/handoff.c``) only keeps that thread off the CPU; the executor
then makes its ``Handoff`` without spinning (``_dispatch``, from
``_cores.usable_cpus``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time

import pytest

from container import AsyncioExecutor
from container.executor._cores import usable_cpus
from container.executor._engine import Handoff
from tests.container_support import REPO
from tests.executor import one_cpu_child as child


def test_the_handoff_spins_only_with_more_than_one_cpu(executor: AsyncioExecutor) -> None:
    assert executor._dispatcher.handoff.spin is (usable_cpus() > 1)


def test_a_handoff_without_spin_waits_for_starts_and_never_stays_awake() -> None:
    """``give`` still lets go of the GIL until the woken worker started (that
    is what gives it the CPU), then returns without waiting for its end;
    ``linger`` returns at once."""
    handoff = Handoff(spin=False)
    assert handoff.spin is False
    started = time.monotonic()
    assert handoff.linger(2_000_000_000) is False  # 2 s asked: not one spent
    assert time.monotonic() - started < 0.5

    finished = threading.Event()

    def worker() -> None:
        time.sleep(0.05)  # started late, as a woken thread is
        handoff.started()
        finished.wait(10.0)
        handoff.finished()

    handoff.handed()
    thread = threading.Thread(target=worker)
    began = time.monotonic()
    thread.start()
    try:
        assert handoff.give(5_000_000_000, 5_000_000_000) is True  # waited for the start...
        waited = time.monotonic() - began
    finally:
        finished.set()
        thread.join(10.0)
    assert 0.04 < waited < 2.0, waited  # ...not for the end (5 s bound) nor the spin


# A child process for several seconds (four scenarios under taskset).
@pytest.mark.slow
@pytest.mark.skipif(shutil.which("taskset") is None, reason="taskset (util-linux) is not installed")
def test_on_one_cpu_nothing_spins_and_plain_async_and_blocked_work_all_run() -> None:
    cpu = min(os.sched_getaffinity(0))  # taskset -c 0, unless this process may not use CPU 0
    result = subprocess.run(
        ["taskset", "-c", str(cpu), sys.executable, "-m", "tests.executor.one_cpu_child"],
        capture_output=True, text=True, timeout=50, check=False, cwd=REPO,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-4000:]
    seen = json.loads(result.stdout.strip().splitlines()[-1])
    assert seen["affinity"] == [cpu] and seen["usable_cpus"] == 1, seen
    assert seen["spin"] is False and seen["lingered"] == 0, seen
    assert seen["ping_pong"] == child.ROUND_TRIPS, seen
    assert seen["plain_service_calls"] == child.CALLS, seen
    assert seen["async_service_calls"] == child.CALLS, seen
    gaps = seen["gaps"]
    assert len(gaps) == child.TICKS, seen
    # A 20 Hz timer: under two periods (the blocker's 1 s blocks would show as 1 s).
    assert max(gaps) < 2 * child.PERIOD, f"largest gap {max(gaps) * 1000:.0f} ms beside a callback blocked for 1 s"
