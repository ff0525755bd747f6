from __future__ import annotations

from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from ldlidar import (
    Packet,
    PacketGenerator,
    ScanAssembler,
    StreamParser,
    _bulk,
    crc8,
    decode_bytes,
    decode_file,
    encode_health,
    encode_info,
    encode_packet,
)
from tests.ldlidar.ldlidar_support import corrupted_stream, decode_command_modules


def streaming(data: bytes) -> tuple[list[Packet], StreamParser]:
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
    packets, _parser = streaming(data)
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
    assert decoded.revolutions() == len(scans) == 10


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


# The chain fast path: links of back-to-back packets are checked in place and
# the bytes inside them are not scanned. These tests put every kind of break
# where it could fool that: mid-chain, on block boundaries, and frames that
# overlap the first link of a chain (which forces a full re-scan).


def full_scans(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Record the start of every block that ``decode_bytes`` re-scans in full."""
    calls: list[int] = []
    real = _bulk._find

    def spy(b: np.ndarray, a: int, e: int, *, full: bool = False) -> _bulk._Found:
        if full:
            calls.append(a)
        return real(b, a, e, full=full)

    monkeypatch.setattr(_bulk, "_find", spy)
    return calls


def small_blocks(monkeypatch: pytest.MonkeyPatch, size: int) -> None:
    monkeypatch.setattr(_bulk, "_BLOCK", size)
    monkeypatch.setattr(_bulk, "_THREADS", 2)


def with_crc(packet: bytearray) -> bytes:
    packet[46] = crc8(packet[:46])
    return bytes(packet)


def health_over_next_packet() -> bytes:
    """The first 3 bytes of a valid health frame whose CRC byte is ``54``.

    Followed by a packet, the frame's last byte is the packet's header: a
    parser that accepted the frame would skip that packet.
    """
    code = next(c for c in range(256) if crc8(bytes((0x54, 0xE0, c))) == 0x54)
    return bytes((0x54, 0xE0, code))


@pytest.mark.parametrize("garbage", [1, 2, 20, 46, 47, 48, 94, 300])
def test_chain_break_mid_stream(garbage: int, blocks: None) -> None:
    generator = PacketGenerator("STL27L", seed=7)
    rng = np.random.default_rng(garbage)
    noise = rng.integers(0, 256, garbage, dtype=np.uint8).tobytes()
    data = generator.packets(150) + noise + generator.packets(150)
    assert_agree(data)
    assert len(decode_bytes(data)) >= 300 - 2


@pytest.mark.parametrize("block", [470, 471, 997, 1000])
def test_corruption_exactly_at_block_boundaries(block: int, monkeypatch: pytest.MonkeyPatch) -> None:
    small_blocks(monkeypatch, block)
    clean = PacketGenerator("LD06", seed=2).packets(120)
    for boundary in (block, 3 * block):
        for d in (-47, -46, -2, -1, 0, 1, 2, 45, 46):
            x = boundary + d
            faults = [
                clean[:x] + bytes((clean[x] ^ 0x01,)) + clean[x + 1 :],  # flipped byte
                clean[:x] + clean[x + 13 :],  # lost bytes
                clean[:x] + b"\x54\x2c" + clean[x:],  # header spliced in
                clean[:x] + encode_health(7) + clean[x:],
                clean[:x] + health_over_next_packet() + clean[x - x % 47 :],
            ]
            for data in faults:
                assert_agree(data)


@pytest.mark.parametrize("block", [None, 300, 301, 302, 303, 330])
def test_a_packet_starting_inside_a_health_frame_wins(block: int | None, monkeypatch: pytest.MonkeyPatch) -> None:
    if block:
        small_blocks(monkeypatch, block)
    calls = full_scans(monkeypatch)
    generator = PacketGenerator("LD06", seed=4)
    data = generator.packets(6) + health_over_next_packet() + generator.packets(20)
    packets, parser = streaming(data)
    assert parser.stats.health_frames == 0 and len(packets) == 6 + 20
    assert parser.stats.skipped_bytes == 3
    assert_agree(data)
    assert not calls  # the false frame never unseats the chain's first link


@pytest.mark.shared
def test_real_capture_with_truncated_health_frames_spliced_in_keeps_every_packet(capture: Path) -> None:
    """``54 E0 C8`` before every 10th packet: each would swallow the next header (issue 14)."""
    data = capture.read_bytes()
    offsets = decode_bytes(data).offsets.tolist()
    spliced = bytearray()
    for j, (a, b) in enumerate(pairwise([0, *offsets, len(data)])):
        spliced += data[a:b]
        if j % 10 == 0 and j < len(offsets):
            spliced += bytes((0x54, 0xE0, 0xC8))
    assert crc8(bytes((0x54, 0xE0, 0xC8))) == 0x54  # the frame would be complete and valid
    packets, parser = streaming(bytes(spliced))
    assert len(packets) == 863 and parser.stats.health_frames == 0
    assert len(decode_bytes(bytes(spliced))) == 863
    assert_agree(bytes(spliced))


def test_packet_overlapping_the_first_link_forces_a_full_scan(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = full_scans(monkeypatch)
    generator = PacketGenerator("LD06", seed=5)
    # A truncated packet leaves the outer packet of the pair to the scan; the
    # inner one starts after it and begins a chain.
    data = generator.packets(5) + generator.packets(1)[:20] + _overlapping_pair(40) + generator.packets(5)
    packets, _ = streaming(data)
    assert len(packets) == 5 + 1 + 5
    assert_agree(data)
    assert calls


def test_noisy_block_then_a_chain(monkeypatch: pytest.MonkeyPatch) -> None:
    chains: list[int] = []
    real = _bulk._chain

    def spy(b: np.ndarray, p: int, e: int) -> np.ndarray:
        chains.append(p)
        return real(b, p, e)

    monkeypatch.setattr(_bulk, "_chain", spy)
    rng = np.random.default_rng(9)
    noise = bytearray(rng.integers(0, 256, 3000, dtype=np.uint8).tobytes())
    for at in rng.integers(0, len(noise) - 2, 4 * _bulk._FREE_CHAINS):
        noise[at : at + 2] = b"\x54\x2c"  # more false starts than chains allowed per block
    data = bytes(noise) + PacketGenerator("STL27L", seed=9).packets(100)
    assert_agree(data)
    assert len(chains) == _bulk._FREE_CHAINS  # in its one block; the rest was scanned


def _segment(rng: np.random.Generator, generator: PacketGenerator) -> bytes:
    """One random piece of a faulty stream."""
    kind = int(rng.integers(0, 9))
    if kind <= 2:
        return generator.packets(int(rng.integers(1, 40)))
    if kind == 3:
        return generator.packets(1)[: int(rng.integers(1, 47))]
    if kind == 4:
        garbage = bytearray(rng.integers(0, 256, int(rng.integers(1, 200)), dtype=np.uint8).tobytes())
        for _ in range(int(rng.integers(0, 5))):
            at = int(rng.integers(0, len(garbage)))
            garbage[at : at + 2] = bytes((0x54, int(rng.choice([0x2C, 0xE0, 0x0F]))))
        return bytes(garbage)
    if kind == 5:
        return _overlapping_pair(int(rng.integers(2, 46)))
    if kind == 6:
        return health_over_next_packet()
    if kind == 7:
        bad = bytearray(generator.packets(1))
        bad[int(rng.integers(0, 47))] ^= 1 << int(rng.integers(0, 8))
        return bytes(bad)
    # A CRC-valid packet with impossible angles (rejected by the span rule).
    odd = bytearray(generator.packets(1))
    end = ((odd[4] | odd[5] << 8) + 20000) % 36000
    odd[42:44] = end.to_bytes(2, "little")
    return with_crc(odd)


@pytest.mark.parametrize("seed", range(12))
def test_bulk_agrees_on_randomly_spliced_streams(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(1000 + seed)
    small_blocks(monkeypatch, int(rng.choice([97, 470, 997, 4703])))
    generator = PacketGenerator("LD06", seed=seed)
    data = b"".join(_segment(rng, generator) for _ in range(60))
    assert_agree(data)


def test_angle_range_equals_point_angles(capture: Path) -> None:
    streams = [capture.read_bytes(), PacketGenerator("LD06").packets(400)]
    streams += [corrupted_stream(seed)[0] for seed in range(3)]
    # Packets crossing 0 at every point index, with the widest allowed span.
    streams.append(
        b"".join(
            encode_packet(
                speed=3600, start_angle=36000 - 9000 * k // 11 - 1, end_angle=36000 - 9000 * k // 11 - 1 + 9000,
                timestamp=k, distances=[1] * 12, intensities=[0] * 12,
            )
            for k in range(12)
        )
    )
    for data in streams:
        decoded = decode_bytes(data)
        angles = decoded.point_angles()
        assert decoded.angle_range() == (float(angles.min()), float(angles.max()))
    assert decode_bytes(b"").angle_range() is None


def reference_times(decoded: _bulk.DecodedStream) -> np.ndarray:
    """Device times packet by packet: a step beyond one revolution is replaced by the rotation's time."""
    times = [0]
    for i in range(1, len(decoded)):
        step = (int(decoded.timestamp[i]) - int(decoded.timestamp[i - 1])) % 30000
        speed = int(decoded.speed[i])
        if speed and step > 360_000 / speed:
            turned = (int(decoded.start_angle[i]) - int(decoded.start_angle[i - 1])) % 36000
            step = round(turned * 10 / speed)
        times.append(times[-1] + step)
    return np.array(times[: len(decoded)], dtype=np.int64)


def test_device_times_with_out_of_range_stamps() -> None:
    rows = PacketGenerator("LD06", start_ms=29_000).rows(50)
    rows[10:12, 44:46] = 0xFF  # 65535: CRC-valid, yet beyond the 30 s clock
    rows[:, 46] = _bulk.crc_rows(rows)
    decoded = decode_bytes(rows.tobytes())
    stamps = decoded.timestamp.astype(np.int64)
    assert stamps.max() == 65535
    times = decoded.device_times()
    assert np.array_equal(times, reference_times(decoded))
    assert np.all(np.diff(times) <= 3)  # 2.7 ms a packet: the bad stamps are jumps, not time


@pytest.mark.parametrize("jump_ms", [-5717, 5000, 29_000])
def test_device_clock_jumps_are_not_time(jump_ms: int) -> None:
    """A jump of the device clock (seen: 26,755 -> 21,038 ms) leaves times and rates right."""
    rows = PacketGenerator("LD06", start_ms=26_000).rows(800)
    stamps = (rows[:, 44].astype(np.int64) | rows[:, 45].astype(np.int64) << 8)
    stamps[300:] = (stamps[300:] + jump_ms) % 30000
    rows[:, 44], rows[:, 45] = stamps & 0xFF, stamps >> 8
    rows[:, 46] = _bulk.crc_rows(rows)
    decoded = decode_bytes(rows.tobytes())
    steps = decoded.device_steps()
    assert steps.max() <= 3 and steps.min() >= 2
    assert decoded.device_elapsed() == pytest.approx(799 / 375 * 1000, abs=2)


def test_crc_rows_matches_crc8() -> None:
    rows = np.random.default_rng(3).integers(0, 256, (200, 48), dtype=np.uint8)
    expected = [crc8(row[:46].tobytes()) for row in rows]
    assert _bulk.crc_rows(rows).tolist() == expected
    assert _bulk.crc_rows(rows[:, :47]).tolist() == expected


def test_decode_file_maps_or_reads_the_same_bytes(tmp_path: Path) -> None:
    data, _ = corrupted_stream(3)
    path = tmp_path / "capture.bin"
    path.write_bytes(data)
    from_file = decode_file(path)
    assert from_file.packets() == decode_bytes(data).packets()
    assert from_file.stats == decode_bytes(data).stats
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    assert len(decode_file(empty)) == 0 and decode_file(empty).size == 0


def test_blockwise_raises_a_worker_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_bulk, "_THREADS", 2)

    def fail_on_third(a: int, e: int) -> int:
        if a == 20:
            raise ValueError("third block")
        return a

    assert _bulk._blockwise(lambda a, e: a, 100, 10) == list(range(0, 100, 10))
    with pytest.raises(ValueError, match="third block"):
        _bulk._blockwise(fail_on_third, 100, 10)


