"""``python -m ldlidar``: decode captures, draw scans, run an emulator, replay a capture.

Kept light on imports: ``decode`` loads NumPy and the bulk decoder only (no
asyncio, no serial, never rclpy), because it is also the benchmark's unit of
work and a tool people run in loops.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

__all__ = ["main"]

_PROG = "ldlidar"


def _fail(command: str, message: str) -> int:
    print(f"{_PROG} {command}: error: {message}", file=sys.stderr)
    return 2


def _summary(path: str) -> dict[str, Any]:
    import numpy as np

    from ._bulk import decode_file

    decoded = decode_file(path)
    # Figures from spans and extremes, not from (n, 12) angle or per-packet
    # time arrays: on a large capture, fresh memory is a visible cost.
    angles = decoded.angle_range()
    wraps = decoded.wraps() // 12  # packet index of each wrap
    out: dict[str, Any] = {"file": path, "bytes": decoded.size}
    out.update(decoded.stats.as_dict())
    out["revolutions"] = max(len(wraps) - 1, 0)
    out["points"] = int(decoded.distances.size)
    out["valid_points"] = int(np.count_nonzero(decoded.distances))
    out["max_range_m"] = float(decoded.distances.max()) / 1000 if len(decoded) else None
    out["angle_min_deg"] = angles[0] if angles else None
    out["angle_max_deg"] = angles[1] if angles else None
    duration = decoded.device_elapsed() / 1000
    out["device_duration_s"] = duration
    out["packet_rate_hz"] = (len(decoded) - 1) / duration if duration > 0 else None
    turns = decoded.device_elapsed(int(wraps[0]), int(wraps[-1])) if len(wraps) > 1 else 0
    out["scan_rate_hz"] = (len(wraps) - 1) / (turns / 1000) if turns > 0 else None
    out["speed_min_deg_s"] = int(decoded.speed.min()) if len(decoded) else None
    out["speed_max_deg_s"] = int(decoded.speed.max()) if len(decoded) else None
    return out


def _decode(args: argparse.Namespace) -> int:
    from ._errors import DeviceError

    try:
        summary = _summary(args.file)
    except DeviceError as exc:
        return _fail("decode", str(exc))
    if args.json:
        print(json.dumps(summary))
        return 0
    rows = [
        ("file", summary["file"]),
        ("bytes", summary["bytes"]),
        ("packets", summary["packets"]),
        ("crc errors", summary["crc_errors"]),
        ("implausible", summary["implausible"]),
        ("resyncs", summary["resyncs"]),
        ("skipped bytes", summary["skipped_bytes"]),
        ("health frames", summary["health_frames"]),
        ("info frames", summary["info_frames"]),
        ("revolutions", summary["revolutions"]),
        ("points", f"{summary['points']} ({summary['valid_points']} with a return)"),
        ("device time", f"{summary['device_duration_s']:.3f} s"),
        ("packet rate", _rate(summary["packet_rate_hz"], "packets/s")),
        ("scan rate", _rate(summary["scan_rate_hz"], "Hz")),
        ("speed", f"{summary['speed_min_deg_s']}..{summary['speed_max_deg_s']} deg/s"),
    ]
    for name, value in rows:
        print(f"{name + ':':15} {value}")
    return 0


def _rate(value: float | None, unit: str) -> str:
    return "n/a" if value is None else f"{value:.2f} {unit}"


def _scans_from(source: str, *, bins: int, direction: str, revolutions: int) -> list[Any]:
    from ._parser import StreamParser
    from ._scan import ScanAssembler

    if source.startswith("emu:"):
        from ._emulator import PacketGenerator

        generator = PacketGenerator(source[4:] or "LD06")
        per_turn = generator.model.packets_per_revolution
        data = generator.packets(int(per_turn * (revolutions + 2)))
    else:
        from pathlib import Path

        from ._errors import DeviceError

        try:
            data = Path(source).read_bytes()
        except OSError as exc:
            raise DeviceError(f"cannot read capture: {exc.strerror or exc}", device=source) from exc
    parser = StreamParser()
    assembler = ScanAssembler(bins=bins, direction=direction)  # type: ignore[arg-type]
    scans = []
    for packet in parser.feed(data) + parser.flush():
        scans += assembler.push(packet)
    return scans


def _render(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ._errors import DeviceError
    from ._render import encode_png, render_scan

    try:
        scans = _scans_from(args.source, bins=args.bins, direction=args.direction, revolutions=args.revolution + 1)
    except (DeviceError, ValueError) as exc:
        return _fail("render", str(exc))
    if args.revolution >= len(scans):
        return _fail("render", f"{args.source} holds {len(scans)} complete revolutions, no #{args.revolution}")
    image = render_scan(scans[args.revolution], size=args.size, extent=args.extent)
    try:
        Path(args.output).write_bytes(encode_png(image))
    except OSError as exc:
        return _fail("render", f"cannot write {args.output}: {exc.strerror or exc}")
    print(f"{args.output}: revolution {args.revolution}, {scans[args.revolution].points} points")
    return 0


def _emulate(args: argparse.Namespace) -> int:
    import asyncio
    import contextlib

    from ._emulator import Emulator

    async def run() -> None:
        async with Emulator(model=args.model, link_dir=args.link_dir) as emu:
            print(f"{emu.model.name} emulator on {emu.port} (link {emu.link}); Ctrl-C stops", flush=True)
            await asyncio.Event().wait()

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(run())
    return 0


def _replay(args: argparse.Namespace) -> int:
    import asyncio
    import contextlib

    from ._emulator import Replayer
    from ._errors import DeviceError

    if not args.rate > 0:
        return _fail("replay", f"--rate must be positive, not {args.rate:g}")

    async def run() -> None:
        async with Replayer(args.file, rate=args.rate, loop=args.loop, link_dir=args.link_dir) as player:
            print(
                f"replaying {args.file} at {args.rate:g}x its device's pace on {player.port} "
                f"(link {player.link}); Ctrl-C stops",
                flush=True,
            )
            await player.finished.wait()
            print(f"end of {args.file}: {player.packets_sent} packets", flush=True)

    try:
        with contextlib.suppress(KeyboardInterrupt):
            asyncio.run(run())
    except DeviceError as exc:
        return _fail("replay", str(exc))
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=_PROG, description="LDRobot LD06 / LD19 / STL-27L tools")
    sub = parser.add_subparsers(dest="command", required=True)

    decode = sub.add_parser("decode", help="decode a raw capture and report what it holds")
    decode.add_argument("file")
    decode.add_argument("--json", action="store_true", help="print one JSON object")
    decode.set_defaults(run=_decode)

    render = sub.add_parser("render", help="draw one revolution as a PNG")
    render.add_argument("source", help="a capture file, or emu:LD06 / emu:STL27L")
    render.add_argument("-o", "--output", default="scan.png")
    render.add_argument("--revolution", type=int, default=0, help="which complete revolution (0 = first)")
    render.add_argument("--bins", type=int, default=0)
    render.add_argument("--direction", choices=("ccw", "cw"), default="ccw")
    render.add_argument("--size", type=int, default=800)
    render.add_argument("--extent", type=float, default=None, help="metres from centre to edge")
    render.set_defaults(run=_render)

    emulate = sub.add_parser("emulate", help="run an emulated LiDAR on a pseudo-terminal")
    emulate.add_argument("--model", default="LD06")
    emulate.add_argument("--link-dir", default=None, help="directory for the stable symlink")
    emulate.set_defaults(run=_emulate)

    replay = sub.add_parser(
        "replay", help="play a capture on a pseudo-terminal at its device's pace (from its timestamps)"
    )
    replay.add_argument("file")
    replay.add_argument("--rate", type=float, default=1.0, help="2 plays twice as fast, 0.5 at half speed")
    replay.add_argument("--loop", action="store_true", help="start over at the end")
    replay.add_argument("--link-dir", default=None, help="directory for the stable symlink")
    replay.set_defaults(run=_replay)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    result: int = args.run(args)
    return result
