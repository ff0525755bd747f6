from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from ldlidar import DeviceClock, Packet, Scan, ScanAssembler, decode_packet, encode_packet

POINTS = 456  # per turn: 38 packets, as an LD06 at 10 Hz


def packets_for(
    dist: Callable[[float], int],
    *,
    turns: float = 3,
    offset: float = 5.0,
    start_ms: float = 0.0,
    ms_per_turn: float = 100.0,
    points: int = POINTS,
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
                    intensities=[100] * 12,
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


# ---- revolutions ---------------------------------------------------------------


def test_partial_first_turn_is_dropped_and_each_scan_is_one_turn() -> None:
    scans = run(ScanAssembler(), packets_for(lambda a: 1000, turns=4.5))
    assert len(scans) == 3
    for scan in scans:
        assert scan.points in (POINTS - 1, POINTS, POINTS + 1)
        assert np.all((scan.angles >= -math.pi) & (scan.angles < math.pi))


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


def test_dynamic_scan_is_sorted_by_angle_with_positive_increment() -> None:
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
        assert scan.angle_min == -math.pi
        assert scan.angle_increment == pytest.approx(2 * math.pi / 455)
        assert scan.angle_max == pytest.approx(math.pi - scan.angle_increment)
    assert all(np.array_equal(s.angles, scans[0].angles) for s in scans)


def test_zero_and_360_are_never_both_present() -> None:
    scan = run(ScanAssembler(bins=360), packets_for(lambda a: 1000))[0]
    wrapped = np.round(np.degrees(scan.angles) % 360, 6)
    assert len(set(wrapped)) == len(wrapped)
    assert scan.angle_max - scan.angle_min == pytest.approx(2 * math.pi - scan.angle_increment)


def test_readings_just_either_side_of_the_front_share_the_front_bin() -> None:
    dist = lambda a: 700 if a > 359.5 or a < 0.5 else 2000  # noqa: E731
    scan = run(ScanAssembler(bins=360), packets_for(dist, offset=0.1))[0]
    assert scan.ranges[ray_near(scan, 0.0)] == pytest.approx(0.7)
    assert np.count_nonzero(scan.ranges < 1) == 1


def test_shorter_range_wins_a_shared_bin() -> None:
    # 8 bins of 45 degrees: every bin gets about 57 points.
    dist = lambda a: 600 if 88 < a < 89 else (800 if 89 < a < 91 else 2000)  # noqa: E731
    scan = run(ScanAssembler(bins=8), packets_for(dist))[0]
    assert scan.ranges[ray_near(scan, -math.pi / 2)] == pytest.approx(0.6)
    assert np.count_nonzero(scan.ranges == np.float32(2.0)) == 7


def test_finite_reading_beats_no_return_in_a_bin() -> None:
    dist = lambda a: 900 if 179 < a < 180 else 0  # noqa: E731
    scan = run(ScanAssembler(bins=8), packets_for(dist))[0]
    assert scan.ranges[ray_near(scan, math.pi)] == pytest.approx(0.9)
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


def test_crop_excludes_the_sector_in_device_degrees() -> None:
    scan = run(ScanAssembler(crop=(90, 270)), packets_for(lambda a: 1000))[0]
    device = np.degrees(-scan.angles) % 360
    assert len(device) > POINTS * 0.45
    assert not np.any((device > 90.01) & (device < 269.99))


def test_crop_through_zero() -> None:
    scan = run(ScanAssembler(crop=(350, 10)), packets_for(lambda a: 1000))[0]
    device = np.degrees(-scan.angles) % 360
    assert not np.any((device > 350.01) | (device < 9.99))
    assert np.any(device > 300) and np.any(device < 60)


def test_cropped_bins_are_nan() -> None:
    scan = run(ScanAssembler(bins=360, crop=(90, 270)), packets_for(lambda a: 1000))[0]
    device = np.degrees(-scan.angles) % 360
    inside = (device > 91) & (device < 269)
    assert np.all(np.isnan(scan.ranges[inside]))
    assert np.all(scan.ranges[(device < 89) | (device > 271)] == np.float32(1.0))


# ---- time -----------------------------------------------------------------------------


def test_scan_time_and_time_increment() -> None:
    scans = run(ScanAssembler(bins=500), packets_for(lambda a: 1000, turns=4, ms_per_turn=100))
    for scan in scans:
        assert scan.scan_time == pytest.approx(0.1, abs=0.002)
        assert scan.time_increment == pytest.approx(scan.scan_time / 500)
    starts = [s.device_time for s in scans]
    assert np.diff(starts) == pytest.approx([0.1] * (len(scans) - 1), abs=0.002)


def test_device_clock_wrap_at_30000_ms() -> None:
    scans = run(ScanAssembler(), packets_for(lambda a: 1000, turns=6, start_ms=29800))
    assert len(scans) == 5
    assert np.all(np.diff([s.device_time for s in scans]) > 0.09)
    assert all(s.scan_time == pytest.approx(0.1, abs=0.002) for s in scans)


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


def test_stamp_is_the_first_ray_not_the_publish_time() -> None:
    packets = packets_for(lambda a: 1000, turns=3, offset=5)
    hosts = [10 + (12 * i + 11) * 0.1 / POINTS for i in range(len(packets))]
    scans = run(ScanAssembler(), packets, hosts)
    # Turn 2 starts at the wrap, 355 degrees after the 5-degree start.
    assert scans[0].stamp == pytest.approx(10 + 0.1 * 355 / 360, abs=0.001)


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
def test_bad_parameters_are_rejected(kwargs: dict) -> None:  # type: ignore[type-arg]
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
