"""Revolutions out of packets: rays where and when the message says they are.

A ``sensor_msgs/LaserScan`` describes ray ``i`` by two linear formulas:
its direction is ``angle_min + i * angle_increment`` and its measurement time
``header.stamp + i * time_increment``. Both must hold for every ray, or
anything that projects or de-skews a scan (laser_geometry's high-fidelity
projection, motion compensation) puts points in the wrong place. The choices
that make both hold for this sensor:

* **Angles.** The device measures clockwise from its front; ROS (REP 103)
  counter-clockwise about z-up. ``direction="ccw"`` (the default, a sensor
  mounted upright) publishes a device angle θ as -θ; ``direction="cw"`` (one
  mounted upside down) publishes θ. ``angle_increment`` is always positive
  (``2π / n``): slam_toolbox (Karto) takes ``angle_min``, ``angle_max`` and
  ``angle_increment`` as a laser's geometry and needs them increasing.
* **The revolution boundary is the back of the sensor** (device 180°, published
  ±π), not its front. The n rays split the turn into n equal sectors, ray
  ``i`` covering ``[-π + i·2π/n, -π + (i+1)·2π/n)`` with its direction at the
  centre: ``angle_min = -π + π/n`` (0 and 2π are never both present, and an
  odd n, such as the default 455, has a ray pointing straight ahead). Each
  measured point goes to the ray whose sector holds it, so a ray is never more
  than half an increment from its point; a turn that ended at the front would
  put the two halves of the array at opposite ends of the revolution in time.
* **Time.** Within one revolution, array order is time order: with ``"cw"``
  ray 0 is measured first and ``time_increment > 0``; with ``"ccw"`` the
  device sweeps from +π down to -π, so ray 0 is measured *last* and
  ``time_increment < 0``. ``header.stamp`` is always ray 0's time (the
  LaserScan definition: "the acquisition time of the first ray in the scan"),
  and ``scan_time`` the revolution's period. laser_geometry interpolates the
  sensor pose from ``stamp`` to ``stamp + (n - 1) * time_increment``, either
  sign. Ray times come from a least-squares line through the device's own
  timestamps of the revolution's points (each packet's stamp, plus the
  point's share of the packet's sweep), so the 1 ms resolution of a single
  stamp does not reach the scan.
* **Resolution.** ``bins > 0`` gives exactly that many rays every turn (what
  slam_toolbox needs; the shorter range wins a shared ray). ``bins = 0``
  gives the device's native resolution: n is the turn's own point count at the
  measured point spacing (about 450 for an LD06 at 10 Hz), so the length may
  change by a ray or two between turns.
* **Ranges** follow REP 117: a device zero (no echo) or a reading beyond
  ``range_max`` is +inf, a reading below ``range_min`` -inf, a ray that no
  point reached +inf, and a ray whose direction is in the crop NaN.
* **The device clock** (milliseconds, wrapping at 30,000) is unwrapped; a step
  backwards or forwards by more than a revolution is a jump of the device's
  clock, not time that passed: the stamps are re-anchored on the rotation
  (and the host clock, when there is one) and :attr:`DeviceClock.jumps`
  counts it. A stall the host clock saw pass is time, not a jump; when a
  turn or more of packets never arrived, the revolution they broke is
  dropped rather than published spliced. Device time is mapped onto the
  host clock by :class:`DeviceClock`, so stamps are free of read jitter.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from ._protocol import (
    ANGLE_UNITS,
    BOUNDARY,
    PACKET_SIZE,
    POINTS_PER_PACKET,
    SUBUNITS,
    TIMESTAMP_WRAP_MS,
    TURN_SUBUNITS,
    Packet,
    encode_packet,
)

__all__ = ["DeviceClock", "Direction", "Scan", "ScanAssembler"]

Direction = Literal["ccw", "cw"]

_HALF_TURN_SUB = TURN_SUBUNITS // 2
_BOUNDARY_SUB = BOUNDARY * SUBUNITS
_TWO_PI = 2 * math.pi
#: Milliseconds a stalled packet may seem to have been measured after it was
#: read (the offset is an estimate) and still count as time that passed.
_SLACK_MS = 5.0

_K = np.arange(POINTS_PER_PACKET, dtype=np.int64)
_KF = _K.astype(np.float64)

#: Noise filter (the vendor's LD06/LD19 near filter): only returns closer
#: than this (mm) are judged.
_NOISE_NEAR_MM = 5000
#: Two neighbouring returns belong to one object when they are at most this
#: many point spacings apart and their distances differ by at most this share.
_NOISE_GAP_POINTS = 2
_NOISE_CONTINUITY = 0.03
#: A group of fewer points than this is dropped unless its mean intensity
#: reaches the second figure (a small object must be a bright one).
_NOISE_SMALL = 3
_NOISE_SMALL_INTENSITY = 220
#: A group of at most this many points is dropped when its mean intensity is
#: at most the second figure.
_NOISE_MEDIUM = 15
_NOISE_DIM_INTENSITY = 15


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
    :param rate: device seconds per host second; 2 for a capture replayed at
        twice its speed, so that stamps, ``scan_time`` and the host clock
        agree.
    :ivar jumps: device clock jumps seen (see :meth:`unwrap`).
    :ivar last_jump: the device timestamps (ms) either side of the latest jump.
    """

    def __init__(self, *, drift: float = 2e-4, max_gap: float = 10.0, rate: float = 1.0) -> None:
        if rate <= 0:
            raise ValueError(f"rate must be positive, got {rate}")
        self._drift = drift
        self._max_gap = max_gap
        self.rate = rate
        self.jumps = 0
        self.last_jump: tuple[int, int] | None = None
        self.reset()

    def reset(self) -> None:
        """Forget all history (after a reopen the device clock is unrelated); keep the jump count."""
        self._last_stamp: int | None = None
        self._device_ms = 0.0
        self._offset: float | None = None
        self._last_host: float | None = None

    @property
    def offset(self) -> float | None:
        """Host time minus device time, in seconds, once anchored."""
        return self._offset

    @property
    def last_host(self) -> float | None:
        """Host time of the latest sample, if any."""
        return self._last_host

    def unwrap(self, timestamp: int, *, limit_ms: float | None = None, instead_ms: float = 0.0) -> float:
        """Return device seconds since the first timestamp, across wraps.

        :param limit_ms: the largest believable step from the previous
            timestamp; a larger one (a backward jump reads as nearly 30 s) is
            a jump of the device's clock: time advances by *instead_ms*.
        """
        if self._last_stamp is not None:
            step: float = (timestamp - self._last_stamp) % TIMESTAMP_WRAP_MS
            if limit_ms is not None and step > limit_ms:
                self.jumps += 1
                self.last_jump = (self._last_stamp, timestamp)
                step = instead_ms
            self._device_ms += step
        self._last_stamp = timestamp
        return self._device_ms / (1000 * self.rate)

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
    ranges metres with REP 117 special values, times seconds. Ray ``i`` points
    at ``angle_min + i * angle_increment`` (= ``angles[i]``) and was measured
    at ``stamp + i * time_increment``.

    :param stamp: host time of ray 0.
    :param device_time: device time of ray 0 (unwrapped).
    :param scan_time: the revolution's period.
    :param time_increment: time from one ray to the next (negative when
        ray 0 is measured last, see the module docstring).
    :param angles: each ray's direction.
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


