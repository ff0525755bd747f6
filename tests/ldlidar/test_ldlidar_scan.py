"""Revolutions into scans: every ray where and when the message says, REP 117, crop, clock.

The reference in the ray tests is computed here, independently: each point's
direction from its packet's start and end angles and its time from its
packet's device timestamp; the scan only says ``angle_min + i *
angle_increment`` and ``stamp + i * time_increment``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ldlidar import DeviceClock, Packet, Scan, ScanAssembler, StreamParser, decode_packet, encode_packet

POINTS = 456  # per turn: 38 packets, as an LD06 at 10 Hz


def packets_for(
    dist: Callable[[float], int],
    *,
    turns: float = 3,
    offset: float = 5.0,
    start_ms: float = 0.0,
    ms_per_turn: float = 100.0,
    points: int = POINTS,
    intensity: Callable[[float], int] = lambda a: 100,
) -> list[Packet]:
    """Packets of a device turning at a constant rate, *dist* mm at each clockwise angle."""
    step = 360 / points
    out = []
    for i in range(int(turns * points / 12)):
        first = offset + 12 * i * step
        angles = [(first + k * step) % 360 for k in range(12)]
        out.append(
            decode_packet(
                encode_packet(
                    speed=round(360 * 1000 / ms_per_turn),
                    start_angle=round(angles[0] * 100),
                    end_angle=round(angles[-1] * 100),
                    timestamp=round(start_ms + 12 * i * ms_per_turn / points),
                    distances=[dist(a) for a in angles],
                    intensities=[intensity(a) for a in angles],
                )
            )
        )
    return out


def run(assembler: ScanAssembler, packets: list[Packet], hosts: list[float] | None = None) -> list[Scan]:
    scans: list[Scan] = []
    for i, packet in enumerate(packets):
        scans += assembler.push(packet, host_time=None if hosts is None else hosts[i])
    return scans


def ray_near(scan: Scan, angle: float) -> int:
    return int(np.argmin(np.abs((scan.angles - angle + math.pi) % (2 * math.pi) - math.pi)))


def blip(at: float, mm: int, *, width: float = 1.0, other: int = 2000) -> Callable[[float], int]:
    return lambda a: mm if abs((a - at + 180) % 360 - 180) < width else other


def points_of(packets: list[Packet]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every point's device time (s, the device's own unwrapped clock), clockwise angle (rad) and distance (mm)."""
    stamps = np.array([p.timestamp for p in packets])
    ms = np.concatenate(([0], np.cumsum(np.diff(stamps) % 30000)))
    times, angles, dist = [], [], []
    for t, p in zip(ms / 1000, packets, strict=True):
        dt = p.span / 11 / 100 / p.speed
        times += [t + k * dt for k in range(12)]
        angles += [math.radians(a) for a in p.angles()]
        dist += list(p.distances)
    return np.array(times), np.array(angles), np.array(dist)


def check_every_ray(
    scans: list[Scan], packets: list[Packet], direction: str, *, time_tolerance: float
) -> list[float]:
    """Each ray holding a reading came from a point within half an increment of its direction
    and *time_tolerance* of its time; return the time errors (s)."""
    times, angles, dist = points_of(packets)
    published = -angles if direction == "ccw" else angles
    errors: list[float] = []
    for scan in scans:
        n = len(scan.ranges)
        assert scan.angle_increment > 0
        assert scan.angle_max == pytest.approx(scan.angle_min + (n - 1) * scan.angle_increment)
        if direction == "ccw":
            assert scan.time_increment < 0  # ray 0 is the last measured
        else:
            assert scan.time_increment > 0
        assert abs(scan.time_increment) * n == pytest.approx(scan.scan_time, rel=1e-6)
        ends = sorted((scan.device_time, scan.device_time + (n - 1) * scan.time_increment))
        window = (times >= ends[0] - 0.005) & (times <= ends[1] + 0.005)
        for i in np.flatnonzero(np.isfinite(scan.ranges) & (scan.ranges > 0)):
            direction_i = scan.angle_min + i * scan.angle_increment
            time_i = scan.device_time + i * scan.time_increment
            off = np.abs((published - direction_i + math.pi) % (2 * math.pi) - math.pi)
            mine = window & (off <= scan.angle_increment / 2 + 1e-9)
            mine &= np.isclose(dist / 1000, scan.ranges[i], rtol=0, atol=5e-7)
            assert mine.any(), f"ray {i} of {n}: no point within half an increment reads {scan.ranges[i]}"
            error = float(np.min(np.abs(times[mine] - time_i)))
            assert error <= time_tolerance, f"ray {i} of {n}: {error * 1000:.3f} ms from its point"
            errors.append(error)
    return errors


