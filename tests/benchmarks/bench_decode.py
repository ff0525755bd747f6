"""Decode benchmark: the whole ``python -m ldlidar decode --json`` process.

Run: ``python tests/benchmarks/bench_decode.py [--packets 2600000] [--rounds 5]``

1. Generate (once, cached in the temp directory) a capture of about 2.6
   million STL-27L packets from the emulator's room, with a few corrupted
   spots: truncated packets, garbage, health frames.
2. Time ``python -m ldlidar decode --json FILE`` end to end as a subprocess
   (interpreter start, imports, file read, every packet's CRC, fields,
   per-point angles and distances, revolutions, JSON out), several rounds.
3. In the same run, time the peer: a plain pure-Python scanner that only
   finds headers and checks CRCs, also a whole process on the same file.

Printed: packets per second, as a multiple of the STL-27L line rate (1,800
packets/s), and the ratio to the peer. Also the interpreter's bare start-up
and ``import numpy`` times, since at this size they are a visible share.

To compare versions side by side, give ``--plugin DIR`` once per copy of
``plugins/ldlidar`` (e.g. one checked out from git into a temp directory):
the rounds alternate between them, so a busy machine slows all alike, and
each must report the same summary. ``--busy`` keeps one core spinning in
another process while timing, for the figure on a shared machine.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve()
PLUGIN = HERE.parents[2] / "plugins" / "ldlidar"
sys.path.insert(0, str(HERE.parents[2]))  # the repository: tests.benchmarks

from tests.benchmarks import cpus  # noqa: E402

LINE_RATE = 1800  # STL-27L packets per second

PEER = r"""
import sys
table = []
for v in range(256):
    c = v
    for _ in range(8):
        c = ((c << 1) ^ 0x4D) & 0xFF if c & 0x80 else (c << 1) & 0xFF
    table.append(c)
data = open(sys.argv[1], "rb").read()
find = data.find
n = len(data) - 47
pos = good = bad = 0
while True:
    pos = find(b"\x54\x2c", pos)
    if pos < 0 or pos > n:
        break
    crc = 0
    for byte in data[pos:pos + 46]:
        crc = table[crc ^ byte]
    if crc == data[pos + 46]:
        good += 1
        pos += 47
    else:
        bad += 1
        pos += 1