#: The four header fields of a 47-byte data packet the assembler reads per
#: packet: speed, start angle, end angle, timestamp (C speed, no NumPy call).
_FIELDS = struct.Struct("<2xHH36xHH1x")

#: A data packet as a NumPy record, for the points of a whole revolution at once.
_RECORD = np.dtype(
    [
        ("head", "u1", 2),
        ("speed", "<u2"),
        ("start", "<u2"),
        ("points", [("distance", "<u2"), ("intensity", "u1")], POINTS_PER_PACKET),
        ("end", "<u2"),
        ("timestamp", "<u2"),
        ("crc", "u1"),
    ]
)


@dataclass(slots=True)
class _Turn:
    """One revolution so far: its packets and, per packet, what the points need.

    Points ``first`` of the first packet up to ``until`` of the last belong
    to it (a packet crossing the boundary is shared with the next turn).
    """

    rows: list[NDArray[np.uint8]] = field(default_factory=list)
    device: list[float] = field(default_factory=list)
    """Each packet's first point, device seconds."""
    steps: list[float] = field(default_factory=list)
    """Seconds from one point of the packet to the next."""
    rel: list[int] = field(default_factory=list)
    """Each packet's first point, subunits past the boundary (may exceed a turn)."""
    spans: list[int] = field(default_factory=list)
    first: int = 0
    until: int = POINTS_PER_PACKET
    speed: int = 0


