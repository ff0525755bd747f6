from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from ldlidar import (
    PacketGenerator,
    ScanAssembler,
    StreamParser,
    crc8,
    decode_bytes,
    decode_file,
    encode_health,
    encode_packet,
)
from ldlidar import _bulk
from ldlidar_support import corrupted_stream


def streaming(data: bytes) -> tuple[list, StreamParser]:  # type: ignore[type-arg]
    parser = StreamParser()
    packets = parser.feed(data) + parser.flush()
    return packets, parser


def assert_agree(data: bytes) -> None:
    packets, parser = streaming(data)
    decoded = decode_bytes(data)
    assert decoded.packets() == packets
    assert decoded.stats == parser.stats
    assert len(decoded) == parser.stats.packets


@pytest.fixture(params=[False, True], ids=["one-block", "many-blocks-threads"])
def blocks(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """Run each test both in one block and in many small blocks on two threads."""
    if request.param:
        monkeypatch.setattr(_bulk, "_BLOCK", 997)
        monkeypatch.setattr(_bulk, "_THREADS", 2)


def test_real_capture_bulk_equals_streaming(capture: Path, blocks: None) -> None:
    decoded = decode_file(capture)
    assert len(decoded) == 863
    assert decoded.offsets[0] == 30
    assert_agree(capture.read_bytes())


@pytest.mark.parametrize("seed", range(10))
def test_bulk_agrees_on_corrupted_streams(seed: int, blocks: None) -> None:
    data, _ = corrupted_stream(seed)
    assert_agree(data)


@pytest.mark.parametrize("seed", range(4))
def test_bulk_agrees_on_stl27l_streams_with_garbage(seed: int, blocks: None) -> None:
    data, _ = corrupted_stream(100 + seed, model="STL27L", packets=600)
    assert_agree(data)


def test_bulk_agrees_on_pure_noise_with_headers(blocks: None) -> None:
    rng = np.random.default_rng(5)
    noise = bytearray(rng.integers(0, 256, 20000, dtype=np.uint8).tobytes())
    for at in rng.integers(0, len(noise) - 2, 600):
        noise[at : at + 2] = bytes((0x54, int(rng.choice([0x2C, 0xE0, 0x0F]))))
    assert_agree(bytes(noise))


def _overlapping_pair(offset: int) -> bytes:
    """Two valid packets, the second starting *offset* bytes into the first."""
    generator = PacketGenerator("LD06")
    first = generator.packets(1)
    second = bytearray(generator.packets(1))
    # The first packet's end angle and CRC fall on bytes of the second: make
    # the end angle plausible, then fix both CRCs (the first's byte 46 is one
    # of the second's point bytes, covered by the second's CRC).
    end = (first[4] | first[5] << 8) + 800
    second[42 - offset : 44 - offset] = end.to_bytes(2, "little")
    stream = bytearray(first[:offset]) + second
    stream[46] = crc8(stream[:46])
    stream[offset + 46] = crc8(stream[offset : offset + 46])
    assert crc8(stream[:47]) == 0 and crc8(stream[offset : offset + 47]) == 0
    return bytes(stream)


@pytest.mark.parametrize("offset", [8, 20, 40])
def test_frame_inside_an_accepted_frame_is_not_a_frame(offset: int, blocks: None) -> None:
    data = _overlapping_pair(offset) + PacketGenerator("LD06", seed=1).packets(3)
    packets, parser = streaming(data)
    assert packets[0].crc == data[46]  # the first packet won; the one inside it is skipped
    assert_agree(data)


def test_health_frame_inside_a_packet_is_not_counted(blocks: None) -> None:
    health = encode_health(0x42)
    distances = [health[0] | health[1] << 8, health[3], *range(10)]
    packet = encode_packet(
        speed=3600, start_angle=100, end_angle=900, timestamp=5, distances=distances,
        intensities=[health[2]] + [0] * 11,
    )
    assert health in packet
    packets, parser = streaming(packet)
    assert parser.stats.health_frames == 0 and len(packets) == 1
    assert_agree(packet)


def test_empty_and_tiny_inputs(blocks: None) -> None:
    for data in (b"", b"\x54", b"\x54\x2c", b"\x00" * 10):
        assert_agree(data)


def test_generated_stream_decodes_exactly(blocks: None) -> None:
    rows = PacketGenerator("STL27L", seed=3).rows(5000)
    decoded = decode_bytes(rows.tobytes())
    assert len(decoded) == 5000
    assert decoded.stats.skipped_bytes == 0 and decoded.stats.resyncs == 0
    assert np.array_equal(decoded.crc, rows[:, 46])
    dist = rows[:, 6:42].reshape(-1, 12, 3)
    assert np.array_equal(decoded.distances, dist[:, :, 0] | dist[:, :, 1].astype(np.uint16) << 8)
    assert np.array_equal(decoded.intensities, dist[:, :, 2])


def test_point_angles_match_packet_angles(capture: Path, blocks: None) -> None:
    decoded = decode_file(capture)
    angles = decoded.point_angles()
    for i, packet in enumerate(decoded.packets()[:100]):
        assert angles[i] == pytest.approx(packet.angles(), abs=1e-3)


def test_revolutions_match_the_assembler(capture: Path) -> None:
    decoded = decode_file(capture)
    assembler = ScanAssembler()
    scans = [scan for p in decoded.packets() for scan in assembler.push(p)]
    assert decoded.revolutions() == len(scans) == 22
    assert sum(s.points for s in scans) == decoded.wraps()[-1] - decoded.wraps()[0]


def test_revolutions_across_a_wrap_inside_and_between_packets() -> None:
    data = PacketGenerator("LD06").packets(400)  # a bit over 10 turns
    decoded = decode_bytes(data)
    assembler = ScanAssembler()
    scans = [scan for p in decoded.packets() for scan in assembler.push(p)]
    assert decoded.revolutions() == len(scans) == 9


def test_device_times_unwrap(capture: Path) -> None:
    times = decode_file(capture).device_times()
    assert times[-1] == 19454 - 17179
    data = PacketGenerator("LD06", start_ms=29990).packets(50)
    times = decode_bytes(data).device_times()
    assert np.all(np.diff(times) > 0)


def test_unreadable_file_is_a_device_error(tmp_path: Path) -> None:
    from ldlidar import DeviceError

    with pytest.raises(DeviceError) as info:
        decode_file(tmp_path / "missing.bin")
    assert info.value.device.endswith("missing.bin")