# ---- where and when every ray is -------------------------------------------------------------


MS_PER_TURN, PER_TURN = 112.5, 450  # an LD06 at 8.9 Hz: 3 ms a packet, every stamp exact
POINT_PERIOD = MS_PER_TURN / 1000 / PER_TURN


@pytest.mark.parametrize("direction", ["ccw", "cw"])
@pytest.mark.parametrize(("bins", "crop"), [(455, None), (0, None), (455, (90, 200)), (0, (300, 30))])
def test_every_ray_is_where_and_when_the_message_says(
    direction: str, bins: int, crop: tuple[float, float] | None
) -> None:
    """angle_min + i*angle_increment within half an increment, stamp + i*time_increment within half a point."""
    dist = lambda a: 1000 + int(a * 10)  # noqa: E731  every point's range tells which it is
    packets = packets_for(dist, turns=4, offset=37.0, ms_per_turn=MS_PER_TURN, points=PER_TURN)
    scans = run(ScanAssembler(bins=bins, direction=direction, crop=crop), packets)  # type: ignore[arg-type]
    assert len(scans) == 3
    errors = check_every_ray(scans, packets, direction, time_tolerance=POINT_PERIOD / 2)
    assert len(errors) > 3 * 250
    for scan in scans:
        if crop is not None:
            device = np.degrees(-scan.angles if direction == "ccw" else scan.angles) % 360
            low, high = crop
            inside = (device >= low) & (device <= high) if low <= high else (device >= low) | (device <= high)
            assert np.all(np.isnan(scan.ranges[inside])) and not np.any(np.isnan(scan.ranges[~inside]))
        if bins:
            assert len(scan.ranges) == bins
        else:
            assert len(scan.ranges) == 450  # the native resolution


# Every ray of the whole real capture.
@pytest.mark.slow
@pytest.mark.shared
@pytest.mark.parametrize("direction", ["ccw", "cw"])
@pytest.mark.parametrize("bins", [455, 0])
def test_every_ray_of_the_real_capture_against_the_devices_timestamps(
    capture: Path, direction: str, bins: int
) -> None:
    """Issue 14: stamp + i*time_increment was 50 ms off at the median, 164 ms at worst.

    The device's stamps have a resolution of 1 ms, so that bounds the check; the
    time line through a revolution's stamps lands within 0.3 ms of them at the median.
    """
    parser = StreamParser()
    packets = parser.feed(capture.read_bytes()) + parser.flush()
    scans = run(ScanAssembler(bins=bins, direction=direction), packets)  # type: ignore[arg-type]
    assert len(scans) == 22
    errors = check_every_ray(scans, packets, direction, time_tolerance=0.001)
    assert len(errors) > 22 * 400
    assert np.median(errors) < 0.0004
    if not bins:
        assert {len(s.ranges) for s in scans} <= {454, 455, 456}  # 4,500 points/s at 9.95 Hz