class ScanAssembler:
    """Collect packets into revolutions.

    :param bins: rays per scan; 0 publishes the native resolution (see the
        module docstring).
    :param direction: ``"ccw"`` or ``"cw"``, see the module docstring.
    :param range_min: metres; closer readings become -inf.
    :param range_max: metres; farther readings become +inf.
    :param crop: ``(min, max)`` device degrees to blank out (rays become NaN),
        inclusive; when min > max the sector wraps through 0.
    :param noise_filter: drop isolated dim returns as the vendor's LD06/LD19
        driver does: under 5 m, a group of neighbouring points (each within
        two point spacings and 3% of the distance of the one before) with
        fewer than 3 points and a mean intensity under 220, or with up to 15
        points and a mean intensity of 15 or less. Dropped points count as
        "no return".
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
        noise_filter: bool = False,
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
        self.noise_filter = noise_filter
        self.clock = clock if clock is not None else DeviceClock()
        self._ranges = _range_table(range_min, range_max)
        self._layouts: dict[int, tuple[NDArray[np.float64], NDArray[np.bool_] | None]] = {}
        self._turn: _Turn | None = None
        self._last_end: int | None = None
        self._last_start: int | None = None
        self._last_device: float | None = None
        self._due: float | None = None
        self._due_packets = 0

    def reset(self) -> None:
        """Drop the revolution in progress and the clock (after a reopen)."""
        self._turn = None
        self._last_end = None
        self._last_start = None
        self._last_device = None
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

    @property
    def due_packets(self) -> int:
        """Packets still to come until the current revolution is complete (0: unknown)."""
        return self._due_packets if self._due is not None else 0

    def push(self, packet: Packet, *, host_time: float | None = None) -> list[Scan]:
        """Add one packet; return the revolutions it completed (usually none).

        :param host_time: when the bytes holding *packet* were read, on the
            clock the scans are to be stamped with.
        """
        row = encode_packet(
            speed=packet.speed,
            start_angle=packet.start_angle,
            end_angle=packet.end_angle,
            timestamp=packet.timestamp,
            distances=packet.distances,
            intensities=packet.intensities,
        )
        return self.push_rows(np.frombuffer(row, dtype=np.uint8).reshape(1, PACKET_SIZE), host_time=host_time)

    def push_rows(self, rows: NDArray[np.uint8], *, host_time: float | None = None) -> list[Scan]:
        """Add ``(n, 47)`` data packets read together at *host_time*; return the revolutions they completed.

        The same as pushing them one by one (see :meth:`StreamParser.feed_rows`),
        for a fraction of the cost: the per-packet work is a few integer
        operations, and the points are handled once per revolution.
        """
        if not len(rows):
            return []
        clock = self.clock
        if host_time is not None and clock.gap_too_long(host_time):
            self.reset()
        rows = np.ascontiguousarray(rows, dtype=np.uint8)
        # The latest the first of these packets can have been measured: it
        # was read at host_time, and the offset is the quickest delivery seen.
        slack = (
            None
            if host_time is None or clock.offset is None or self._last_device is None
            else (host_time - clock.offset - self._last_device) * 1000 * clock.rate
        )
        last_start, last_end, previous = self._last_start, self._last_end, self._last_device
        device = -math.inf
        dt = 0.0
        span = speed = 0
        turn = self._turn
        packets = _FIELDS.iter_unpack(rows.data)
        cuts: list[tuple[int, int, bool]] = []  # (packet, first point of the new turn, a turn was lost)
        devices: list[float] = []
        steps: list[float] = []
        rels: list[int] = []
        spans: list[int] = []
        rate = clock.rate
        unwrap = clock.unwrap
        for j, (speed, start, end_angle, stamp) in enumerate(packets):
            if start >= ANGLE_UNITS:
                start %= ANGLE_UNITS
            span = (end_angle - start) % ANGLE_UNITS
            if last_start is None or previous is None or not speed:
                device = unwrap(stamp)
            else:
                turn_ms = 360_000 / speed
                # What the rotation says passed since the previous packet (less whole turns).
                turned = ((start - last_start) % ANGLE_UNITS) * 10 / speed
                limit = turn_ms
                if j == 0 and slack is not None and slack + _SLACK_MS > turn_ms:
                    # A stall of the stream (the device kept turning and
                    # counting) is time that passed, if it had passed by
                    # the time the packet was read.
                    limit = slack + _SLACK_MS
                device = unwrap(stamp, limit_ms=limit, instead_ms=turned)
                if (device - previous) * 1000 * rate - turned > turn_ms / 2:
                    # A turn or more never arrived: the revolution in
                    # progress has a hole of unknown size; drop it.
                    cuts.append((j, 0, True))
            # Degrees/s and 0.01 degree: seconds from one point to the next.
            dt = span / (SUBUNITS * 100 * speed * rate) if speed else 0.0
            rel = ((start - BOUNDARY) % ANGLE_UNITS) * SUBUNITS
            last = rel + span * (POINTS_PER_PACKET - 1)
            # A new revolution starts between packets where the angle past
            # the boundary drops by over half a turn, or inside a packet
            # that crosses it.
            if last_end is not None and rel < last_end - _HALF_TURN_SUB:
                cuts.append((j, 0, False))
            if last >= TURN_SUBUNITS:
                if span:
                    cuts.append((j, -((rel - TURN_SUBUNITS) // span), False))
                last -= TURN_SUBUNITS
            last_end, last_start, previous = last, start, device
            devices.append(device)
            steps.append(dt)
            rels.append(rel)
            spans.append(span)
        # Every packet's last point was measured before host_time; the latest is the tightest bound.
        latest = device + dt * (POINTS_PER_PACKET - 1)
        self._last_start, self._last_end, self._last_device = last_start, last_end, previous
        if host_time is not None:
            clock.observe(latest, host_time)
        self._predict(span, speed, device, dt)

        scans: list[Scan] = []
        begin = (0, 0)
        # A lost turn first: the revolution it broke is dropped, not finished.
        for b, m, lost in sorted([*cuts, (len(rows), 0, False)], key=lambda c: (c[0], c[1], not c[2])):
            a, k = begin
            until = b + 1 if m else b  # packets holding points of this piece
            if turn is not None and (a, k) < (b, m):
                turn.rows.append(rows[a:until])
                turn.device += devices[a:until]
                turn.steps += steps[a:until]
                turn.rel += rels[a:until]
                turn.spans += spans[a:until]
                turn.until = m if m else POINTS_PER_PACKET
                turn.speed = int(rows[until - 1, 2]) | int(rows[until - 1, 3]) << 8
            if lost:
                turn = None
            elif b < len(rows):
                if turn is not None and turn.rel:
                    scans.append(self._finish(turn))
                turn = _Turn(first=m)
            begin = (b, m)
        self._turn = turn
        return scans

    def rehearse(self) -> None:
        """Finish the revolution in progress as if it were complete, and drop the result.

        For a reader to call while a revolution's last packets are on their
        way. After a sleep, this machine runs the finish (some thirty NumPy
        calls) with cold caches: 0.3-0.4 ms against 70 us warm, most of the
        delay from the last byte to the scan. Rehearsed a few milliseconds
        before, it runs warm when it counts: the median delay went from
        0.83-0.92 ms to 0.74-0.80 ms in three alternating pairs of runs, for
        one more finish per revolution (about 0.1% of a core at 10 Hz).
        """
        turn = self._turn
        if turn is not None and turn.rows and turn.rel:
            self._finish(turn)

    def _predict(self, span: int, speed: int, device: float, dt: float) -> None:
        """When the packet completing the revolution will have been measured, in device time."""
        if not span or not speed or self._last_end is None:
            self._due = None
            return
        # Points to come until one reaches the boundary; the turn completes
        # with the last point of the packet holding it.
        remaining = TURN_SUBUNITS - self._last_end
        points = -(-remaining // span)
        packets = -(-points // POINTS_PER_PACKET)
        self._due = device + dt * (POINTS_PER_PACKET - 1 + POINTS_PER_PACKET * packets)
        self._due_packets = packets

    def _finish(self, turn: _Turn) -> Scan:
        rows = turn.rows[0] if len(turn.rows) == 1 else np.concatenate(turn.rows)
        record = rows.view(_RECORD).ravel()
        stop = len(rows) * POINTS_PER_PACKET - (POINTS_PER_PACKET - turn.until)
        points = slice(turn.first, stop)
        rel = np.array(turn.rel, dtype=np.int64)
        spans = np.array(turn.spans, dtype=np.int64)
        pos = (rel[:, None] + spans[:, None] * _K).ravel()[points] % TURN_SUBUNITS
        times = (np.array(turn.device)[:, None] + np.array(turn.steps)[:, None] * _KF).ravel()[points]
        dist = record["points"]["distance"].ravel()[points]
        inten = record["points"]["intensity"].ravel()[points]
        if self.noise_filter:
            dist = _filter_noise(pos, dist, inten, spans)

        n = self.bins or _native_rays(rel, spans, len(pos))
        slope, intercept = _time_line(pos, times, turn.speed)
        # Ray i's sector: [i, i + 1) * turn / n past the boundary, in the
        # direction of measurement; for ccw ray 0 is the last sector.
        index = pos * n
        index //= TURN_SUBUNITS
        if self.direction == "ccw":
            np.subtract(n - 1, index, out=index)
        out, out_int = _winners(index, dist, inten, n, self._ranges)

        angles, cropped = self._layout(n)
        if cropped is not None:
            out[cropped] = np.nan
            out_int[cropped] = 0
        increment = _TWO_PI / n
        sector = TURN_SUBUNITS / n
        centre = TURN_SUBUNITS - sector / 2 if self.direction == "ccw" else sector / 2
        first_time = intercept + slope * centre
        time_increment = slope * sector * (-1 if self.direction == "ccw" else 1)
        return Scan(
            stamp=self.clock.to_host(first_time),
            device_time=first_time,
            scan_time=slope * TURN_SUBUNITS,
            time_increment=time_increment,
            angle_min=float(angles[0]),
            angle_max=float(angles[-1]),
            angle_increment=increment,
            range_min=self.range_min,
            range_max=self.range_max,
            angles=angles,
            ranges=out,
            intensities=out_int,
            points=len(pos),
        )

    def _layout(self, n: int) -> tuple[NDArray[np.float64], NDArray[np.bool_] | None]:
        """The ray directions of an n-ray scan (read-only, shared) and which of them the crop blanks."""
        layout = self._layouts.get(n)
        if layout is None:
            increment = _TWO_PI / n
            angles = (-math.pi + increment / 2) + increment * np.arange(n, dtype=np.float64)
            angles.setflags(write=False)
            layout = angles, (self._cropped(angles) if self.crop is not None else None)
            if len(self._layouts) < 64:  # bins: 0 sees a few lengths only
                self._layouts[n] = layout
        return layout

    def _cropped(self, angles: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which published *angles* lie in the crop, a sector given in device degrees."""
        assert self.crop is not None
        device = -angles if self.direction == "ccw" else angles
        deg = np.degrees(device) % 360
        low, high = self.crop
        if low <= high:
            return (deg >= low) & (deg <= high)
        return (deg >= low) | (deg <= high)


