"""A signal at every moment of a container's start-up: one line, 130 or 143, within a second.

Run from the repository root::

    .venv/bin/python tests/benchmarks/sweep_early_signals.py [--tries 200] [--busy 2] [--cpus N]

Each try starts ``container run examples/demo.yaml`` through the
environment's ``container`` command, as from a shell (what a terminal and
``ros2 launch`` run: a sh launcher that starts Python with the signals
blocked where env can, and the ROS wheels' bootstrapper re-executes Python
on the way; ``tests/signal_support.py``), sends it
SIGINT or SIGTERM a set time after the start (0 to 490 ms in 10 ms steps,
round after round; the rounds alternate SIGINT and SIGTERM), and waits up
to ``--deadline`` seconds for it to end. The delay is the stimulus, slept
on purpose; everything else is waited on. The process's output tells what
became of the signal:

* ``traceback``: a Python traceback (``KeyboardInterrupt``, "Fatal Python
  error"); those from the first interpreter's own start, before site reads
  the project's ``.pth`` file (CPython's SIGINT handler is installed a few
  milliseconds earlier; only a launcher that blocks the signals before
  Python starts covers it), are counted apart too;
* ``ignored``: Python printed "Exception ignored" (a ``KeyboardInterrupt``
  raised in a weakref callback is swallowed there);
* ``still running``: alive ``--deadline`` seconds after the signal (then
  killed);
* ``killed by the signal``: ended by the signal's default action, before
  Python ran any code of the project (the launcher's shell before its
  ``exec``; without env's blocking, the interpreter's own start too):
  silent, and what shells report as 130/143 too; counted apart;
* ``status``: anything but 130 (SIGINT) / 143 (SIGTERM) otherwise (0 for
  a signal after the container said it was ready: its ordinary stop, which
  a sweep past the start-up, ``--until``, reaches);
* ``lines``: the lines that name the signal (``SIGINT received: ...``):
  exactly one is right, whatever the start-up was doing;
* ``deadline``: the start-up did not stop in order within its deadline
  (``container._session.START_UP_STOP_S``) and the process ended anyway
  (its line names the signal too).

``--busy N`` keeps N busy-looping processes running throughout (on the
CPUs the sweep runs on): the machine under load. The time to exit is
from the signal to the exit status, as the sweep sees it. Exits 1 when
any try went wrong (tracebacks, ignored, still running, wrong status or
line count).
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import statistics
import subprocess
import sys
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # tests.benchmarks, tests.signal_support

from tests.benchmarks import cpus  # noqa: E402
from tests.signal_support import COMMAND, SignalTry, signal_at, signals_as_from_a_terminal  # noqa: E402

DEMO = REPO / "examples" / "demo.yaml"


def busy_loops(count: int) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]


def report(tries: list[SignalTry], examples: int) -> bool:
    by_signal = Counter(t.name for t in tries)
    print(f"tries: {len(tries)} ({', '.join(f'{n} {name}' for name, n in sorted(by_signal.items()))})")
    counts = {
        "tracebacks": sum(t.traceback for t in tries),
        "  of which in the first interpreter's own start": sum(t.in_interpreter_start for t in tries),
        "ignored": sum(t.ignored for t in tries),
        "still running": sum(t.status is None for t in tries),
        "killed by the signal before Python ran our code": sum(t.killed_before_python for t in tries),
        "wrong status": sum(
            t.status is not None and not t.killed_before_python and not t.traceback and t.status != t.expected_status
            for t in tries
        ),
        "after the container said it was ready (exit 0 expected)": sum(t.after_ready for t in tries),
        "ended by the start-up's deadline (not cleanly)": sum(t.deadline for t in tries),
        "not exactly one line naming the signal": sum(
            t.status is not None and not t.killed_before_python and not t.traceback and t.signal_lines != 1
            for t in tries
        ),
    }
    for what, n in counts.items():
        print(f"  {what}: {n}")
    times = sorted(t.to_exit for t in tries if t.to_exit is not None)
    if times:
        p99 = times[min(len(times) - 1, round(0.99 * (len(times) - 1)))]
        print(
            f"  time to exit: median {statistics.median(times) * 1000:.0f} ms, "
            f"99th percentile {p99 * 1000:.0f} ms, max {times[-1] * 1000:.0f} ms"
        )
        slowest = max((t for t in tries if t.to_exit is not None), key=lambda t: t.to_exit or 0.0)
        print(f"  slowest: {slowest.name} at {slowest.delay * 1000:.0f} ms")
    wrong = [t for t in tries if t.problems()]
    for t in wrong[:examples]:
        print(f"\n--- {t.name} at {t.delay * 1000:.0f} ms: {', '.join(t.problems())} (status {t.status})")
        print("\n".join(t.output.splitlines()[-25:]))
    return not wrong


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tries", type=int, default=200)
    parser.add_argument("--step", type=float, default=10.0, help="milliseconds between delays (default 10)")
    parser.add_argument("--until", type=float, default=500.0, help="the delays stay below this, ms (default 500)")
    parser.add_argument("--busy", type=int, default=0, help="busy-looping processes meanwhile (load)")
    parser.add_argument("--deadline", type=float, default=3.0, help="seconds after the signal: still running")
    parser.add_argument("--examples", type=int, default=5, help="outputs of wrong tries shown")
    parser.add_argument("--command", nargs="+", help="default: the environment's `container run examples/demo.yaml`")
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    command = args.command or [str(COMMAND), "run", str(DEMO)]
    signals_as_from_a_terminal()
    # A domain of its own, on this host: other runs never see these containers.
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 200)))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    print(cpus.header())
    print(f"command: {' '.join(command)}; busy loops: {args.busy}")
    steps = max(1, int(args.until // args.step))
    loads = busy_loops(args.busy)
    tries: list[SignalTry] = []
    try:
        for i in range(args.tries):
            lap, step = divmod(i, steps)
            signum = signal.SIGINT if lap % 2 == 0 else signal.SIGTERM
            tries.append(signal_at(command, step * args.step / 1000, signum, deadline=args.deadline))
    finally:
        for load in loads:
            load.kill()
            load.wait()
    sys.exit(0 if report(tries, args.examples) else 1)


if __name__ == "__main__":
    main()