def test_array_order_is_time_order_and_the_turn_ends_at_the_back() -> None:
    """Upright: ray 0 is just right of the back (-π), measured last; the front is the middle ray."""
    packets = packets_for(blip(0, 500), turns=3, ms_per_turn=MS_PER_TURN, points=PER_TURN)
    scan = run(ScanAssembler(bins=455), packets)[0]
    assert scan.angle_min == pytest.approx(-math.pi + math.pi / 455)
    assert scan.angles[227] == pytest.approx(0.0, abs=1e-12)  # an odd count has a ray straight ahead
    assert int(np.argmin(scan.ranges)) == 227
    times = scan.device_time + np.arange(455) * scan.time_increment
    assert np.all(np.diff(times) < 0) and scan.scan_time == pytest.approx(0.1125, abs=1e-4)


def test_missing_packets_leave_the_other_rays_in_place() -> None:
    """bins: 0 used to spread the points evenly over the turn, 36-76 degrees off across a gap."""
    dist = lambda a: 1000 + int(a * 10)  # noqa: E731
    packets = packets_for(dist, turns=4, ms_per_turn=MS_PER_TURN, points=PER_TURN)
    gappy = packets[:25] + packets[33:]  # 8 packets (77 degrees) lost inside the first whole turn
    scans = run(ScanAssembler(bins=0), gappy)
    assert [len(s.ranges) for s in scans] == [450] * len(scans)
    check_every_ray(scans, gappy, "ccw", time_tolerance=POINT_PERIOD / 2)
    holed = scans[0]
    assert np.count_nonzero(np.isposinf(holed.ranges)) == 8 * 12  # the lost packets' rays: no reading


# ---- revolutions ---------------------------------------------------------------


def test_partial_first_turn_is_dropped_and_each_scan_is_one_turn() -> None:
    scans = run(ScanAssembler(), packets_for(lambda a: 1000, turns=4.5))
    assert len(scans) == 4  # from the back at 180 degrees, 175 degrees after the start
    for scan in scans:
        assert scan.points in (POINTS - 1, POINTS, POINTS + 1)
        assert np.all((scan.angles >= -math.pi) & (scan.angles < math.pi))


def test_rehearsing_a_revolution_in_progress_changes_nothing() -> None:
    # A reader rehearses the finish while a revolution's last packets are on
    # their way (before the first packet, mid-turn, and right before the end).
    packets = packets_for(lambda a: 800 + round(a), turns=4.5, intensity=lambda a: round(a) % 200)
    hosts = [10.0 + i * 0.0025 for i in range(len(packets))]
    plain = run(ScanAssembler(noise_filter=True), packets, hosts)
    assembler = ScanAssembler(noise_filter=True)
    assembler.rehearse()
    rehearsed: list[Scan] = []
    for i, packet in enumerate(packets):
        if i % 7 == 3 or i % 38 == 37:
            assembler.rehearse()
        rehearsed += assembler.push(packet, host_time=hosts[i])
    assert len(plain) == len(rehearsed) == 4
    for a, b in zip(plain, rehearsed, strict=True):
        assert (a.stamp, a.scan_time, a.points) == (b.stamp, b.scan_time, b.points)
        np.testing.assert_array_equal(a.ranges, b.ranges)
        np.testing.assert_array_equal(a.intensities, b.intensities)


# ---- direction -------------------------------------------------------------------


@pytest.mark.parametrize(("direction", "expected"), [("ccw", -math.pi / 2), ("cw", math.pi / 2)])
def test_direction_maps_device_clockwise_angles(direction: str, expected: float) -> None:
    """An object 90 degrees clockwise of the front is on the robot's right: -π/2 in REP 103."""
    scans = run(ScanAssembler(direction=direction), packets_for(blip(90, 500)))  # type: ignore[arg-type]
    scan = scans[0]
    nearest = int(np.argmin(scan.ranges))
    assert scan.ranges[nearest] == pytest.approx(0.5)
    assert scan.angles[nearest] == pytest.approx(expected, abs=math.radians(1.5))


