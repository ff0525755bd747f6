"""Where bytes come from: a serial port, or a capture replayed at line rate.

Both are async byte-chunk sources with the same small surface (:class:`Source`)
and an explicit state: ``unopened`` → ``open`` → ``closed``; a closed source
is not reopened, a new one is made (the port may be a different device by
then). Serial and OS errors are translated into :class:`DeviceError` here,
at the boundary, chained to the original.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from abc import ABC, abstractmethod
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol, Self
from urllib.parse import unquote, urlsplit

from ._errors import DeviceError

if TYPE_CHECKING:
    from types import TracebackType

__all__ = ["RETRY_INTERVAL", "ReplaySource", "SerialSource", "Source", "open_source"]

#: Seconds between a polled source's reads while something is due but late.
RETRY_INTERVAL = 0.002

State = Literal["unopened", "open", "closed"]


class Source(Protocol):
    """An async source of byte chunks."""

    @property
    def device(self) -> str: ...

    @property
    def state(self) -> State: ...

    async def open(self) -> None: ...

    async def read(self, *, due: float | None = None) -> bytes:
        """Return the next chunk; ``b""`` only at the end of a finite source.

        :param due: event-loop time at which the caller expects bytes worth
            reading at once (a polled source reads then); a hint.
        """
        ...

    async def close(self) -> None: ...


class _Base(ABC):
    def __init__(self, device: str) -> None:
        self._device = device
        self._state: State = "unopened"

    @property
    def device(self) -> str:
        return self._device

    @property
    def state(self) -> State:
        return self._state

    def _require(self, state: State, action: str) -> None:
        if self._state != state:
            raise DeviceError(f"cannot {action}: source is {self._state}", device=self._device)

    @abstractmethod
    async def open(self) -> None: ...

    @abstractmethod
    async def read(self, *, due: float | None = None) -> bytes: ...

    @abstractmethod
    async def close(self) -> None: ...

    async def __aenter__(self) -> Self:
        await self.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()


class SerialSource(_Base):
    """A serial port, read as bytes arrive or polled at a fixed interval.

    Waking the event loop for every burst a USB adapter (or the emulator)
    delivers costs more than parsing the bytes: an LD06 sends 375 packets a
    second, often a packet or two at a time. Polling every *poll_interval*
    seconds reads the same bytes in a few large chunks, for a fraction of
    the CPU. A caller that knows when something important arrives (the
    packet completing a revolution) passes it as ``read(due=...)``: the
    source reads then too, and retries every :data:`RETRY_INTERVAL` until
    bytes come, so a revolution is not held back for a whole interval.
    Keep the interval well below the time the line discipline's 4 KiB
    buffer takes to fill between two reads (about 45 ms at 921600 baud).

    :param port: a device path (``/dev/ttyUSB0``, a pty, a symlink) or a
        pyserial URL such as ``socket://host:port``.
    :param baudrate: the line speed; the STL-27L needs 921600.
    :param read_size: the largest chunk returned by :meth:`read`.
    :param poll_interval: seconds between reads; ``None`` reads through
        pyserial-asyncio as soon as bytes arrive (lowest latency).
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int,
        read_size: int = 4096,
        poll_interval: float | None = None,
    ) -> None:
        super().__init__(port)
        if poll_interval is not None and poll_interval <= 0:
            raise ValueError(f"poll_interval must be positive or None, got {poll_interval}")
        self.baudrate = baudrate
        self.poll_interval = poll_interval
        self._read_size = read_size
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._serial: Any = None
        self._next_read = 0.0
        self._last_read = 0.0

    async def open(self) -> None:
        """Open the port at :attr:`baudrate`.

        :raises DeviceError: the port does not exist, is busy, or refuses
            the settings.
        """
        self._require("unopened", "open")
        import serial
        import serial_asyncio

        try:
            if self.poll_interval is None:
                self._reader, self._writer = await serial_asyncio.open_serial_connection(
                    url=self._device, baudrate=self.baudrate
                )
            else:
                # timeout=0: a read returns at once with whatever is there.
                self._serial = serial.serial_for_url(self._device, baudrate=self.baudrate, timeout=0)
        except (serial.SerialException, OSError, ValueError) as exc:
            self._state = "closed"
            raise DeviceError(f"cannot open at {self.baudrate} baud: {exc}", device=self._device) from exc
        self._next_read = self._last_read = asyncio.get_running_loop().time()
        self._state = "open"

    async def read(self, *, due: float | None = None) -> bytes:
        """Return the next chunk of bytes (waiting for them).

        :param due: see :meth:`Source.read`; only a polled source uses it.
        :raises DeviceError: the port vanished (unplugged adapter) or failed.
        """
        self._require("open", "read")
        if self.poll_interval is not None:
            return await self._poll(self.poll_interval, due)
        import serial

        assert self._reader is not None
        try:
            data = await self._reader.read(self._read_size)
        except (serial.SerialException, OSError) as exc:
            await self.close()
            raise DeviceError(f"port failed: {exc}", device=self._device) from exc
        if not data:
            await self.close()
            raise DeviceError("port closed (device unplugged?)", device=self._device)
        return data

    async def _poll(self, interval: float, due: float | None) -> bytes:
        import serial

        loop = asyncio.get_running_loop()
        while True:
            target = self._next_read
            if due is not None and due > loop.time() - interval:
                # Not stale: read when due, or soon after if that has passed.
                target = min(target, max(due, self._last_read + RETRY_INTERVAL))
            wait = target - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)
            if self._serial is None:
                raise DeviceError("cannot read: source is closed", device=self._device)
            now = loop.time()
            try:
                data: bytes = self._serial.read(self._read_size)
            except (serial.SerialException, OSError) as exc:
                # pyserial reports a vanished device as "readiness to read
                # but no data", a pty whose other side closed as EIO.
                await self.close()
                raise DeviceError(f"port failed: {exc}", device=self._device) from exc
            # A full chunk means more is waiting: read it without pausing.
            self._next_read = now if len(data) == self._read_size else now + interval
            self._last_read = now
            if data:
                return data

    async def close(self) -> None:
        """Close the port; safe to call in any state."""
        writer, self._writer, self._reader = self._writer, None, None
        port, self._serial = self._serial, None
        self._state = "closed"
        # The port is gone either way; a close error has nowhere useful to go.
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()
        if writer is not None:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()


