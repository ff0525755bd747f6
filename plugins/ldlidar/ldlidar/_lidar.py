"""A LiDAR as an async stream of scans: source + parser + assembler, and reopen.

The community driver exits when the port cannot open and never reopens after
a USB adapter is pulled. Here :meth:`Lidar.open` raises :class:`DeviceError`
(so a configure transition can fail cleanly), and :meth:`Lidar.scans` keeps
reopening the same path (a udev or emulator symlink) until it comes back.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable
from typing import Literal

from ._errors import DeviceError
from ._parser import ParserStats, StreamParser
from ._protocol import Model, Packet, get_model
from ._scan import Direction, Scan, ScanAssembler
from ._sources import ReplaySource, SerialSource, open_source

__all__ = ["Lidar"]

#: Seconds past the predicted arrival of a revolution's last packet to read
#: it: the clock mapping is the quickest arrival seen, most come a bit later.
_DUE_MARGIN = 0.001


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
    :param bins, direction, range_min, range_max, crop: see :class:`ScanAssembler`.
    :ivar state: ``unopened``, ``open``, ``reconnecting`` (the port failed and
        is being reopened) or ``closed``.
    :ivar reopens: successful reopens since :meth:`open`.
    :ivar last_error: why the device last failed or a reopen attempt last
        failed; ``None`` until something did.
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
        poll_interval: float | None = None,
        timeout: float = 1.0,
        reopen: bool = True,
        reopen_interval: float = 0.5,
        reopen_max_interval: float | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.port = port
        self.model = get_model(model) if isinstance(model, str) else model
        self.baudrate = baudrate if baudrate is not None else self.model.baudrate
        self.poll_interval = poll_interval
        self.timeout = timeout
        self.reopen = reopen
        self.reopen_interval = reopen_interval
        self.reopen_max_interval = reopen_max_interval
        self._clock = clock
        self.parser = StreamParser()
        self.assembler = ScanAssembler(
            bins=bins, direction=direction, range_min=range_min, range_max=range_max, crop=crop
        )
        self._source: SerialSource | ReplaySource | None = None
        self._pending: list[Packet] = []
        self._pending_time = 0.0
        self.state: Literal["unopened", "open", "reconnecting", "closed"] = "unopened"
        self.reopens = 0
        self.last_error: str | None = None

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
        source = open_source(self.port, baudrate=self.baudrate, poll_interval=self.poll_interval)
        await source.open()
        self._source = source
        try:
            async with asyncio.timeout(self.timeout):
                while not self._pending:
                    chunk = await source.read()
                    if not chunk:
                        raise DeviceError("capture holds no valid packet", device=self.port)
                    self._pending_time = self._clock()
                    self._pending = self.parser.feed(chunk)
        except TimeoutError:
            await source.close()
            raise DeviceError(
                f"no valid packet within {self.timeout:g} s at {self.baudrate} baud "
                f"(wrong baud rate or model?)",
                device=self.port,
            ) from None
        except BaseException:
            # A bad capture, or cancelled (a transition timed out): never
            # leave the port open behind the caller's back.
            await source.close()
            raise

    async def scans(self) -> AsyncIterator[Scan]:
        """Yield scans until :meth:`close`, reopening the port after failures.

        :raises DeviceError: the device failed and :attr:`reopen` is off.
        """
        if self.state == "unopened":
            raise DeviceError("cannot read scans: lidar is not open", device=self.port)
        while self.state in ("open", "reconnecting"):
            for packet in self._pending:
                for scan in self.assembler.push(packet, host_time=self._pending_time):
                    yield scan
            self._pending = []
            if self.state == "reconnecting":
                await self._reconnect()
                continue
            source = self._source
            assert source is not None
            try:
                async with asyncio.timeout(self.timeout):
                    chunk = await source.read(due=self._read_due())
            except (DeviceError, TimeoutError) as exc:
                if self.closed:
                    return  # close() ended the read: not a failure to recover from
                self.last_error = str(exc) if isinstance(exc, DeviceError) else f"no data for {self.timeout:g} s"
                if not self.reopen:
                    await self.close()
                    if isinstance(exc, DeviceError):
                        raise
                    raise DeviceError(f"no data for {self.timeout:g} s", device=self.port) from None
                await source.close()
                self.state = "reconnecting"
                continue
            if not chunk:
                await self.close()
                return
            self._pending_time = self._clock()
            self._pending = self.parser.feed(chunk)

    def _read_due(self) -> float | None:
        """Event-loop time at which the current revolution's last packet can be read."""
        due = self.assembler.due
        if due is None or self.poll_interval is None:
            return None
        return asyncio.get_running_loop().time() + (due - self._clock()) + _DUE_MARGIN

    async def _reconnect(self) -> None:
        self.parser.reset()
        self.assembler.reset()
        interval = self.reopen_interval
        while self.state == "reconnecting":
            await asyncio.sleep(interval)
            try:
                await self._connect()
            except DeviceError as exc:
                self.last_error = str(exc)
                if self.reopen_max_interval is not None:
                    interval = min(interval * 2, max(self.reopen_max_interval, self.reopen_interval))
                continue
            self.reopens += 1
            self.state = "open"

    async def close(self) -> None:
        """Close the port; safe to call twice."""
        self.state = "closed"
        source, self._source = self._source, None
        if source is not None:
            await source.close()