@pytest.mark.parametrize("direction", ["ccw", "cw"])
def test_front_is_angle_zero_either_way(direction: str) -> None:
    scan = run(ScanAssembler(direction=direction), packets_for(blip(0, 500)))[0]  # type: ignore[arg-type]
    assert abs(scan.angles[int(np.argmin(scan.ranges))]) < math.radians(1.5)


def test_native_scan_has_increasing_angles_with_positive_increment() -> None:
    scan = run(ScanAssembler(), packets_for(lambda a: 1000))[0]
    assert np.all(np.diff(scan.angles) > 0)
    assert scan.angle_increment > 0
    assert scan.angle_min == scan.angles[0] and scan.angle_max == scan.angles[-1]


# ---- bins --------------------------------------------------------------------------


def test_fixed_bins_give_the_same_layout_every_turn() -> None:
    scans = run(ScanAssembler(bins=455), packets_for(lambda a: 1000, turns=6, points=450))
    assert len(scans) == 5
    for scan in scans:
        assert len(scan.ranges) == len(scan.angles) == 455
        assert scan.angle_min == pytest.approx(-math.pi + math.pi / 455)
        assert scan.angle_increment == pytest.approx(2 * math.pi / 455)
        assert scan.angle_max == pytest.approx(math.pi - math.pi / 455)
    assert all(np.array_equal(s.angles, scans[0].angles) for s in scans)


def test_zero_and_360_are_never_both_present() -> None:
    scan = run(ScanAssembler(bins=360), packets_for(lambda a: 1000))[0]
    wrapped = np.round(np.degrees(scan.angles) % 360, 6)
    assert len(set(wrapped)) == len(wrapped)
    assert scan.angle_max - scan.angle_min == pytest.approx(2 * math.pi - scan.angle_increment)


def test_readings_just_either_side_of_the_front_share_the_front_ray() -> None:
    dist = lambda a: 700 if a > 359.5 or a < 0.5 else 2000  # noqa: E731
    scan = run(ScanAssembler(bins=359), packets_for(dist, offset=0.1))[0]
    assert scan.ranges[ray_near(scan, 0.0)] == pytest.approx(0.7)
    assert np.count_nonzero(scan.ranges < 1) == 1


def test_shorter_range_wins_a_shared_bin() -> None:
    # 8 bins of 45 degrees: every bin gets about 57 points.
    dist = lambda a: 600 if 73 < a < 74 else (800 if 74 < a < 76 else 2000)  # noqa: E731
    scan = run(ScanAssembler(bins=8), packets_for(dist))[0]
    assert scan.ranges[ray_near(scan, -math.radians(67.5))] == pytest.approx(0.6)
    assert np.count_nonzero(scan.ranges == np.float32(2.0)) == 7


def test_finite_reading_beats_no_return_in_a_bin() -> None:
    dist = lambda a: 900 if 159 < a < 160 else 0  # noqa: E731
    scan = run(ScanAssembler(bins=8), packets_for(dist))[0]
    assert scan.ranges[ray_near(scan, -math.radians(157.5))] == pytest.approx(0.9)
    assert np.count_nonzero(np.isposinf(scan.ranges)) == 7


def test_empty_bins_are_positive_infinity() -> None:
    dist = lambda a: 0 if 100 < a < 200 else 1500  # noqa: E731
    scan = run(ScanAssembler(bins=2000), packets_for(dist))[0]
    assert len(scan.ranges) == 2000
    assert np.count_nonzero(np.isposinf(scan.ranges)) > 2000 - POINTS
    assert not np.any(np.isnan(scan.ranges))


# ---- range limits (REP 117) ----------------------------------------------------------


def test_range_limits_are_applied_per_rep_117() -> None:
    def dist(a: float) -> int:
        if a < 90:
            return 20  # too close
        if a < 180:
            return 16000  # beyond range_max
        if a < 270:
            return 0  # no echo
        return 1234

    scan = run(ScanAssembler(range_min=0.03, range_max=15.0), packets_for(dist))[0]
    device = np.degrees(-scan.angles) % 360
    assert np.all(np.isneginf(scan.ranges[(device > 1) & (device < 89)]))
    assert np.all(np.isposinf(scan.ranges[(device > 91) & (device < 269)]))
    assert np.all(scan.ranges[(device > 271) & (device < 359)] == np.float32(1.234))
    assert (scan.range_min, scan.range_max) == (0.03, 15.0)


