from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

from ldlidar import PacketGenerator, ScanAssembler, StreamParser, encode_packet, encode_png, render_scan
from ldlidar._cli import main
from tests.ldlidar.ldlidar_support import PLUGIN


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ldlidar", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PYTHONPATH": str(PLUGIN)},
    )


def test_decode_prints_the_capture_summary(capture: Path) -> None:
    out = run_cli("decode", str(capture))
    assert out.returncode == 0, out.stderr
    lines = dict(line.split(":", 1) for line in out.stdout.splitlines())
    assert lines["packets"].strip() == "863"
    assert lines["crc errors"].strip() == "0"
    assert lines["revolutions"].strip() == "22"
    assert lines["scan rate"].strip().startswith("10.0")
    assert "packets/s" in lines["packet rate"]


def test_decode_json_is_one_object(capture: Path) -> None:
    out = run_cli("decode", "--json", str(capture))
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert summary["packets"] == 863
    assert summary["crc_errors"] == 0
    assert summary["revolutions"] == 22
    assert summary["resyncs"] == 2 and summary["skipped_bytes"] == 49
    assert summary["packet_rate_hz"] == pytest.approx(379, abs=2)
    assert summary["scan_rate_hz"] == pytest.approx(10, abs=0.1)


def test_decode_counts_faults(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = PacketGenerator("STL27L").packets(2000)
    broken = data[:4720] + b"\x00garbage" + data[4730:]  # packet 100 loses bytes 20..29
    path = tmp_path / "broken.bin"
    path.write_bytes(broken)
    assert main(["decode", "--json", str(path)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["packets"] == 1999
    assert summary["crc_errors"] >= 1 and summary["resyncs"] == 1
    assert summary["revolutions"] == 10


def clock_set_back(data: bytes, *, at: int, ms: int) -> bytes:
    """*data* (back-to-back packets) with the device clock set back *ms* from packet *at* on."""
    from ldlidar import decode_bytes
    from ldlidar._bulk import crc_rows

    decoded = decode_bytes(data)
    rows = np.frombuffer(data, dtype=np.uint8)[decoded.offsets[:, None] + np.arange(47)].copy()
    stamps = rows[:, 44].astype(np.int64) | rows[:, 45].astype(np.int64) << 8
    stamps[at:] = (stamps[at:] - ms) % 30000
    rows[:, 44], rows[:, 45] = stamps & 0xFF, stamps >> 8
    rows[:, 46] = crc_rows(rows)
    out: bytes = rows.tobytes()
    return out


@pytest.mark.parametrize("real", [False, True], ids=["generated", "real"])
def test_decode_rates_survive_a_device_clock_jump(
    real: bool, tmp_path: Path, capsys: pytest.CaptureFixture[str], request: pytest.FixtureRequest
) -> None:
    """Issue 14: 26,755 -> 21,038 ms was read as +24.3 s, and the summary said 4.2 Hz."""
    data = request.getfixturevalue("capture").read_bytes() if real else PacketGenerator("LD06").packets(863)
    path = tmp_path / "jump.bin"
    path.write_bytes(clock_set_back(data, at=400, ms=5717))
    assert main(["decode", "--json", str(path)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["packets"] == 863
    assert summary["scan_rate_hz"] == pytest.approx(10, abs=0.1)
    assert summary["packet_rate_hz"] == pytest.approx(379 if real else 375, abs=2)
    assert summary["device_duration_s"] == pytest.approx(862 / (379 if real else 375), abs=0.02)


@pytest.mark.parametrize("json_flag", [[], ["--json"]])
def test_decode_missing_file_exits_2_with_a_message(tmp_path: Path, json_flag: list[str]) -> None:
    out = run_cli("decode", *json_flag, str(tmp_path / "nope.bin"))
    assert out.returncode == 2
    assert out.stdout == ""
    assert "nope.bin" in out.stderr and "No such file" in out.stderr


def test_decode_unreadable_path_exits_2(tmp_path: Path) -> None:
    out = run_cli("decode", str(tmp_path))  # a directory
    assert out.returncode == 2
    assert "cannot read capture" in out.stderr


def read_png(data: bytes) -> np.ndarray:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos = 8
    idat = b""
    header = None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert zlib.crc32(kind + body) == crc
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    assert header is not None
    width, height, depth, colour = header[:4]
    assert (depth, colour) == (8, 2)
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(height, 1 + 3 * width)
    assert np.all(raw[:, 0] == 0)
    return raw[:, 1:].reshape(height, width, 3)


def test_png_round_trips() -> None:
    image = np.random.default_rng(0).integers(0, 256, (7, 5, 3), dtype=np.uint8)
    assert np.array_equal(read_png(encode_png(image)), image)


def test_render_puts_walls_where_the_room_is() -> None:
    parser = StreamParser()
    assembler = ScanAssembler(bins=720)
    scans = [s for p in parser.feed(PacketGenerator("LD06").packets(100)) for s in assembler.push(p)]
    image = render_scan(scans[0], size=400, extent=5.0)
    blue = np.all(image == (20, 60, 200), axis=2)
    scale = (400 / 2 - 4) / 5.0
    # The default room's front wall is 4 m ahead (up) and its right wall 1.5 m to the right.
    front_row = round(200 - 4.0 * scale)
    right_col = round(200 + 1.5 * scale)
    assert blue[front_row - 2 : front_row + 3, 190:210].any()
    assert blue[190:210, right_col - 2 : right_col + 3].any()
    assert not blue[front_row - 2 : front_row + 3, right_col + 20 :].any()  # nothing outside the room


def test_render_command_writes_a_png(tmp_path: Path, capture: Path) -> None:
    out = tmp_path / "scan.png"
    result = run_cli("render", str(capture), "-o", str(out), "--revolution", "3", "--size", "300")
    assert result.returncode == 0, result.stderr
    image = read_png(out.read_bytes())
    assert image.shape == (300, 300, 3)
    assert np.count_nonzero(np.all(image == (20, 60, 200), axis=2)) > 200


def test_render_from_the_emulator(tmp_path: Path) -> None:
    out = tmp_path / "emu.png"
    assert main(["render", "emu:STL27L", "-o", str(out), "--size", "200"]) == 0
    assert read_png(out.read_bytes()).shape == (200, 200, 3)


def test_render_asks_for_a_revolution_that_is_not_there(tmp_path: Path, capture: Path) -> None:
    result = run_cli("render", str(capture), "-o", str(tmp_path / "x.png"), "--revolution", "99")
    assert result.returncode == 2
    assert "22 complete revolutions" in result.stderr


def test_decode_tells_impossible_packets_from_crc_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # A valid CRC over a packet that spans 200 degrees: no device sends that,
    # and no line noise makes it (it would fail its CRC).
    impossible = encode_packet(
        speed=3600, start_angle=0, end_angle=20000, timestamp=0, distances=[1000] * 12, intensities=[100] * 12
    )
    path = tmp_path / "impossible.bin"
    path.write_bytes(impossible * 2000)

    assert main(["decode", "--json", str(path)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert (summary["packets"], summary["crc_errors"], summary["implausible"]) == (0, 0, 2000)
    # The streaming parser counts the same, chunk by chunk.
    parser = StreamParser()
    data = impossible * 2000
    for offset in range(0, len(data), 1000):
        parser.feed_rows(data[offset : offset + 1000])
    parser.flush()
    assert (parser.stats.packets, parser.stats.crc_errors, parser.stats.implausible) == (0, 0, 2000)
