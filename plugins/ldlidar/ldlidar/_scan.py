"""Revolutions out of packets: angles, REP 117 ranges, fixed bins, timestamps.

Conventions, because every LD-series driver gets one of them wrong:

* The device measures angles clockwise from its front. ROS (REP 103) measures
  them counter-clockwise about z-up. ``direction="ccw"`` (the default) turns a
  device angle θ into the ROS angle -θ, which is right for a sensor mounted
  upright; ``direction="cw"`` publishes θ unchanged, which is right for one
  mounted upside down. Either way the published angles are normalised to
  [-π, π) and, for fixed bins, ``angle_min = -π`` and ``angle_increment > 0``
  (what slam_toolbox expects of a 360° scanner).
* A revolution ends where the angle drops by more than half a turn between
  consecutive points; the partial revolution before the first wrap is
  dropped, so every scan covers one full turn.
* Ranges follow REP 117: a device zero (no echo) or a reading beyond
  ``range_max`` is +inf, a reading below ``range_min`` is -inf, an empty bin
  is +inf, and a bin inside the crop is NaN (no measurement taken there).
* ``stamp`` is the host time of the first measured ray, computed from the
  device's millisecond clock (unwrapped at 30,000 ms) through
  :class:`DeviceClock`, not from when the turn happened to be published.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from ._protocol import (
    ANGLE_UNITS,
    POINTS_PER_PACKET,
    SUBUNITS,
    TIMESTAMP_WRAP_MS,
    TURN_SUBUNITS,
    Packet,
)

__all__ = ["DeviceClock", "Direction", "Scan", "ScanAssembler"]

Direction = Literal["ccw", "cw"]

_HALF_TURN = ANGLE_UNITS // 2
_TWO_PI = 2 * math.pi


class DeviceClock:
    """Map the device's wrapping millisecond clock onto the host clock.

    Each packet gives a bound: it was received (host time) after it was
    measured (device time), so ``host - device`` is the true offset plus a
    non-negative latency. The smallest such value is the tightest estimate;
    read jitter only ever makes samples larger, so it never reaches the
    stamps. The estimate may rise by at most *drift* seconds per second so
    that a device clock running slow against the host is followed too.

    :param drift: the largest clock-rate difference followed upwards (s/s).
    :param max_gap: a host gap longer than this (s) between samples makes
        the device clock's wraps ambiguous; the clock starts afresh.
    """

    def __init__(self, *, drift: float = 2e-4, max_gap: float = 10.0) -> None:
        self._drift = drift
        self._max_gap = max_gap
        self.reset()

    def reset(self) -> None:
        """Forget all history (after a reopen the device clock is unrelated)."""
        self._last_stamp: int | None = None
        self._device_ms = 0
        self._offset: float | None = None
        self._last_host: float | None = None

    @property
    def offset(self) -> float | None:
        """Host time minus device time, in seconds, once anchored."""
        return self._offset

    def unwrap(self, timestamp: int) -> float:
        """Return device seconds since the first timestamp, across wraps.

        Consecutive timestamps must be less than one wrap (30 s) apart.
        """
        if self._last_stamp is not None:
            self._device_ms += (timestamp - self._last_stamp) % TIMESTAMP_WRAP_MS
        self._last_stamp = timestamp
        return self._device_ms / 1000

    def observe(self, device: float, host: float) -> None:
        """Take one sample: something measured at *device* was received at *host*."""
        sample = host - device
        if self._offset is None or self._last_host is None:
            self._offset = sample
        else:
            risen = self._offset + self._drift * max(host - self._last_host, 0.0)
            self._offset = min(risen, sample)
        self._last_host = host

    def gap_too_long(self, host: float) -> bool:
        """Whether *host* is so long after the last sample that wraps are ambiguous."""
        return self._last_host is not None and host - self._last_host > self._max_gap

    def to_host(self, device: float) -> float:
        """Return the host time of device time *device* (device time itself if unanchored)."""
        return device + (self._offset or 0.0)


@dataclass(frozen=True, eq=False, slots=True)
class Scan:
    """One revolution, ready to become a ``sensor_msgs/LaserScan``.

    Angles are radians in the published frame (see the module docstring),
    ranges metres with REP 117 special values, times seconds.

    :param stamp: host time of the first measured ray.
    :param device_time: device time of the first measured ray (unwrapped).
    :param scan_time: time of this whole revolution.
    :param time_increment: ``scan_time / len(ranges)``.
    :param angles: each ray's angle; with fixed bins, the bin centres.
    :param points: measurements the device delivered in this revolution.
    """

    stamp: float
    device_time: float
    scan_time: float
    time_increment: float
    angle_min: float
    angle_max: float
    angle_increment: float
    range_min: float
    range_max: float
    angles: NDArray[np.float64]
    ranges: NDArray[np.float32]
    intensities: NDArray[np.float32]
    points: int


@dataclass(slots=True)
class _Turn:
    positions: list[int] = field(default_factory=list)
    distances: list[int] = field(default_factory=list)
    intensities: list[int] = field(default_factory=list)
    first_time: float | None = None


class ScanAssembler:
    """Collect packets into revolutions.

    :param bins: rays per scan; 0 publishes every point at its own angle
        (the length then varies from turn to turn).
    :param direction: ``"ccw"`` or ``"cw"``, see the module docstring.
    :param range_min: metres; closer readings become -inf.
    :param range_max: metres; farther readings become +inf.
    :param crop: ``(min, max)`` device degrees to exclude, inclusive; when
        min > max the excluded sector wraps through 0.
    :param clock: the device-to-host clock; one is made if not given.
    """

    def __init__(
        self,
        *,
        bins: int = 0,
        direction: Direction = "ccw",
        range_min: float = 0.03,
        range_max: float = 15.0,
        crop: tuple[float, float] | None = None,
        clock: DeviceClock | None = None,
    ) -> None:
        if bins < 0:
            raise ValueError(f"bins must be >= 0, got {bins}")
        if direction not in ("ccw", "cw"):
            raise ValueError(f"direction must be 'ccw' or 'cw', got {direction!r}")
        if not 0 <= range_min < range_max:
            raise ValueError(f"need 0 <= range_min < range_max, got {range_min}, {range_max}")
        if crop is not None and not all(0 <= c <= 360 for c in crop):
            raise ValueError(f"crop angles must be in [0, 360] degrees, got {crop}")
        self.bins = bins
        self.direction: Direction = direction
        self.range_min = range_min
        self.range_max = range_max
        self.crop = crop
        self.clock = clock if clock is not None else DeviceClock()
        self._turn: _Turn | None = None
        self._last_end: int | None = None
        self._due: float | None = None

    def reset(self) -> None:
        """Drop the revolution in progress and the clock (after a reopen)."""
        self._turn = None
        self._last_end = None
        self._due = None
        self.clock.reset()

    @property
    def due(self) -> float | None:
        """Host time by which the packet completing the current revolution can be read.

        Extrapolated from the last packet's end angle and rotation speed and
        mapped through :attr:`clock`, so a reader may sleep until then
        instead of polling; ``None`` until a packet with a speed arrived
        with its ``host_time``.
        """
        if self._due is None or self.clock.offset is None:
            return None
        return self.clock.to_host(self._due)

    def push(self, packet: Packet, *, host_time: float | None = None) -> list[Scan]:
        """Add one packet; return the revolutions it completed (usually none).

        :param host_time: when the bytes holding *packet* were read, on the
            clock the scans are to be stamped with.
        """
        if host_time is not None and self.clock.gap_too_long(host_time):
            self.reset()
        device = self.clock.unwrap(packet.timestamp)
        span = packet.span
        dt = span / (SUBUNITS * 100 * packet.speed) if packet.speed else 0.0
        if host_time is not None:
            self.clock.observe(device + dt * (POINTS_PER_PACKET - 1), host_time)

        start = packet.start_angle % ANGLE_UNITS
        splits: list[int] = []
        if self._last_end is not None and start < self._last_end - _HALF_TURN:
            splits.append(0)
        base = start * SUBUNITS
        if base + span * (POINTS_PER_PACKET - 1) >= TURN_SUBUNITS:
            splits.append(-((base - TURN_SUBUNITS) // span))
        self._last_end = packet.end_angle % ANGLE_UNITS
        if span:
            # Points to come until one reaches 360 degrees; the turn completes
            # with the last point of the packet holding it.
            remaining = (ANGLE_UNITS - self._last_end) % ANGLE_UNITS or ANGLE_UNITS
            points = -(-remaining * SUBUNITS // span)
            packets = -(-points // POINTS_PER_PACKET)
            self._due = device + dt * (POINTS_PER_PACKET - 1 + POINTS_PER_PACKET * packets)
        else:
            self._due = None
        positions = [(base + span * k) % TURN_SUBUNITS for k in range(POINTS_PER_PACKET)]

        scans: list[Scan] = []
        bounds = [*splits, POINTS_PER_PACKET]
        self._extend(packet, positions, 0, bounds[0], device, dt)
        for split, until in pairwise(bounds):
            if self._turn is not None and self._turn.first_time is not None:
                scans.append(self._finish(self._turn, device + dt * split))
            self._turn = _Turn()
            self._extend(packet, positions, split, until, device, dt)
        return scans

    def _extend(
        self, packet: Packet, positions: list[int], a: int, b: int, device: float, dt: float
    ) -> None:
        turn = self._turn
        if turn is None or a >= b:
            return
        if turn.first_time is None:
            turn.first_time = device + dt * a
        turn.positions += positions[a:b]
        turn.distances += packet.distances[a:b]
        turn.intensities += packet.intensities[a:b]

    def _finish(self, turn: _Turn, next_first: float) -> Scan:
        assert turn.first_time is not None
        theta = np.array(turn.positions, dtype=np.float64) * (_TWO_PI / TURN_SUBUNITS)
        ranges = np.array(turn.distances, dtype=np.float32) / np.float32(1000)
        intensities = np.array(turn.intensities, dtype=np.float32)
        ranges[ranges == 0] = np.inf
        ranges[(ranges > 0) & (ranges < self.range_min)] = -np.inf
        ranges[ranges > self.range_max] = np.inf

        keep = ~self._cropped(theta)
        angles = self._publish(theta)
        if self.bins:
            angles_out, ranges_out, intens_out = self._bin(angles[keep], ranges[keep], intensities[keep])
            increment = _TWO_PI / self.bins
            angle_min, angle_max = -math.pi, -math.pi + increment * (self.bins - 1)
        else:
            order = np.argsort(angles[keep], kind="stable")
            angles_out = angles[keep][order]
            ranges_out = ranges[keep][order]
            intens_out = intensities[keep][order]
            if len(angles_out):
                angle_min, angle_max = float(angles_out[0]), float(angles_out[-1])
            else:
                angle_min = angle_max = 0.0
            increment = (angle_max - angle_min) / (len(angles_out) - 1) if len(angles_out) > 1 else 0.0

        scan_time = max(next_first - turn.first_time, 0.0)
        return Scan(
            stamp=self.clock.to_host(turn.first_time),
            device_time=turn.first_time,
            scan_time=scan_time,
            time_increment=scan_time / len(ranges_out) if len(ranges_out) else 0.0,
            angle_min=angle_min,
            angle_max=angle_max,
            angle_increment=increment,
            range_min=self.range_min,
            range_max=self.range_max,
            angles=angles_out,
            ranges=ranges_out,
            intensities=intens_out,
            points=len(turn.positions),
        )

    def _publish(self, theta: NDArray[np.float64]) -> NDArray[np.float64]:
        """Turn clockwise device radians into published radians in [-π, π)."""
        angles = -theta if self.direction == "ccw" else theta.copy()
        angles += math.pi
        angles %= _TWO_PI
        angles -= math.pi
        return angles

    def _cropped(self, theta: NDArray[np.float64]) -> NDArray[np.bool_]:
        if self.crop is None:
            return np.zeros(theta.shape, dtype=bool)
        deg = np.degrees(theta)
        low, high = self.crop
        if low <= high:
            return (deg >= low) & (deg <= high)
        return (deg >= low) | (deg <= high)

    def _bin(
        self,
        angles: NDArray[np.float64],
        ranges: NDArray[np.float32],
        intensities: NDArray[np.float32],
    ) -> tuple[NDArray[np.float64], NDArray[np.float32], NDArray[np.float32]]:
        n = self.bins
        increment = _TWO_PI / n
        centres = -math.pi + increment * np.arange(n, dtype=np.float64)
        out = np.full(n, np.inf, dtype=np.float32)
        out_int = np.zeros(n, dtype=np.float32)
        if self.crop is not None:
            device = -centres if self.direction == "ccw" else centres
            out[self._cropped(np.mod(device, _TWO_PI, dtype=np.float64))] = np.nan
        if len(angles):
            index = np.rint((angles + math.pi) / increment).astype(np.int64) % n
            # Finite readings beat "too close", which beats "nothing there";
            # among finite readings the shorter wins.
            rank = np.where(np.isfinite(ranges), 0, np.where(ranges < 0, 1, 2))
            value = np.where(np.isfinite(ranges), ranges, 0)
            order = np.lexsort((value, rank, index))
            first = np.ones(len(order), dtype=bool)
            first[1:] = index[order][1:] != index[order][:-1]
            winners = order[first]
            out[index[winners]] = ranges[winners]
            out_int[index[winners]] = intensities[winners]
        return centres, out, out_int