@pytest.mark.parametrize("false_starts", [0, 2 * _bulk._FREE_CHAINS])
@pytest.mark.parametrize("block", [470, 997, 2000])
def test_frames_in_the_last_bytes_of_a_block(
    block: int, false_starts: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    small_blocks(monkeypatch, block)
    rng = np.random.default_rng(block)
    noise = rng.integers(0, 256, 4 * block, dtype=np.uint8)
    noise[noise == 0x54] = 0  # no header but the frames put in
    for k in range(4):  # chains start and fail all over each block
        for at in range(k * block, k * block + min(false_starts * 48, block - 50), 48):
            noise[at : at + 2] = (0x54, 0x2C)
    for back in (1, 2, 3, 4, 22, 23):
        data = bytearray(noise.tobytes())
        data[block - back : block - back + 4] = encode_health(back)
        data[3 * block - back : 3 * block - back + 23] = encode_info(bytes(range(back, back + 20)))
        data += PacketGenerator("LD06").packets(3)
        _packets, parser = streaming(bytes(data))
        assert parser.stats.health_frames == 1 and parser.stats.info_frames == 1
        assert_agree(bytes(data))


@pytest.mark.parametrize("start", [0, 100, 27000, 35999])
def test_span_limit_is_the_parsers(start: int, blocks: None) -> None:
    def packet(span: int) -> bytes:
        return encode_packet(
            speed=3600, start_angle=start, end_angle=start + span, timestamp=0,
            distances=[1] * 12, intensities=[0] * 12,
        )

    data = b"".join(packet(span) for span in (0, 1, 8999, 9000, 9001, 9000, 20000, 35999)) * 3
    packets, _ = streaming(data)
    assert len(packets) == 3 * 5
    assert_agree(data)


@pytest.mark.parametrize("offset", [2, 8, 20, 40, 45])
def test_overlapping_packets_either_side_of_a_block_boundary(offset: int, monkeypatch: pytest.MonkeyPatch) -> None:
    small_blocks(monkeypatch, 470)
    generator = PacketGenerator("LD06", seed=6)
    head = generator.packets(9)  # 423 bytes: the pair starts just before the boundary
    tail = generator.packets(12)
    for pad in range(0, 47):
        data = head + b"\x00" * pad + _overlapping_pair(offset) + tail
        assert_agree(data)


def reference_wraps(decoded: _bulk.DecodedStream) -> np.ndarray:
    """Whole-array version of :meth:`DecodedStream.wraps`, to check the chunked one."""
    # Angles measured from the back of the sensor, where revolutions begin.
    start = (decoded.start_angle.astype(np.int32) - 18000) % 36000
    end = (decoded.end_angle.astype(np.int32) - 18000) % 36000
    span = end - start
    inside = np.flatnonzero(span < 0)
    k = -((start[inside].astype(np.int64) * 11 - 396000) // (span[inside].astype(np.int64) + 36000))
    between = np.flatnonzero(start[1:] < end[:-1] - 18000) + 1
    return np.sort(np.concatenate((inside * 12 + k, between * 12)))


@pytest.mark.parametrize("chunk", [1, 7, 1 << 16])
def test_summaries_do_not_depend_on_chunks(chunk: int, capture: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_bulk, "_CHUNK", chunk)
    rows = PacketGenerator("LD06", start_ms=29_500).rows(300)
    rows[100:103, 44:46] = 0xFF  # stamps off the 30 s clock take the general modulo
    rows[:, 46] = _bulk.crc_rows(rows)
    for data in (capture.read_bytes(), rows.tobytes(), corrupted_stream(1)[0], b""):
        decoded = decode_bytes(data)
        assert np.array_equal(decoded.wraps(), reference_wraps(decoded))
        times = reference_times(decoded)
        assert np.array_equal(decoded.device_times(), times)
        assert np.array_equal(decoded.device_steps(), np.diff(times))
        assert decoded.device_elapsed() == (times[-1] if len(times) else 0)
        for i, j in ((0, 0), (3, 50), (7, 8), (0, len(decoded) - 1)):
            if 0 <= j < len(decoded):
                assert decoded.device_elapsed(i, j) == times[j] - times[i]
        angles = decoded.point_angles()
        expected = (float(angles.min()), float(angles.max())) if len(decoded) else None
        assert decoded.angle_range() == expected


@pytest.mark.parametrize("every", [1, 3, 50])
def test_frames_between_every_few_packets(every: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Many short chains: past the block's chain budget the rest is scanned, with the same result."""
    monkeypatch.setattr(_bulk, "_LINKS_PER_CHAIN", 64)
    generator = PacketGenerator("STL27L", seed=every)
    data = b"".join(generator.packets(every) + encode_health(k % 256) for k in range(200))
    packets, parser = streaming(data)
    assert len(packets) == 200 * every and parser.stats.health_frames == 200
    assert_agree(data)


def test_decode_command_loads_only_what_it_needs(tmp_path: Path) -> None:
    """Start-up is a visible share of ``python -m ldlidar decode``: keep it lean."""
    capture = tmp_path / "capture.bin"
    capture.write_bytes(corrupted_stream(0)[0])
    loaded = decode_command_modules(capture)
    unwanted = {
        "concurrent.futures", "numpy.ma", "numpy.typing", "ldlidar._render", "ldlidar._scan",
        "ldlidar._emulator", "ldlidar._lidar", "asyncio",
    }
    assert not loaded & unwanted