def _median(values: NDArray[np.int64]) -> float:
    """``np.median`` of a non-empty array, for a fraction of its cost.

    ``np.median`` goes through several layers of Python (partition, mean,
    NaN checks): right after the loop wakes, with cold caches, it took
    about 140 us of the 0.3 ms between a revolution's last bytes and its
    scan; a sort of a turn's 40 packets is a few microseconds.
    """
    ordered = np.sort(values)
    middle = len(ordered) // 2
    if len(ordered) % 2:
        return float(ordered[middle])
    return (float(ordered[middle - 1]) + float(ordered[middle])) / 2


def _native_rays(rel: NDArray[np.int64], spans: NDArray[np.int64], points: int) -> int:
    """Rays at the device's own resolution: a turn over the typical point spacing.

    The spacing is a packet's advance over its 12 points (the span inside a
    packet alone is a little shorter than the step between packets), the
    median over the turn so that a missing packet does not count.
    """
    advance = np.diff(rel) % TURN_SUBUNITS
    known = advance[advance > 0]
    if len(known):
        spacing = _median(known) / POINTS_PER_PACKET
    else:
        spacing = _median(spans) / (POINTS_PER_PACKET - 1) if len(spans) else 0.0
    if spacing <= 0:
        return max(points, 1)
    return max(round(TURN_SUBUNITS / spacing), 1)


