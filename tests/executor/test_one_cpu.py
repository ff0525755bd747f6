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
from tests.engine_support import compiled_only
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


#: Runs at idle priority on one CPU until killed, as CI's later set-ups and
#: test_colcon's prebuild do beside a leg pinned to that CPU.
_IDLE_WORK = """
import os, sys
os.sched_setaffinity(0, {int(sys.argv[1])})
try:
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
except OSError:
    os.nice(19)
print("busy", flush=True)
while True:
    pass
"""


# A pytest of its own (about 5 s), pinned beside the idle work.
@pytest.mark.slow
@compiled_only("carrier deferral")
@pytest.mark.skipif(shutil.which("taskset") is None, reason="taskset (util-linux) is not installed")
def test_on_one_cpu_beside_idle_work_a_carriers_publish_still_does_not_wake_the_loop() -> None:
    """The CPU busy at idle priority, the worker a released GIL wakes runs at
    once, before the loop's next line: the loop had to tell carriers when it
    wakes before letting go of the GIL, or every other message of a 2 ms
    timer woke it (CI's pinned Jazzy 3.13 leg failed so in test_fastpath)."""
    cpu = min(os.sched_getaffinity(0))
    test = "tests/executor/test_fastpath.py::test_a_plain_timers_publish_to_a_plain_callback_does_not_wake_the_loop"
    inherited = {k: v for k, v in os.environ.items() if k not in ("CI_PROGRESS_FILE", "CI_SKIP_FILE")}
    with subprocess.Popen([sys.executable, "-c", _IDLE_WORK, str(cpu)], stdout=subprocess.PIPE, text=True) as idle:
        try:
            assert idle.stdout is not None and idle.stdout.readline() == "busy\n"
            result = subprocess.run(
                ["taskset", "-c", str(cpu), sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", test],
                capture_output=True, text=True, timeout=50, check=False, cwd=REPO, env=inherited,
            )  # fmt: skip
        finally:
            idle.kill()
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert "1 passed" in result.stdout, result.stdout[-2000:]
