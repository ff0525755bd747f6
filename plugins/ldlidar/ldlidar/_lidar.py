"""A LiDAR as an async stream of scans: source + parser + assembler, and reopen.

The community driver exits when the port cannot open and never reopens after
a USB adapter is pulled. Here :meth:`Lidar.open` raises :class:`DeviceError`
(so a configure transition can fail cleanly), and :meth:`Lidar.scans` keeps
reopening the same path (a udev or emulator symlink) until it comes back.
Every open, each reopen included, asks the container's device policy anew:
a symlink re-pointed while the device was away is decided on what it
points to now, and refused without being opened.

Faults are never quiet: a caller passes ``on_event`` and hears of the device
being lost, reconnected (and after how long), stalling (and for how long)
and its clock jumping; :meth:`Lidar.open` tells a silent port from one whose
bytes never form a packet.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from container.devices import DevicePolicy

from ._errors import DeviceError, DeviceRefused
from ._parser import ParserStats, StreamParser
from ._protocol import PACKET_SIZE, Model, get_model
from ._scan import Direction, Scan, ScanAssembler
from ._sources import ReplaySource, SerialSource, open_source

__all__ = ["EventKind", "Lidar"]

#: Bytes gathered before parsing at the latest, whatever is expected.
_HOLD_MAX = 16384

EventKind = Literal["lost", "reconnected", "refused", "stalled", "clock_jump"]
"""What :class:`Lidar` reports through ``on_event``."""


class Lidar:
    """One LD-series LiDAR.

    :param port: device path, pyserial URL, or ``file://capture.bin``.
    :param model: a :class:`Model` or its name; sets the default baud rate.
    :param baudrate: overrides the model's baud rate.
    :param poll_interval: read a serial port every so many seconds instead
        of as soon as bytes arrive, and when each revolution is predicted to
        complete; see :class:`SerialSource`.
    :param timeout: seconds without a valid packet before the device counts
        as failed (``comm.timeout_msec`` in the community driver).
    :param reopen: after a failure, keep trying to reopen the port instead
        of raising.
    :param reopen_interval: seconds before the first reopen attempt.
    :param reopen_max_interval: if given, the wait doubles after each failed
        attempt up to this many seconds (a backoff for a device that stays
        away); if ``None``, every attempt waits :attr:`reopen_interval`.
    :param clock: the host clock scans are stamped with (seconds).
    :param stall: seconds without a packet, short of :attr:`timeout`, that
        count as a stall (reported when data resumes).
    :param on_event: called with an :data:`EventKind` and a one-line
        message when the device is lost or reconnected, stalls, or its clock
        jumps, and when the device policy refuses a reopen (once per reason).
    :param policy: what the port may name, decided at every open and
        reopen; the process's (:func:`container.devices.device_policy`) if
        not given.
    :param bins, direction, range_min, range_max, crop, noise_filter: see
        :class:`ScanAssembler`.
    :ivar state: ``unopened``, ``open``, ``reconnecting`` (the port failed and
        is being reopened) or ``closed``.
    :ivar reopens: successful reopens since :meth:`open`.
    :ivar stalls: stalls (see *stall*) since :meth:`open`.
    :ivar last_error: why the device failed or a reopen attempt failed,
        while it is being reopened; ``None`` when it works.
    :ivar bytes_read: bytes read from the port since :meth:`open`, valid or
        not (with :attr:`stats`, tells a silent port from a garbled one).
    :ivar packet_time: ``time.monotonic()`` when the latest valid packet was
        parsed; ``None`` before the first.
    """

    def __init__(
        self,
        port: str,
        *,
        model: Model | str = "LD06",
        baudrate: int | None = None,
        bins: int = 0,
        direction: Direction = "ccw",
        range_min: float = 0.03,
        range_max: float = 15.0,
        crop: tuple[float, float] | None = None,
        noise_filter: bool = False,
        poll_interval: float | None = None,
        timeout: float = 1.0,
        reopen: bool = True,
        reopen_interval: float = 0.5,
        reopen_max_interval: float | None = None,
        clock: Callable[[], float] = time.time,
        stall: float = 0.25,
        on_event: Callable[[EventKind, str], None] | None = None,
        policy: DevicePolicy | None = None,
    ) -> None:
        self.port = port
        self.policy = policy
        self.model = get_model(model) if isinstance(model, str) else model
        self.baudrate = baudrate if baudrate is not None else self.model.baudrate
        self.poll_interval = poll_interval
        self.timeout = timeout
        self.reopen = reopen
        self.reopen_interval = reopen_interval
        self.reopen_max_interval = reopen_max_interval
        self._clock = clock
        self.stall = stall
        self._on_event = on_event
        self.parser = StreamParser()
        self.assembler = ScanAssembler(
            bins=bins,
            direction=direction,
            range_min=range_min,
            range_max=range_max,
            crop=crop,
            noise_filter=noise_filter,
        )
        self._source: SerialSource | ReplaySource | None = None
        # Packets parsed but not yet assembled, each batch with its read time.
        self._pending: list[tuple[NDArray[np.uint8], float]] = []
        self.state: Literal["unopened", "open", "reconnecting", "closed"] = "unopened"
        self.reopens = 0
        self.last_error: str | None = None
        self.stalls = 0
        self.bytes_read = 0
        self.packet_time: float | None = None
        self._held = b""
        self._held_time = 0.0
        self._last_packet = 0.0
        self._jumps = 0

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` ran (or the device failed for good, or a capture ended)."""
        # Not an inline comparison: mypy narrows ``state`` and cannot see it change across awaits.
        return self.state == "closed"

    @property
    def stats(self) -> ParserStats:
        return self.parser.stats

    async def __aenter__(self) -> Lidar:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def open(self) -> None:
        """Open the port and wait for the first valid packet.

        :raises DeviceError: the port cannot open, or sends nothing valid
            within :attr:`timeout`.
        """
        if self.state != "unopened":
            raise DeviceError(f"cannot open: lidar is {self.state}", device=self.port)
        try:
            await self._connect()
        except BaseException:
            self.state = "closed"
            raise
        self.state = "open"

    async def _connect(self) -> None:
        source = open_source(
            self.port, baudrate=self.baudrate, poll_interval=self.poll_interval, policy=self.policy
        )
        await source.open()
        self._source = source
        if isinstance(source, ReplaySource) and source.rate is not None:
            self.assembler.clock.rate = source.rate
        received = 0
        try:
            async with asyncio.timeout(self.timeout):
                while not self._pending:
                    chunk = await source.read()
                    if not chunk:
                        raise DeviceError("capture holds no valid packet", device=self.port)
                    received += len(chunk)
                    self.bytes_read += len(chunk)
                    rows = self.parser.feed_rows(chunk)
                    if len(rows):
                        self._pending.append((rows, self._clock()))
        except TimeoutError:
            await source.close()
            if not received:
                raise DeviceError(
                    f"silent: not one byte within {self.timeout:g} s (is the LiDAR powered, "
                    "and is this its port?)",
                    device=self.port,
                ) from None
            raise DeviceError(
                f"{received} bytes within {self.timeout:g} s but no valid packet "
                f"({self.parser.stats.crc_errors} failed CRC): wrong baud rate "
                f"(reading at {self.baudrate}) or not an LD-series LiDAR?",
                device=self.port,
            ) from None
        except BaseException:
            # A bad capture, or cancelled (a transition timed out): never
            # leave the port open behind the caller's back.
            await source.close()
            raise
        self._last_packet = self.packet_time = time.monotonic()

    async def scans(self) -> AsyncIterator[Scan]:
        """Yield scans until :meth:`close`, reopening the port after failures.

        :raises DeviceError: the device failed and :attr:`reopen` is off.
        """
        if self.state == "unopened":
            raise DeviceError("cannot read scans: lidar is not open", device=self.port)
        assembler = self.assembler
        rehearse = False
        while self.state in ("open", "reconnecting"):
            while self._pending:
                rows, read_at = self._pending.pop(0)
                for scan in assembler.push_rows(rows, host_time=read_at):
                    yield scan
                if assembler.clock.jumps != self._jumps:
                    self._clock_jumped()
            if rehearse:
                rehearse = False
                assembler.rehearse()
            if self.state == "reconnecting":
                await self._reconnect()
                continue
            source = self._source
            assert source is not None
            due = self._read_due()
            if self._held and due is not None and self._next_read_ends_turn(due):
                # Digest what is held before waiting for the revolution's last
                # bytes: then only they are parsed between their arrival and
                # the scan (with the loop's caches cold, parsing a turn's
                # bytes there took a third of that time), and the finish
                # runs warm (see ScanAssembler.rehearse), once the loop's top
                # has pushed what was parsed.
                self._parse_held()
                rehearse = True
                continue
            try:
                async with asyncio.timeout(self.timeout):
                    chunk = await source.read(due=due, expect=self._expected_bytes())
            except (DeviceError, TimeoutError) as exc:
                if self.closed:
                    return  # close() ended the read: not a failure to recover from
                reason = exc.reason if isinstance(exc, DeviceError) else f"no data for {self.timeout:g} s"
                self.last_error = str(exc) if isinstance(exc, DeviceError) else reason
                if not self.reopen:
                    await self.close()
                    if isinstance(exc, DeviceError):
                        raise
                    raise DeviceError(f"no data for {self.timeout:g} s", device=self.port) from None
                await source.close()
                self.state = "reconnecting"
                self._event("lost", f"{self.port}: device lost ({reason}); reopening")
                continue
            if not chunk:
                # The end of a capture: what is held is all there will be.
                self._parse_held()
                while self._pending:
                    rows, read_at = self._pending.pop(0)
                    for scan in assembler.push_rows(rows, host_time=read_at):
                        yield scan
                await self.close()
                return
            self.bytes_read += len(chunk)
            now = time.monotonic()
            if now - self._last_packet > self.stall:
                self.stalls += 1
                gap = now - self._last_packet
                self._event("stalled", f"{self.port}: no data for {gap:.2f} s (stalled); streaming again")
                self._parse_held()  # what came before the stall was read before it
            self._last_packet = now
            # Bytes short of completing the revolution wait for the rest:
            # parsing twice per revolution (what came before it was due, then
            # its last bytes) costs a fraction of once per burst.
            self._held += chunk
            self._held_time = self._clock()
            if not self._expected_bytes() or len(self._held) >= _HOLD_MAX:
                self._parse_held()

    def _parse_held(self) -> None:
        held, self._held = self._held, b""
        if held:
            rows = self.parser.feed_rows(held)
            if len(rows):
                self._pending.append((rows, self._held_time))
                self.packet_time = time.monotonic()

    def _event(self, kind: EventKind, message: str) -> None:
        if self._on_event is not None:
            self._on_event(kind, message)

    def _clock_jumped(self) -> None:
        clock = self.assembler.clock
        jumps, self._jumps = clock.jumps - self._jumps, clock.jumps
        if clock.last_jump is not None:
            before, after = clock.last_jump
            times = "" if jumps == 1 else f" ({jumps} jumps)"
            self._event(
                "clock_jump",
                f"{self.port}: the device clock jumped from {before} to {after} ms{times}; "
                "stamps re-anchored on the rotation",
            )

    def _read_due(self) -> float | None:
        """Event-loop time at which the current revolution's last packet can be read."""
        due = self.assembler.due
        if due is None or self.poll_interval is None:
            return None
        return asyncio.get_running_loop().time() + (due - self._clock())

    def _next_read_ends_turn(self, due: float) -> bool:
        """Whether the next read waits for the revolution's last packet (a polled
        source reads at most a poll interval before it is due, then on its bytes)."""
        assert self.poll_interval is not None
        return due - asyncio.get_running_loop().time() <= self.poll_interval

    def _expected_bytes(self) -> int:
        """Bytes that complete the current revolution (less what is held), or 0."""
        return max(self.assembler.due_packets * PACKET_SIZE - self.parser.pending - len(self._held), 0)

    async def _reconnect(self) -> None:
        self._held = b""
        self._pending.clear()
        self.parser.reset()
        self.assembler.reset()
        interval = self.reopen_interval
        lost = time.monotonic()
        attempts = 0
        while self.state == "reconnecting":
            await asyncio.sleep(interval)
            attempts += 1
            try:
                await self._connect()
            except DeviceError as exc:
                if isinstance(exc, DeviceRefused) and str(exc) != self.last_error:
                    self._event("refused", f"{self.port}: not reopened: {exc.reason}")
                self.last_error = str(exc)
                if self.reopen_max_interval is not None:
                    interval = min(interval * 2, max(self.reopen_max_interval, self.reopen_interval))
                continue
            self.reopens += 1
            self.state = "open"
            self.last_error = None
            self._event(
                "reconnected",
                f"{self.port}: reconnected after {time.monotonic() - lost:.1f} s ({attempts} attempt(s))",
            )

    async def close(self) -> None:
        """Close the port; safe to call twice."""
        self.state = "closed"
        source, self._source = self._source, None
        if source is not None:
            await source.close()