def test_custom_range_max_cuts_readings() -> None:
    scan = run(ScanAssembler(range_max=1.0), packets_for(lambda a: 1500))[0]
    assert np.all(np.isposinf(scan.ranges))


# ---- crop ---------------------------------------------------------------------------


@pytest.mark.parametrize("bins", [0, 360])
def test_crop_blanks_the_sector_in_device_degrees_with_nan(bins: int) -> None:
    """Cropped rays are NaN (REP 117: no measurement), not dropped: the others keep their angles."""
    scan = run(ScanAssembler(bins=bins, crop=(90, 270)), packets_for(lambda a: 1000))[0]
    device = np.degrees(-scan.angles) % 360
    inside = (device > 90.5) & (device < 269.5)
    assert np.all(np.isnan(scan.ranges[inside]))
    assert np.all(scan.ranges[(device < 89.5) | (device > 270.5)] == np.float32(1.0))
    assert len(scan.ranges) == (bins or POINTS)


def test_crop_through_zero() -> None:
    scan = run(ScanAssembler(crop=(350, 10)), packets_for(lambda a: 1000))[0]
    device = np.degrees(-scan.angles) % 360
    assert np.all(np.isnan(scan.ranges[(device > 350.5) | (device < 9.5)]))
    assert np.all(scan.ranges[(device > 10.5) & (device < 349.5)] == np.float32(1.0))


# ---- noise filter ----------------------------------------------------------------------


def test_noise_filter_drops_isolated_dim_returns_only() -> None:
    """The vendor's near filter: under 5 m, groups of under 3 points need an intensity of 220."""

    def dist(a: float) -> int:
        if 40.0 < a < 41.0:
            return 700  # one or two dim points in mid-air: noise
        if 100.0 < a < 101.0:
            return 900  # as few points, but bright: a thin pole
        if 200.0 < a < 260.0:
            return 6000 + int(a)  # beyond 5 m: never judged
        return 2000 + int(30 * math.sin(math.radians(a)))  # a wall

    def intensity(a: float) -> int:
        return 250 if 100.0 < a < 101.0 else (10 if 200.0 < a < 260.0 else 100)

    packets = packets_for(dist, intensity=intensity)
    plain = run(ScanAssembler(bins=0), packets)[0]
    filtered = run(ScanAssembler(bins=0, noise_filter=True), packets)[0]
    device = np.degrees(-plain.angles) % 360
    noise = (device > 39.5) & (device < 41.5)
    assert np.any(plain.ranges[noise] == np.float32(0.7))
    assert not np.any(filtered.ranges[noise] == np.float32(0.7))
    assert np.isposinf(filtered.ranges[noise & (plain.ranges == np.float32(0.7))]).all()  # "no return"
    pole = (device > 99.5) & (device < 101.5)
    assert np.any(filtered.ranges[pole] == np.float32(0.9))
    rest = ~noise
    assert np.array_equal(filtered.ranges[rest], plain.ranges[rest])


# ---- time -----------------------------------------------------------------------------


def test_scan_time_and_time_increment() -> None:
    scans = run(ScanAssembler(bins=500), packets_for(lambda a: 1000, turns=4, ms_per_turn=100))
    for scan in scans:
        assert scan.scan_time == pytest.approx(0.1, abs=0.002)
        assert scan.time_increment == pytest.approx(-scan.scan_time / 500)
    starts = [s.device_time for s in scans]
    assert np.diff(starts) == pytest.approx([0.1] * (len(scans) - 1), abs=0.002)