def _time_line(pos: NDArray[np.int64], times: NDArray[np.float64], speed: int) -> tuple[float, float]:
    """Least-squares ``time = intercept + slope * pos`` over the revolution's points.

    One stamp has a resolution of 1 ms, about four points of an LD06; a line
    through all of a turn's stamps is far better than any one of them. With
    too few points, the rotation speed gives the slope.
    """
    count = len(pos)
    if count >= 2:
        x = pos.astype(np.float64)
        sx, st = float(x.sum()), float(times.sum())
        var = count * float(x @ x) - sx * sx
        if var > 0:
            slope = (count * float(x @ times) - sx * st) / var
            if slope > 0:
                return slope, (st - slope * sx) / count
    slope = 1 / (SUBUNITS * 100 * speed) if speed else 0.0
    return slope, float(times[0]) - slope * float(pos[0])


#: Keys of a reading when rays are shared: a finite distance (mm) is its own
#: key, so the shorter wins; then "too close", then "nothing there".
_TOO_CLOSE = 1 << 17
_NOTHING = 1 << 18
_EMPTY = 1 << 19


def _range_table(range_min: float, range_max: float) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """Tables from a device distance (mm) to its key, and from a key to the published range.

    Two lookups replace the per-scan REP 117 arithmetic: 0 (no echo) and
    beyond *range_max* are +inf, below *range_min* -inf, a ray no point
    reached +inf.
    """
    mm = np.arange(1 << 16, dtype=np.int64)
    metres = mm.astype(np.float32) / np.float32(1000)
    key = np.where(metres > range_max, _NOTHING, np.where(metres < range_min, _TOO_CLOSE, mm))
    key[0] = _NOTHING
    ranges = np.full(_EMPTY + 1, np.inf, dtype=np.float32)
    ranges[: 1 << 16] = metres
    ranges[_TOO_CLOSE] = -np.inf
    return key.astype(np.int32), ranges


