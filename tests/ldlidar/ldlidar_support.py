"""Paths and stream builders shared by the ldlidar tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
PLUGIN = REPO / "plugins" / "ldlidar"
CAPTURE = REPO.parent / "shared" / "data" / "ld06" / "ld06-clean-863.bin"

try:
    import ldlidar  # noqa: F401
except ImportError:
    sys.path.insert(0, str(PLUGIN))

from ldlidar import PacketGenerator, encode_health, encode_info  # noqa: E402


def corrupted_stream(seed: int, *, packets: int = 400, model: str = "LD06") -> tuple[bytes, list[bytes]]:
    """Return a stream full of faults and the valid packets that were put in it.

    Faults: truncated packets (often followed at once by a good one), headers
    spliced into packets, random garbage (with headers sprinkled in), health
    and info frames, flipped bytes.
    """
    rng = np.random.default_rng(seed)
    generator = PacketGenerator(model, seed=seed, start_ms=29000)
    good: list[bytes] = []
    out = bytearray(rng.integers(0, 256, int(rng.integers(0, 60)), dtype=np.uint8).tobytes())
    for _ in range(packets):
        packet = generator.packets(1)
        fault = rng.random()
        if fault < 0.08:
            out += packet[: int(rng.integers(2, 46))]  # truncated: never delivered
            continue
        if fault < 0.14:
            bad = bytearray(packet)
            bad[int(rng.integers(2, 47))] ^= 1 << int(rng.integers(0, 8))
            out += bad  # flipped bit: CRC fails
            continue
        if fault < 0.20:
            garbage = bytearray(rng.integers(0, 256, int(rng.integers(1, 120)), dtype=np.uint8).tobytes())
            for _ in range(int(rng.integers(0, 4))):
                at = int(rng.integers(0, len(garbage)))
                garbage[at : at + 2] = bytes((0x54, int(rng.choice([0x2C, 0xE0, 0x0F]))))
            out += garbage
        elif fault < 0.24:
            out += encode_health(int(rng.integers(0, 256)))
        elif fault < 0.26:
            out += encode_info(rng.integers(0, 256, 20, dtype=np.uint8).tobytes())
        elif fault < 0.30:
            out += packet[: int(rng.integers(2, 40))] + b"\x54\x2c"  # header spliced in
        out += packet
        good.append(packet)
    out += generator.packets(1)[:20]  # ends mid-packet
    return bytes(out), good


def is_subsequence(needles: list[bytes], haystack: list[bytes]) -> bool:
    it = iter(haystack)
    return all(any(n == h for h in it) for n in needles)


def decode_command_modules(capture: Path) -> set[str]:
    """The modules ``python -m ldlidar decode --json capture`` has loaded when it ends."""
    script = (
        "import sys, runpy, io, contextlib\n"
        f"sys.argv = ['ldlidar', 'decode', '--json', {str(capture)!r}]\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    try:\n"
        "        runpy.run_module('ldlidar', run_name='__main__')\n"
        "    except SystemExit as exc:\n"
        "        assert exc.code == 0, exc.code\n"
        "print(' '.join(sorted(sys.modules)))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
        env={**os.environ, "PYTHONPATH": str(PLUGIN)},
    )
    assert out.returncode == 0, out.stderr
    return set(out.stdout.split())