def test_device_clock_wrap_at_30000_ms() -> None:
    scans = run(ScanAssembler(), packets_for(lambda a: 1000, turns=6, start_ms=29800))
    assert len(scans) == 5
    assert np.all(np.diff([s.device_time for s in scans]) > 0.09)
    assert all(s.scan_time == pytest.approx(0.1, abs=0.002) for s in scans)


def with_stamps(packets: list[Packet], shift_from: int, shift_ms: int) -> list[Packet]:
    """*packets* whose device clock jumps by *shift_ms* at packet *shift_from*."""
    out = []
    for i, p in enumerate(packets):
        stamp = (p.timestamp + (shift_ms if i >= shift_from else 0)) % 30000
        out.append(
            decode_packet(
                encode_packet(
                    speed=p.speed,
                    start_angle=p.start_angle,
                    end_angle=p.end_angle,
                    timestamp=stamp,
                    distances=p.distances,
                    intensities=p.intensities,
                )
            )
        )
    return out


@pytest.mark.parametrize("jump_ms", [-5717, 4000, 300], ids=["backwards", "forwards", "three-turns"])
@pytest.mark.parametrize("with_host", [False, True])
def test_a_device_clock_jump_is_re_anchored(jump_ms: int, with_host: bool) -> None:
    """Issue 14: 26,755 -> 21,038 ms was read as +24.3 s: scan_time 24.4 s, a stamp 24 s in the past."""
    packets = with_stamps(packets_for(lambda a: 1000, turns=6, start_ms=26_000), 100, jump_ms)
    hosts = [50 + (12 * i + 11) * 0.1 / POINTS + 0.002 for i in range(len(packets))] if with_host else None
    assembler = ScanAssembler(bins=455)
    scans = run(assembler, packets, hosts)
    assert len(scans) == 5
    assert assembler.clock.jumps == 1
    assert [round(s.scan_time, 3) for s in scans] == [0.1] * 5
    stamps = [s.stamp for s in scans]
    assert np.diff(stamps) == pytest.approx([0.1] * 4, abs=0.002)
    if with_host:
        assert stamps[-1] == pytest.approx(hosts[-1] - 0.002, abs=0.2)  # type: ignore[index]


def test_a_stall_the_host_clock_saw_is_time_not_a_jump() -> None:
    """The stream stopped for 0.4 s while the device turned on: the device's own step is believed."""
    packets = packets_for(lambda a: 1000, turns=9)  # a revolution ends at packets 18.5 + 38k
    kept = packets[:100] + packets[252:]  # 152 packets (0.4 s) never arrived
    hosts = [10 + (12 * (i if i < 100 else i + 152) + 11) * 0.1 / POINTS + 0.002 for i in range(len(kept))]
    assembler = ScanAssembler(bins=455)
    scans = run(assembler, kept, hosts)
    assert assembler.clock.jumps == 0
    late = scans[-1]
    assert late.stamp == pytest.approx(late.device_time + 10, abs=0.003)
    # The revolution the gap broke is dropped, not published with another turn's points spliced in.
    assert len(scans) == 3  # 18.5-56.5, 56.5-94.5, and after the gap 284.5-322.5 (not 94.5-284.5)
    assert all(s.points in (POINTS - 1, POINTS, POINTS + 1) for s in scans)
    assert [round(s.scan_time, 3) for s in scans] == [0.1] * 3


def test_unwrap_follows_the_real_capture_pattern() -> None:
    clock = DeviceClock()
    assert [clock.unwrap(t) for t in (29990, 29998, 1, 9)] == pytest.approx([0, 0.008, 0.011, 0.019])