def _winners(
    index: NDArray[np.int64],
    dist: NDArray[np.uint16],
    intensities: NDArray[np.uint8],
    n: int,
    tables: tuple[NDArray[np.int32], NDArray[np.float32]],
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """One range per ray: finite beats "too close", which beats "nothing there"; the shorter finite wins."""
    keys, ranges = tables
    key = keys.take(dist)
    best = np.full(n, _EMPTY, dtype=np.int32)
    np.minimum.at(best, index, key)
    out = ranges.take(best)
    won = key == best.take(index)
    out_int = np.zeros(n, dtype=np.float32)
    out_int[index[won]] = intensities[won]
    return out, out_int


def _filter_noise(
    pos: NDArray[np.int64], dist: NDArray[np.uint16], inten: NDArray[np.uint8], spans: NDArray[np.int64]
) -> NDArray[np.uint16]:
    """Return *dist* with isolated dim returns set to 0 (see :class:`ScanAssembler`)."""
    near = (dist > 0) & (dist < _NOISE_NEAR_MM)
    if not near.any():
        return dist
    # Positions are subunits, and a packet's points are `span` subunits apart.
    spacing = _median(spans) if len(spans) else 0.0
    idx = np.flatnonzero(near)
    p, d = pos[idx], dist[idx].astype(np.int64)
    # Neighbours in angle among the near points, as the vendor groups them.
    joined = (np.diff(p) <= _NOISE_GAP_POINTS * spacing) & (
        np.abs(np.diff(d)) <= _NOISE_CONTINUITY * d[:-1]
    )
    group = np.concatenate(([0], np.cumsum(~joined)))
    if len(idx) > 1 and group[-1] > 0 and (
        p[0] + TURN_SUBUNITS - p[-1] <= _NOISE_GAP_POINTS * spacing
        and abs(int(d[0]) - int(d[-1])) <= _NOISE_CONTINUITY * d[-1]
    ):
        group[group == group[-1]] = 0  # the groups either side of the boundary are one
    size = np.bincount(group)
    mean = np.bincount(group, weights=inten[idx]) / size
    drop = ((size < _NOISE_SMALL) & (mean < _NOISE_SMALL_INTENSITY)) | (
        (size <= _NOISE_MEDIUM) & (mean <= _NOISE_DIM_INTENSITY)
    )
    out = dist.copy()
    out[idx[drop[group]]] = 0
    return out
