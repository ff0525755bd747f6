"""rclpy's own executor tests, run with AsyncioExecutor in place of rclpy's executors.

Run: ``.venv/bin/python tests/benchmarks/rclpy_suite.py --tests DIR``

``DIR`` holds rclpy's test files of the distribution in use, for Jazzy:
``git clone -b jazzy https://github.com/ros2/rclpy`` and pass
``rclpy/rclpy/test``. They import ``test_msgs``
(``pip install ros-jazzy-test-msgs`` into the virtualenv; the project does
not depend on it). Each file runs in a pytest process of its own, first with
rclpy's executors (the peer, which should pass everything) and then with
``rclpy.executors.SingleThreadedExecutor`` and ``MultiThreadedExecutor``
replaced by subclasses of :class:`container.AsyncioExecutor` before the file
is imported (this module is also the pytest plugin that does it). A file
that does not finish within ``--timeout`` runs again one test per process,
so one test that hangs counts as one failure. Printed: the tests that fail
with AsyncioExecutor only, and the count that pass under each.

Every difference this shows is meant to be a row of the executor's table of
differences (``docs/executor/contract.md``), each with a test of its own in
``tests/executor/test_conformance.py``.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

#: rclpy's test files that exercise an executor's contract.
FILES = (
    "test_executor.py",
    "test_guard_condition.py",
    "test_timer.py",
    "test_client.py",
    "test_service.py",
    "test_task.py",
    "test_callback_group.py",
    "test_waitable.py",
    "test_create_while_spinning.py",
    "test_rate.py",
    "test_service_introspection.py",
)
_SUBSTITUTE = "LIFECYCLE_CONTAINER_SUBSTITUTE_EXECUTOR"
#: pytest's ``-rA`` summary lines: ``PASSED file::test[id, maybe with spaces]`` (`` - why``).
_RESULT = re.compile(r"^(PASSED|FAILED|ERROR) (\S+::.+?)(?: - .*)?$", re.M)


# -- the pytest plugin (-p rclpy_suite) -----------------------------------------------
def pytest_configure(config: Any) -> None:
    if os.environ.get(_SUBSTITUTE) != "1":
        return
    import rclpy.executors

    from container import AsyncioExecutor

    class SingleThreadedExecutor(AsyncioExecutor):
        """rclpy's name, this project's executor."""

    class MultiThreadedExecutor(AsyncioExecutor):
        """rclpy's name and positional ``num_threads``, this project's executor."""

        def __init__(self, num_threads: int | None = None, *, context: Any = None) -> None:
            super().__init__(num_threads=num_threads, context=context)

    # Replaced before the test file imports the names.
    setattr(rclpy.executors, "SingleThreadedExecutor", SingleThreadedExecutor)  # noqa: B010
    setattr(rclpy.executors, "MultiThreadedExecutor", MultiThreadedExecutor)  # noqa: B010


# -- the runner ---------------------------------------------------------------------------------
def run(target: list[str], *, cwd: Path, substitute: bool, timeout: float) -> dict[str, str] | None:
    """Outcome of every test ``target`` names (in ``cwd``), or ``None`` if it did not finish in time."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")]))
    env[_SUBSTITUTE] = "1" if substitute else "0"
    command = [sys.executable, "-m", "pytest", "-p", "rclpy_suite", "-p", "no:cacheprovider", "-rA", "-q", *target]
    try:
        done = subprocess.run(
            command, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
        )
    except subprocess.TimeoutExpired:
        return None
    outcomes: dict[str, str] = {}
    for match in _RESULT.finditer(done.stdout):
        outcomes[match.group(2)] = match.group(1)
    return outcomes


def collect(path: Path) -> list[str]:
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", path.name],
        cwd=path.parent,
        capture_output=True,
        text=True,
        check=False,
    )
    return [line.strip() for line in done.stdout.splitlines() if "::" in line]


def outcomes_of(path: Path, *, substitute: bool, timeout: float) -> dict[str, str]:
    whole = run([path.name], cwd=path.parent, substitute=substitute, timeout=timeout)
    if whole is not None:
        return whole
    found: dict[str, str] = {}
    for test in collect(path):
        one = run([test], cwd=path.parent, substitute=substitute, timeout=timeout)
        found[test] = "HANGS" if one is None else next(iter(one.values()), "ERROR")
    return found


def main() -> None:
    # Here, not at import: pytest imports this module as its plugin in rclpy's own test directory.
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.benchmarks
    from tests.benchmarks import cpus

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tests", type=Path, required=True, help="rclpy's rclpy/test directory")
    parser.add_argument("--only", nargs="*", default=list(FILES), help="these files of it")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds a file (or a test) may take")
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    print(cpus.header(), flush=True)
    totals = {False: [0, 0], True: [0, 0]}
    differences: list[str] = []
    for name in args.only:
        path = args.tests.resolve() / name
        if not path.exists():
            print(f"{name}: not in {args.tests}, skipped")
            continue
        results = {sub: outcomes_of(path, substitute=sub, timeout=args.timeout) for sub in (False, True)}
        for sub, outcomes in results.items():
            totals[sub][0] += sum(outcome == "PASSED" for outcome in outcomes.values())
            totals[sub][1] += len(outcomes)
        for test, outcome in sorted(results[True].items()):
            if outcome != "PASSED" and results[False].get(test) == "PASSED":
                differences.append(f"  {test}: {outcome}")
        print(
            f"{name}: rclpy {sum(o == 'PASSED' for o in results[False].values())}/{len(results[False])}, "
            f"AsyncioExecutor {sum(o == 'PASSED' for o in results[True].values())}/{len(results[True])}",
            flush=True,
        )
    print("\nfailing with AsyncioExecutor only:")
    print("\n".join(differences) or "  none")
    (peer, peer_all), (ours, ours_all) = totals[False], totals[True]
    print(f"\npassed: rclpy's executors {peer} of {peer_all}, AsyncioExecutor {ours} of {ours_all}")


if __name__ == "__main__":
    main()
