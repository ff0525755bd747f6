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


class Lidar:
    """One LD-series LiDAR.

    :param port: device path, pyserial URL, or ``file://capture.bin``.
    :param model: a :class:`Model` or its name; sets the default baud rate.
    :param baudrate: overrides the model's baud rate.
    :param timeout: seconds without a valid packet before the device counts
        as failed (``comm.timeout_msec`` in the community driver).
    :param reopen: after a failure, keep trying to reopen the port instead
        of raising.
    :param reopen_interval: seconds between reopen attempts.
    :param clock: the host clock scans are stamped with (seconds).
    :param bins, direction, range_min, range_max, crop: see :class:`ScanAssembler`.
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
        timeout: float = 1.0,
        reopen: bool = True,
        reopen_interval: float = 0.5,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.port = port
        self.model = get_model(model) if isinstance(model, str) else model
        self.baudrate = baudrate if baudrate is not None else self.model.baudrate
        self.timeout = timeout
        self.reopen = reopen
        self.reopen_interval = reopen_interval
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
        except DeviceError:
            self.state = "closed"
            raise
        self.state = "open"

    async def _connect(self) -> None:
        source = open_source(self.port, baudrate=self.baudrate)
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
        except DeviceError:
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
                    chunk = await source.read()
            except (DeviceError, TimeoutError) as exc:
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

    async def _reconnect(self) -> None:
        self.parser.reset()
        self.assembler.reset()
        while self.state == "reconnecting":
            await asyncio.sleep(self.reopen_interval)
            try:
                await self._connect()
            except DeviceError:
                continue
            self.reopens += 1
            self.state = "open"

    async def close(self) -> None:
        """Close the port; safe to call twice."""
        self.state = "closed"
        source, self._source = self._source, None
        if source is not None:
            await source.close()
