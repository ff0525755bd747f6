"""A LiDAR you can run without one: a room, a packet generator, a pseudo-terminal.

:class:`PacketGenerator` makes the byte stream a device in a :class:`Room`
would send (real packet format, real rates, a 30,000 ms wrapping clock).
:class:`Emulator` writes it to a pseudo-terminal in real time, with faults
on demand; a pty ignores the baud rate, so the emulator paces itself at the
model's packet rate. :class:`Replayer` writes a capture instead, at the pace
of its device's timestamps.

The writing runs on a thread of its own, not on the event loop: waking the
container's loop (through ``rcl_wait``) and a NumPy call for every few
packets cost the README's first command 11-14% of a core. Packets are made
half a second at a time; the thread writes what is due every ``tick`` and
when a revolution ends. On the project's VM every wake-up of a sleeping
thread costs 75-200 us of CPU as ``/proc`` counts it, so few wake-ups is
what keeps the emulator under 1% of a core.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import math
import os
import shutil
import tempfile
import threading
import time
import tty
from dataclasses import dataclass
from typing import Literal, Self

import numpy as np
from numpy.typing import NDArray

from ._bulk import crc_rows
from ._errors import DeviceError, LidarError
from ._protocol import (
    ANGLE_UNITS,
    BOUNDARY,
    HEADER,
    PACKET_SIZE,
    PACKET_TYPE,
    POINTS_PER_PACKET,
    TIMESTAMP_WRAP_MS,
    Model,
    encode_health,
    get_model,
)

__all__ = ["Emulator", "PacketGenerator", "Replayer", "Room"]

_State = Literal["unopened", "running", "unplugged", "closed"]

#: Seconds of packets an emulator makes at once (NumPy's cost is per call).
_BATCH_S = 0.5

#: Longest time between an emulator's writes: a USB serial adapter hands the
#: host its bytes in bursts too. Each write costs the writer thread a wake-up,
#: on the project's 2-core VM 75-200 us of CPU as /proc counts it. The writes
#: are spread evenly up to each revolution's end (three per LD06 revolution).
DEFAULT_TICK_S = 0.035


@dataclass(frozen=True, slots=True)
class Room:
    """A rectangular room around the sensor and a round object pacing in it.

    Coordinates are metres in the sensor's frame (x forward, y left); the
    object moves along x at height *object_y*, back and forth over
    *object_travel* metres every *object_period* seconds.
    """

    x_min: float = -2.0
    x_max: float = 4.0
    y_min: float = -1.5
    y_max: float = 2.5
    object_radius: float = 0.25
    object_x: float = 1.5
    object_y: float = -0.6
    object_travel: float = 1.2
    object_period: float = 8.0
    noise_mm: float = 4.0
    dropout: float = 0.004
    max_range: float = 12.0

    def object_centre(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
        x = self.object_x + self.object_travel * np.sin(2 * math.pi * t / self.object_period)
        return x, self.object_y

    def measure(
        self,
        theta: NDArray[np.float64],
        t: NDArray[np.float64],
        rng: np.random.Generator,
    ) -> tuple[NDArray[np.uint16], NDArray[np.uint8]]:
        """Return distances (mm) and intensities seen along clockwise angles *theta* (degrees)."""
        rad = np.radians(theta)
        dx = np.cos(rad)
        dy = -np.sin(rad)
        with np.errstate(divide="ignore"):
            tx = np.where(dx > 0, self.x_max / dx, np.where(dx < 0, self.x_min / dx, np.inf))
            ty = np.where(dy > 0, self.y_max / dy, np.where(dy < 0, self.y_min / dy, np.inf))
        wall = np.minimum(tx, ty)
        cx, cy = self.object_centre(t)
        along = dx * cx + dy * cy
        disc = along**2 - (cx**2 + cy**2) + self.object_radius**2
        hit = np.where(disc >= 0, along - np.sqrt(np.maximum(disc, 0)), np.inf)
        hit = np.where(hit > 0, hit, np.inf)
        on_object = hit < wall
        dist = np.minimum(wall, hit) * 1000 + rng.normal(0, self.noise_mm, theta.shape)
        intensity = np.where(on_object, 120, 200) + rng.integers(-8, 9, theta.shape)
        lost = (dist > self.max_range * 1000) | (rng.random(theta.shape) < self.dropout)
        dist = np.where(lost, 0, np.clip(dist, 0, 65535))
        intensity = np.where(lost, 0, intensity)
        return dist.astype(np.uint16), intensity.astype(np.uint8)


class PacketGenerator:
    """The packets a device in a room sends, in order, as bytes.

    :param model: a :class:`Model` or its name.
    :param room: the scene; a default :class:`Room` if not given.
    :param scan_hz: rotation rate (the LD06's PWM-less default is about 10 Hz).
    :param start_ms: the device clock at the first packet.
    :param seed: noise seed, for reproducible streams.
    """

    def __init__(
        self,
        model: Model | str = "LD06",
        *,
        room: Room | None = None,
        scan_hz: float | None = None,
        start_ms: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.model = get_model(model) if isinstance(model, str) else model
        self.room = room if room is not None else Room()
        self.scan_hz = scan_hz if scan_hz is not None else self.model.scan_hz
        self.start_ms = start_ms
        self._rng = np.random.default_rng(seed)
        self.count = 0

    @property
    def time(self) -> float:
        """Device seconds at the next packet, since the generator started."""
        return self.count / self.model.packets_per_second

    def rows(self, count: int) -> NDArray[np.uint8]:
        """Return the next *count* packets as a ``(count, 47)`` array."""
        pps = self.model.packets_per_second
        point_dt = 1 / self.model.points_per_second
        t = (self.count + np.arange(count)) / pps
        self.count += count
        tp = t[:, None] + point_dt * np.arange(POINTS_PER_PACKET)
        theta = (360.0 * self.scan_hz * tp) % 360.0
        dist, inten = self.room.measure(theta, tp, self._rng)
        start = np.rint(theta[:, 0] * 100).astype(np.int64) % ANGLE_UNITS
        end = np.rint(theta[:, -1] * 100).astype(np.int64) % ANGLE_UNITS
        stamp = np.rint(t * 1000 + self.start_ms).astype(np.int64) % TIMESTAMP_WRAP_MS

        rows = np.zeros((count, PACKET_SIZE), dtype=np.uint8)
        rows[:, 0] = HEADER
        rows[:, 1] = PACKET_TYPE
        _put_u16(rows, 2, np.full(count, round(360 * self.scan_hz)))
        _put_u16(rows, 4, start)
        for k in range(POINTS_PER_PACKET):
            _put_u16(rows, 6 + 3 * k, dist[:, k])
            rows[:, 8 + 3 * k] = inten[:, k]
        _put_u16(rows, 42, end)
        _put_u16(rows, 44, stamp)
        rows[:, 46] = crc_rows(rows)
        return rows

    def packets(self, count: int) -> bytes:
        """Return the next *count* packets as a byte string."""
        return self.rows(count).tobytes()


def _put_u16(rows: NDArray[np.uint8], at: int, values: NDArray[np.integer]) -> None:
    rows[:, at] = values & 0xFF
    rows[:, at + 1] = (values >> 8) & 0xFF


class Emulator:
    """An emulated LiDAR on a pseudo-terminal, paced in real time.

    Use as ``async with Emulator(model="LD06") as emu:`` and open
    :attr:`link` (stable across :meth:`unplug` / :meth:`replug`) or
    :attr:`port` (the current ``/dev/pts/N``).

    :param model: a :class:`Model` or its name.
    :param room: the scene.
    :param start_ms: device clock at start (set near 30,000 to see a wrap soon).
    :param link_dir: where to put the stable symlink; a temporary directory
        (removed on :meth:`stop`) if not given.
    :param tick: the most seconds between writes (:data:`DEFAULT_TICK_S`); packets due in between go together.
    """

    def __init__(
        self,
        *,
        model: Model | str = "LD06",
        room: Room | None = None,
        scan_hz: float | None = None,
        start_ms: float = 0.0,
        seed: int = 0,
        link_dir: str | None = None,
        tick: float = DEFAULT_TICK_S,
    ) -> None:
        self.generator = PacketGenerator(model, room=room, scan_hz=scan_hz, start_ms=start_ms, seed=seed)
        self.model = self.generator.model
        self._tick = tick
        self._own_dir = link_dir is None
        self._dir = link_dir
        self._master: int | None = None
        self._slave: int | None = None
        self._port: str | None = None
        self._writer: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping = threading.Event()
        # The pty's file descriptors and what waits to be injected are
        # shared with the writer thread.
        self._lock = threading.Lock()
        self._injected = bytearray()
        self._paused = False
        # Packets made and not sent yet, and which of them end a revolution.
        self._pending = b""
        self._turn_ends: collections.deque[int] = collections.deque()
        self._last_angle: int | None = None
        self.state: _State = "unopened"
        self.packets_sent = 0
        self.bytes_dropped = 0

    @property
    def port(self) -> str:
        """The current pseudo-terminal, e.g. ``/dev/pts/3``."""
        if self._port is None:
            raise LidarError(f"emulator is {self.state}: no port")
        return self._port

    @property
    def link(self) -> str:
        """A symlink to :attr:`port` that survives :meth:`replug`."""
        if self._dir is None:
            raise LidarError(f"emulator is {self.state}: no link")
        return os.path.join(self._dir, f"ldlidar-{self.model.name.lower()}")

    def owns(self, device: int) -> bool:
        """Whether *device* (an ``st_rdev``) is this emulator's pseudo-terminal, now.

        What a node that started this emulator admits besides the
        operator's device policy (:meth:`container.devices.DevicePolicy.with_own_devices`):
        this very pty, not pseudo-terminals at large.
        """
        with self._lock:
            slave = self._slave
            return slave is not None and os.fstat(slave).st_rdev == device

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def start(self) -> None:
        """Open the pty and start sending."""
        if self.state != "unopened":
            raise LidarError(f"emulator is {self.state}; start() needs a new one")
        if self._dir is None:
            self._dir = tempfile.mkdtemp(prefix="ldlidar-emu-")
        self._plug()
        self.state = "running"
        self._loop = asyncio.get_running_loop()
        self._writer = threading.Thread(target=self._write_paced, name="ldlidar-emulator", daemon=True)
        self._writer.start()

    async def stop(self) -> None:
        """Stop sending and close the pty; safe to call twice."""
        if self.state == "closed":
            return
        writer, self._writer = self._writer, None
        if writer is not None:
            self._stopping.set()
            # It ends within a tick: its writes never block (O_NONBLOCK).
            writer.join(1.0)
        self._unplug()
        if self._own_dir and self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
        self.state = "closed"

    def inject(self, data: bytes) -> None:
        """Send *data* raw, between two packets, at the next tick."""
        with self._lock:
            self._injected += data

    def inject_garbage(self, count: int, *, seed: int | None = None) -> bytes:
        """Send *count* random bytes; return them."""
        data = np.random.default_rng(seed).integers(0, 256, count, dtype=np.uint8).tobytes()
        self.inject(data)
        return data

    def inject_health(self, code: int = 0) -> None:
        """Send a health frame with error *code*."""
        self.inject(encode_health(code))

    def pause(self) -> None:
        """Stop delivering packets, as a stalled USB link: the device turns on, its packets are lost."""
        self._paused = True

    def resume(self) -> None:
        """Deliver packets again (from where the device is now)."""
        self._paused = False

    async def unplug(self) -> None:
        """Close the pty as a pulled USB adapter would; the link disappears."""
        if self.state != "running":
            raise LidarError(f"emulator is {self.state}; cannot unplug")
        self._unplug()
        self.state = "unplugged"

    async def replug(self) -> None:
        """Open a new pty behind the same :attr:`link`."""
        if self.state != "unplugged":
            raise LidarError(f"emulator is {self.state}; cannot replug")
        self._plug()
        self.state = "running"

    def _plug(self) -> None:
        try:
            master, slave = os.openpty()
        except OSError as exc:
            raise DeviceError(f"cannot open a pseudo-terminal: {exc}", device="emulator") from exc
        tty.setraw(slave)
        os.set_blocking(master, False)
        with self._lock:
            self._master, self._slave = master, slave
        self._port = os.ttyname(slave)
        tmp = self.link + ".new"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        os.symlink(self._port, tmp)
        os.replace(tmp, self.link)

    def _unplug(self) -> None:
        with self._lock:
            for fd in (self._master, self._slave):
                if fd is not None:
                    os.close(fd)
            self._master = self._slave = None
        self._port = None
        if self._dir is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.link)

    def _write_paced(self) -> None:
        """The writer thread: at most a ``tick`` apart and when a revolution ends, write what is due.

        A revolution's last packet goes out with the next one, when that is
        due, not up to a tick later: a real device delivers every packet
        within a millisecond or so, and a driver's latency is measured from
        the bytes that complete a revolution.
        """
        begin = time.monotonic()
        wake = 0.0
        while not self._stopping.is_set():
            count, data = self._due(time.monotonic() - begin)
            with self._lock:
                if self._injected:
                    data = bytes(self._injected) + data
                    self._injected.clear()
                if not data:
                    pass
                elif self._master is None or self._paused:
                    self.bytes_dropped += len(data)
                else:
                    self.packets_sent += count
                    self._write(data)
            if self._finished():
                return
            # Scheduled, not from when it woke, so that late wake-ups do not
            # add up. A plain sleep: a timed Event.wait costs 85 us of CPU
            # here, sleep 29 us; stop() waits out at most one tick.
            wake = self._next_wake(wake)
            late = time.monotonic() - begin
            if wake <= late:  # overslept (a loaded machine): no burst of catch-up writes
                wake = self._next_wake(late)
            time.sleep(max(0.0, begin + wake - time.monotonic()))

    def _next_wake(self, last: float) -> float:
        """Seconds from the start of the write after the one scheduled at ``last``.

        The time up to the next revolution's end is cut into equal steps of
        at most a tick, so that the end falls on a step: a write every 33 ms
        at the LD06's 10 Hz and 35 ms ticks, 30 wake-ups a second, where a
        fixed grid of 30 ms ticks plus one wake-up per end made 43.
        """
        end = self._next_end()
        if end is None or end <= last:
            return last + self._tick
        steps = math.ceil((end - last) / self._tick - 1e-9)
        return last + (end - last) / steps

    def _released(self) -> int:
        """Packets made and already handed to the writer (sent or dropped)."""
        return self.generator.count - len(self._pending) // PACKET_SIZE

    def _next_end(self) -> float | None:
        """Seconds from the start at which the packet after a revolution's last is due (the next such)."""
        sent = self._released()
        ends = self._turn_ends
        # Done with an end once the packet after it went out too.
        while ends and ends[0] + 1 < sent:
            ends.popleft()
        if not ends:
            self._generate(round(self.model.packets_per_second * _BATCH_S))
        # With the packet after it: a driver knows a revolution has ended
        # when it sees the angle pass the back of the sensor.
        return (ends[0] + 2) / self.model.packets_per_second if ends else None

    def _generate(self, count: int) -> None:
        """Make ``count`` more packets; note which of them end a revolution."""
        first = self.generator.count
        rows = self.generator.rows(count)
        self._pending += rows.tobytes()
        # Where a driver ends a revolution, by ScanAssembler's rule (that of
        # DecodedStream.wraps, without decoding again what was just made):
        # the angle, measured from the back of the sensor, drops within a
        # packet or by more than half a turn from one packet to the next.
        start = ((rows[:, 4].astype(np.int64) | rows[:, 5].astype(np.int64) << 8) - BOUNDARY) % ANGLE_UNITS
        end = ((rows[:, 42].astype(np.int64) | rows[:, 43].astype(np.int64) << 8) - BOUNDARY) % ANGLE_UNITS
        previous = np.concatenate(([self._last_angle if self._last_angle is not None else start[0]], end[:-1]))
        turning = (end < start) | (start < previous - ANGLE_UNITS // 2)
        self._turn_ends.extend(first + int(k) for k in np.flatnonzero(turning))
        self._last_angle = int(end[-1])

    def _due(self, elapsed: float) -> tuple[int, bytes]:
        """The packets due ``elapsed`` seconds after the start that are not sent yet."""
        pps = self.model.packets_per_second
        due = int(elapsed * pps + 1e-9) - self._released()
        if due <= 0:
            return 0, b""
        if len(self._pending) < due * PACKET_SIZE:
            self._generate(max(due, round(pps * _BATCH_S)))
        size = due * PACKET_SIZE
        data, self._pending = self._pending[:size], self._pending[size:]
        return due, data

    def _finished(self) -> bool:
        """Whether the writer is done (a replay that does not loop)."""
        return False

    def _write(self, data: bytes) -> None:
        """Write without blocking; a device without a listener loses bytes too.

        Runs on the writer thread, with the emulator's lock held.
        """
        assert self._master is not None
        try:
            written = os.write(self._master, data)
        except (BlockingIOError, OSError):
            written = 0
        self.bytes_dropped += len(data) - written


class Replayer(Emulator):
    """A capture played on a pseudo-terminal at its device's own pace, for any driver to read.

    :param path: the capture file.
    :param rate: 2.0 plays twice as fast, 0.5 at half speed.
    :param loop: play again from the start at the end (the device clock
        then jumps back, as after a device reset); otherwise the pty stays
        open and silent.
    :param link_dir, tick: see :class:`Emulator`.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        rate: float = 1.0,
        loop: bool = False,
        model: Model | str = "LD06",
        link_dir: str | None = None,
        tick: float = DEFAULT_TICK_S,
    ) -> None:
        if not rate > 0:
            raise ValueError(f"rate must be positive, got {rate}")
        super().__init__(model=model, link_dir=link_dir, tick=tick)
        self.path = os.fspath(path)
        self.rate = rate
        self.loop = loop
        self.finished = asyncio.Event()

    async def start(self) -> None:
        """Read the capture, open the pty and start playing.

        :raises DeviceError: the capture cannot be read.
        """
        from ._sources import replay_schedule

        try:
            with open(self.path, "rb") as f:
                self._data = f.read()
        except OSError as exc:
            raise DeviceError(f"cannot read capture: {exc.strerror or exc}", device=self.path) from exc
        self._ends, self._times, self._duration = replay_schedule(self._data)
        self._lap, self._sent, self._pos = 0, 0, 0
        await super().start()

    def _due(self, elapsed: float) -> tuple[int, bytes]:
        played = elapsed * self.rate - self._lap * self._duration
        sent = due = self._sent
        while due < len(self._ends) and self._times[due] <= played:
            due += 1
        data = b""
        if due > sent:
            data = self._data[self._pos : self._ends[due - 1]]
            self._pos, self._sent = self._ends[due - 1], due
        if self._sent == len(self._ends) and self.loop:
            self._lap, self._sent, self._pos = self._lap + 1, 0, 0
        return due - sent, data

    def _next_end(self) -> float | None:
        return None  # a capture is written on its ticks only

    def _finished(self) -> bool:
        if self._sent < len(self._ends) or self.loop:
            return False
        assert self._loop is not None
        with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
            self._loop.call_soon_threadsafe(self.finished.set)
        return True
