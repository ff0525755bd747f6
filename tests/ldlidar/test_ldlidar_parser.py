from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ldlidar import PacketGenerator, StreamParser, encode_health, encode_info, encode_packet
from tests.ldlidar.ldlidar_support import corrupted_stream, is_subsequence


def parse(data: bytes, chunks: list[int] | None = None) -> tuple[list[bytes], StreamParser]:
    parser = StreamParser()
    out = []
    if chunks is None:
        out += parser.feed(data)
    else:
        pos = 0
        for size in chunks:
            out += parser.feed(data[pos : pos + size])
            pos += size
        out += parser.feed(data[pos:])
    out += parser.flush()
    return [reencode(p) for p in out], parser


def reencode(p) -> bytes:  # type: ignore[no-untyped-def]
    return encode_packet(
        speed=p.speed, start_angle=p.start_angle, end_angle=p.end_angle, timestamp=p.timestamp,
        distances=p.distances, intensities=p.intensities,
    )


def random_chunks(rng: np.random.Generator, total: int) -> list[int]:
    sizes: list[int] = []
    while sum(sizes) < total:
        sizes.append(int(rng.choice([1, 2, 3, 46, 47, 48, int(rng.integers(1, 300))])))
    return sizes


def test_real_capture_yields_863_packets(capture: Path) -> None:
    packets, parser = parse(capture.read_bytes())
    assert len(packets) == 863
    assert parser.stats.packets == 863
    assert parser.stats.crc_errors == 0
    # The capture starts 30 bytes into a packet and ends inside one.
    assert parser.stats.skipped_bytes == len(capture.read_bytes()) - 863 * 47
    assert parser.stats.resyncs == 2


def test_real_capture_device_clock_wraps_or_climbs(capture: Path) -> None:
    parser = StreamParser()
    stamps = [p.timestamp for p in parser.feed(capture.read_bytes())]
    assert stamps[0] == 17179 and stamps[-1] == 19454


@pytest.mark.parametrize("seed", range(6))
def test_random_chunking_changes_nothing(capture: Path, seed: int) -> None:
    data = capture.read_bytes()
    whole, parser_whole = parse(data)
    chunked, parser_chunked = parse(data, random_chunks(np.random.default_rng(seed), len(data)))
    assert chunked == whole
    assert parser_chunked.stats == parser_whole.stats


@pytest.mark.parametrize("seed", range(12))
def test_corruption_never_loses_a_valid_packet(seed: int) -> None:
    data, good = corrupted_stream(seed)
    packets, parser = parse(data)
    assert is_subsequence(good, packets)
    # Only a CRC-valid frame born of garbage could add packets; the seeds used never do.
    assert len(packets) == len(good)
    assert parser.stats.crc_errors > 0
    chunked, chunked_parser = parse(data, random_chunks(np.random.default_rng(seed), len(data)))
    assert chunked == packets
    assert chunked_parser.stats == parser.stats


def test_truncated_packet_hiding_the_next_header_loses_nothing() -> None:
    """The vendor parser drops the 47-byte window and with it the next packet."""
    generator = PacketGenerator("LD06")
    first, second, third = (generator.packets(1) for _ in range(3))
    data = first + second[:30] + third
    packets, parser = parse(data)
    assert packets == [first, third]
    assert parser.stats.crc_errors == 1
    assert parser.stats.skipped_bytes == 30
    assert parser.stats.resyncs == 1


def test_health_and_info_frames_are_skipped_and_counted() -> None:
    generator = PacketGenerator("LD06")
    a, b = generator.packets(1), generator.packets(1)
    data = a + encode_health(3) + encode_info() + b + encode_health(9)
    packets, parser = parse(data)
    assert packets == [a, b]
    assert parser.stats.health_frames == 2
    assert parser.stats.info_frames == 1
    assert parser.stats.last_health_code == 9
    assert parser.stats.skipped_bytes == 0 and parser.stats.resyncs == 0