print(good, bad)
"""


def generate(path: Path, packets: int) -> None:
    sys.path.insert(0, str(PLUGIN))
    import numpy as np

    from ldlidar import PacketGenerator, encode_health

    rng = np.random.default_rng(0)
    generator = PacketGenerator("STL27L", seed=0, start_ms=12_345)
    chunk = 200_000
    spots = set(rng.integers(0, packets, 12).tolist())
    with path.open("wb") as out:
        done = 0
        while done < packets:
            count = min(chunk, packets - done)
            data = generator.packets(count)
            here = sorted(s - done for s in spots if done <= s < done + count)
            pos = 0
            for i, spot in enumerate(here):
                at = spot * 47
                out.write(data[pos:at])
                kind = i % 3
                if kind == 0:
                    out.write(data[at : at + 20])  # a truncated packet
                    pos = at + 47
                elif kind == 1:
                    out.write(rng.integers(0, 256, 300, dtype=np.uint8).tobytes())  # garbage
                    pos = at
                else:
                    out.write(encode_health(1))
                    pos = at
            out.write(data[pos:])
            done += count


def timed(cmd: list[str], env: dict[str, str]) -> tuple[float, str]:
    begin = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    elapsed = time.perf_counter() - begin
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({out.returncode}):\n{out.stderr}")
    return elapsed, out.stdout


@contextlib.contextmanager
def busy_core(enabled: bool) -> Iterator[None]:
    """Keep one core busy in another process (a spinning interpreter) meanwhile."""
    if not enabled:
        yield
        return
    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        yield
    finally:
        spinner.kill()
        spinner.wait()


def report(label: str, times: list[float], summary: dict[str, Any]) -> float:
    """Print one variant's figures; return its best time."""
    packets = int(summary["packets"])
    best, median = min(times), statistics.median(times)
    print(f"\n{label}")
    print(
        f"  decode --json: {packets:,} packets, {summary['crc_errors']} CRC errors, "
        f"{summary['resyncs']} resyncs, {summary['revolutions']:,} revolutions, {summary['points']:,} points"
    )
    print(
        f"  whole process: best {best:.3f} s, median {median:.3f} s "
        f"over {len(times)} rounds ({', '.join(f'{t:.3f}' for t in times)})"
    )
    print(
        f"  => {packets / best / 1e6:.2f} M packets/s best ({packets / best / LINE_RATE:,.0f}x STL-27L line rate), "
        f"{packets / median / 1e6:.2f} M packets/s median ({packets / median / LINE_RATE:,.0f}x)"
    )
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--packets", type=int, default=2_600_000)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--python", action="append", default=None, help="interpreter(s) to time; default: this one")
    parser.add_argument(
        "--plugin", action="append", default=None, type=Path,
        help="plugins/ldlidar copies to compare, rounds interleaved; default: this checkout's",
    )
    parser.add_argument("--busy", action="store_true", help="keep one core busy in another process while timing")
    parser.add_argument("--no-peer", action="store_true")
    cpus.add_option(parser)
    args = parser.parse_args()
    cpus.pin(parser, args.cpus)
    print(cpus.header(), flush=True)
    pythons = args.python or [sys.executable]
    plugins = [p.resolve() for p in args.plugin] if args.plugin else [PLUGIN]

    path = Path(tempfile.gettempdir()) / f"ldlidar-bench-{args.packets}.bin"
    if not path.exists():
        print(f"generating {path} ...", flush=True)
        tmp = path.with_suffix(".tmp")
        generate(tmp, args.packets)
        tmp.replace(path)
    size = path.stat().st_size
    print(f"capture: {path} ({size / 1e6:.1f} MB, {args.packets:,} packets generated, a few corrupted spots)")
    if args.busy:
        print("one core kept busy by another process while timing")

    variants = [(python, plugin) for python in pythons for plugin in plugins]
    times: dict[tuple[str, Path], list[float]] = {v: [] for v in variants}
    summaries: dict[tuple[str, Path], dict[str, Any]] = {}
    with busy_core(args.busy):
        for python in pythons:
            env = {**os.environ, "PYTHONPATH": str(plugins[0])}
            start = min(timed([python, "-c", "pass"], env)[0] for _ in range(5))
            numpy = min(timed([python, "-c", "import numpy"], env)[0] for _ in range(5))
            print(f"{python}: bare start {start * 1000:.0f} ms, start + import numpy {numpy * 1000:.0f} ms")
        for _ in range(args.rounds):
            for python, plugin in variants:
                env = {**os.environ, "PYTHONPATH": str(plugin)}
                elapsed, out = timed([python, "-m", "ldlidar", "decode", "--json", str(path)], env)
                times[python, plugin].append(elapsed)
                summaries[python, plugin] = json.loads(out)
        best = min(
            report(f"{python} with {plugin}", times[python, plugin], summaries[python, plugin])
            for python, plugin in variants
        )
        first = next(iter(summaries.values()))
        if any(summary != first for summary in summaries.values()):
            raise SystemExit("the variants disagree on the summary")

        if not args.no_peer:
            elapsed, out = timed([pythons[0], "-c", PEER, str(path)], {**os.environ})
            good, _bad = (int(x) for x in out.split())
            print(f"\npeer (pure-Python CRC scanner, whole process): {good:,} packets in {elapsed:.2f} s")
            print(f"  => {good / elapsed / 1e6:.2f} M packets/s ({good / elapsed / LINE_RATE:,.0f}x line rate)")
            print(f"  the fastest decode is {elapsed / best:.1f}x faster than the peer (best)")


if __name__ == "__main__":
    main()