def test_stamps_are_free_of_host_read_jitter() -> None:
    packets = packets_for(lambda a: 1000, turns=30)
    rng = np.random.default_rng(0)
    device_end = [
        (12 * i + 11) * 100 / POINTS / 1000 + 5.0 for i in range(len(packets))
    ]  # when each packet's last point was measured, host seconds
    latency = rng.uniform(0.002, 0.030, len(packets))
    latency[::50] = 0.002  # now and then a read comes straight through
    hosts = [d + lat for d, lat in zip(device_end, latency, strict=True)]
    scans = run(ScanAssembler(), packets, hosts)
    late = scans[5:]
    # Each stamp is the first ray's true time (+ the 2 ms floor), not the jittery read time.
    errors = [s.stamp - (s.device_time + 5.0) for s in late]
    assert max(errors) - min(errors) < 0.0015
    assert np.mean(errors) == pytest.approx(0.002, abs=0.002)


def test_clock_follows_drift_both_ways() -> None:
    for rate in (1 + 1e-4, 1 - 1e-4):  # host runs fast, then slow, against the device
        clock = DeviceClock()
        for i in range(6000):  # one minute of 10 ms samples, 1-3 ms latency
            device = i * 0.01
            clock.observe(device, 100 + device * rate + 0.001 + (i % 3) * 0.001)
        true_offset = 100 + 60 * (rate - 1)
        assert clock.to_host(60.0) - 60.0 == pytest.approx(true_offset + 0.001, abs=0.002)


def test_stamp_is_ray_zero_not_the_publish_time() -> None:
    packets = packets_for(lambda a: 1000, turns=3, offset=5)
    hosts = [10 + (12 * i + 11) * 0.1 / POINTS for i in range(len(packets))]
    scans = run(ScanAssembler(direction="cw"), packets, hosts)
    # Turn 2 starts at the back, 175 degrees after the 5-degree start; clockwise, ray 0 is its first.
    assert scans[0].stamp == pytest.approx(10 + 0.1 * 175 / 360, abs=0.001)
    upright = run(ScanAssembler(), packets, hosts)
    # Upright (ccw), ray 0 is the turn's last: a whole turn later.
    assert upright[0].stamp == pytest.approx(10 + 0.1 * 535 / 360, abs=0.001)


def test_long_host_gap_restarts_the_clock_and_the_turn() -> None:
    assembler = ScanAssembler()
    packets = packets_for(lambda a: 1000, turns=4)  # wraps at packets 37, 75, 113, 151
    assert len(run(assembler, packets[:80], [i * 0.002 for i in range(80)])) == 1
    # Without the reset, the turn from packet 75 would be completed at 113.
    assert run(assembler, packets[80:120], [100 + i * 0.002 for i in range(40)]) == []
    scans = run(assembler, packets[120:], [100.08 + i * 0.002 for i in range(len(packets) - 120)])
    assert len(scans) == 1 and scans[0].stamp > 100


# ---- validation -------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs",
    [{"bins": -1}, {"direction": "left"}, {"range_min": 2.0, "range_max": 1.0}, {"crop": (0, 400)}],
)
def test_bad_parameters_are_rejected(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        ScanAssembler(**kwargs)


def test_due_predicts_when_the_packet_completing_a_turn_arrives() -> None:
    latency = 0.004  # seconds from a packet's last point to its read
    packets = packets_for(lambda a: 1000, turns=4)
    point_time = 0.1 / POINTS
    assert ScanAssembler().due is None  # nothing to predict before the first packet
    assembler = ScanAssembler()
    predictions: list[float] = []
    completed_at: list[float] = []
    for packet in packets:
        read_at = 1000.0 + packet.timestamp / 1000 + 11 * point_time + latency
        if assembler.push(packet, host_time=read_at):
            completed_at.append(read_at)
        due = assembler.due
        assert due is not None
        predictions.append(due)
    # Every prediction made while a turn was in progress names the read that
    # completes it, to the timestamps' 1 ms rounding.
    for done in completed_at[1:]:
        made = [p for p in predictions if done - 0.05 < p < done + 0.05]
        assert len(made) >= 30  # about 38 packets a turn
        for prediction in made:
            assert prediction == pytest.approx(done, abs=0.0015)
    assembler.reset()
    assert assembler.due is None