class ReplaySource(_Base):
    """A capture file streamed at line rate, as a device would send it.

    :param path: the capture file.
    :param bytes_per_second: pacing; ``None`` streams as fast as read.
    :param chunk_size: bytes per chunk.
    :param loop: start over at the end instead of ending.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        bytes_per_second: float | None = None,
        chunk_size: int = 512,
        loop: bool = False,
    ) -> None:
        super().__init__(os.fspath(path))
        self.bytes_per_second = bytes_per_second
        self._chunk = chunk_size
        self._loop = loop
        self._data = b""
        self._pos = 0
        self._sent = 0
        self._begin = 0.0

    async def open(self) -> None:
        """Read the capture.

        :raises DeviceError: the file is missing or unreadable.
        """
        self._require("unopened", "open")
        try:
            self._data = Path(self._device).read_bytes()
        except OSError as exc:
            self._state = "closed"
            raise DeviceError(f"cannot read capture: {exc.strerror or exc}", device=self._device) from exc
        self._begin = asyncio.get_running_loop().time()
        self._state = "open"

    async def read(self, *, due: float | None = None) -> bytes:
        """Return the next chunk, waiting until the line would have delivered it."""
        self._require("open", "read")
        if self._pos >= len(self._data):
            if not self._loop or not self._data:
                return b""
            self._pos = 0
        chunk = self._data[self._pos : self._pos + self._chunk]
        self._pos += len(chunk)
        self._sent += len(chunk)
        if self.bytes_per_second:
            loop = asyncio.get_running_loop()
            delay = self._begin + self._sent / self.bytes_per_second - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
        return chunk

    async def close(self) -> None:
        self._state = "closed"
        self._data = b""


def open_source(
    url: str, *, baudrate: int, read_size: int = 4096, poll_interval: float | None = None
) -> SerialSource | ReplaySource:
    """Return an unopened source for *url*.

    ``file://path`` (or ``file:path``) replays a capture at the line rate of
    *baudrate* (10 bits a byte); anything else is a serial port or pyserial
    URL, read as :class:`SerialSource` with *poll_interval*.
    """
    parts = urlsplit(url)
    if parts.scheme == "file":
        path = unquote(parts.netloc + parts.path)
        return ReplaySource(path, bytes_per_second=baudrate / 10, chunk_size=min(read_size, max(baudrate // 1000, 16)))
    return SerialSource(url, baudrate=baudrate, read_size=read_size, poll_interval=poll_interval)