def test_health_frame_with_bad_crc_is_noise_not_a_skip_of_four() -> None:
    generator = PacketGenerator("LD06")
    packet = generator.packets(1)
    data = b"\x54\xe0" + packet  # a broken health frame right before a packet
    packets, parser = parse(data)
    assert packets == [packet]
    assert parser.stats.health_frames == 0
    assert parser.stats.skipped_bytes == 2


def test_unknown_frame_types_are_skipped() -> None:
    packet = PacketGenerator("LD06").packets(1)
    packets, parser = parse(b"\x54\xa8\x04\x00\x00\x00\x00\x11" + packet)
    assert packets == [packet]
    assert parser.stats.skipped_bytes == 8


def test_partial_packet_waits_for_the_rest() -> None:
    packet = PacketGenerator("LD06").packets(1)
    parser = StreamParser()
    assert parser.feed(packet[:46]) == []
    assert parser.pending == 46
    assert [reencode(p) for p in parser.feed(packet[46:])] == [packet]
    assert parser.pending == 0


def test_flush_decides_held_bytes_and_still_finds_frames_behind_them() -> None:
    # "54 2C" that can never complete, followed by a complete health frame.
    parser = StreamParser()
    assert parser.feed(b"\x54\x2c\x01\x02" + encode_health(1)) == []
    assert parser.stats.health_frames == 0
    parser.flush()
    assert parser.stats.health_frames == 1
    assert parser.stats.skipped_bytes == 4
    assert parser.pending == 0


def test_reset_counts_dropped_bytes() -> None:
    parser = StreamParser()
    parser.feed(b"\x54\x2c\x00")
    parser.reset()
    assert parser.pending == 0
    assert parser.stats.skipped_bytes == 3 and parser.stats.resyncs == 1


def spliced_health(packets: bytes, *, every: int) -> bytes:
    """``54 E0 C8`` (a truncated health frame whose CRC would be the next ``54``) before every *every*-th packet."""
    out = bytearray()
    for i in range(0, len(packets), 47):
        if (i // 47) % every == 0:
            out += b"\x54\xe0\xc8"
        out += packets[i : i + 47]
    return bytes(out)


@pytest.mark.parametrize("seed", range(4))
def test_a_false_health_frame_never_swallows_a_packet_however_the_bytes_arrive(seed: int) -> None:
    """Issue 14: the decoder found 777 of the real capture's 863 packets with these bytes spliced in."""
    clean = PacketGenerator("LD06", seed=seed).packets(200)
    data = spliced_health(clean, every=3)
    sizes = random_chunks(np.random.default_rng(seed), len(data))
    sizes[0] = 3  # one chunk ends right after 54 E0 C8: the parser must wait, not decide
    packets, parser = parse(data, sizes)
    assert len(packets) == 200 and parser.stats.health_frames == 0
    assert parser.stats.skipped_bytes == 3 * 67
    # A real, complete health frame is still one.
    real, parser = parse(clean[:47] + encode_health(4) + clean[47:94], [47, 3, 1, 47])
    assert len(real) == 2 and parser.stats.health_frames == 1 and parser.stats.last_health_code == 4


@pytest.mark.parametrize("seed", range(8))
def test_rows_and_packets_are_the_same_stream(seed: int) -> None:
    """feed_rows (what the node uses) takes the same packets and counts the same as feed."""
    data, _ = corrupted_stream(seed)
    data = spliced_health(data[:3000], every=5) + data[3000:]
    sizes = random_chunks(np.random.default_rng(seed), len(data))
    packets, by_packet = parse(data, sizes)
    by_rows = StreamParser()
    rows = []
    pos = 0
    for size in [*sizes, len(data)]:
        chunk = by_rows.feed_rows(data[pos : pos + size])
        assert chunk.shape[1:] == (47,)
        rows += [bytes(r) for r in chunk]
        pos += size
    rows += [reencode(p) for p in by_rows.flush()]
    assert rows == packets
    assert by_rows.stats == by_packet.stats
