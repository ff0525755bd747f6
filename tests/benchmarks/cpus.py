"""``--cpus N``, shared by the benchmarks: run on N CPUs, and every process started too.

A robot may give the container one CPU (``docker --cpus=1``, a cpuset,
``taskset``) or four to eight. With ``--cpus N`` a benchmark re-executes
itself under ``taskset -c`` on the first N CPUs it may use (``0-(N-1)`` on
a machine that lets it use all of them; ``0`` for one), before it measures
anything: every contender, peer and helper process it starts inherits that
affinity. N above what the process may use (its affinity, bounded by its
cgroup CPU quota: ``container.executor._cores``) is refused. Each
benchmark's header says which CPUs it ran on (:func:`header`).

Only the benchmark's own process calls :func:`pin` and :func:`header`,
which import the container's code: a child started under another
virtualenv (``bench_executor.py --pythons``, the code before a change)
imports this module without importing anything of the container through it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys

__all__ = ["add_option", "header", "pin"]

#: Set in the re-executed process: the CPU list it asked taskset for (a loop guard).
PINNED = "BENCH_CPUS_PINNED"


def add_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--cpus N`` to a benchmark's options."""
    parser.add_argument(
        "--cpus", type=int, metavar="N",
        help="run on N CPUs (taskset -c 0-(N-1)), every process the benchmark starts too; "
        "default: the CPUs this process may use",
    )  # fmt: skip


def pin(parser: argparse.ArgumentParser, cpus: int | None) -> None:
    """Re-execute this script under ``taskset`` on ``cpus`` CPUs, unless it runs on them already.

    Returns only when nothing is to be done (``cpus`` is ``None``, or the
    affinity is already those CPUs); a count this process cannot have ends
    it through ``parser.error``.
    """
    if cpus is None:
        return
    from container.executor._cores import usable_cpus

    allowed = sorted(os.sched_getaffinity(0))
    usable = usable_cpus()
    if cpus < 1:
        parser.error(f"--cpus {cpus}: at least 1")
    if cpus > usable:
        parser.error(
            f"--cpus {cpus}: this process may use {usable} CPU(s) of the machine's {os.cpu_count()} ({_limits()})"
        )
    wanted = allowed[:cpus]
    if allowed == wanted:
        return
    listed = _listed(wanted)
    if os.environ.get(PINNED) == listed:
        parser.error(f"--cpus {cpus}: taskset -c {listed} left this process on CPUs {_listed(allowed)}")
    taskset = shutil.which("taskset")
    if taskset is None:
        parser.error("--cpus needs taskset (util-linux)")
    os.environ[PINNED] = listed
    sys.stdout.flush()
    os.execv(taskset, [taskset, "-c", listed, sys.executable, *sys.orig_argv[1:]])


def header() -> str:
    """One line for a benchmark's header: the CPUs it runs on."""
    allowed = sorted(os.sched_getaffinity(0))
    return f"CPUs: {len(allowed)} ({_listed(allowed)}) of the machine's {os.cpu_count()}; {_limits()}"


def _limits() -> str:
    from container.executor._cores import cpu_quota

    quota = cpu_quota()
    allowed = _listed(sorted(os.sched_getaffinity(0)))
    return f"affinity {allowed}, " + ("no cgroup CPU quota" if quota is None else f"cgroup CPU quota {quota:g}")


def _listed(cpus: list[int]) -> str:
    """``[0, 1, 2, 5]`` as taskset's list: ``0-2,5``."""
    runs: list[str] = []
    start: int | None = None
    previous: int | None = None
    for cpu in [*cpus, None]:
        if cpu is not None and previous is not None and cpu == previous + 1:
            previous = cpu
            continue
        if start is not None:
            runs.append(str(start) if start == previous else f"{start}-{previous}")
        start = previous = cpu
    return ",".join(runs)
