"""Where bytes come from: a serial port, or a capture replayed at its device's pace.

Both are async byte-chunk sources with the same small surface (:class:`Source`)
and an explicit state: ``unopened`` → ``open`` → ``closed``; a closed source
is not reopened, a new one is made (the port may be a different device by
then). Every open goes through the container's device policy
(:mod:`container.devices`): a serial port is opened and checked by
:meth:`DevicePolicy.open_serial` and only then handed to pyserial, a capture
by :meth:`DevicePolicy.open_replay`. Serial and OS errors are translated
into :class:`DeviceError` here, at the boundary, chained to the original; a
refusal is a :class:`DeviceRefused`.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, Literal, Protocol, Self
from urllib.parse import parse_qs, unquote, urlsplit

import container
from container.devices import DevicePolicy, PortRefused, device_policy

from ._errors import DeviceError, DeviceRefused

if TYPE_CHECKING:
    from types import TracebackType

__all__ = ["RETRY_INTERVAL", "ReplaySource", "SerialSource", "Source", "open_source", "replay_schedule"]

#: Seconds between a polled source's reads while something is due but late,
#: on a port without a file descriptor to wait on.
RETRY_INTERVAL = 0.002

#: Bytes a polled source lets gather between two reads at most: three
#: quarters of the 4 KiB the kernel's line discipline buffers.
_LINE_BUFFER = 3072

#: Seconds opening a port or reading a capture may take: done on a thread,
#: so a port that blocks (a named pipe, a network URL) holds up only itself.
OPEN_TIMEOUT = 5.0

#: The StreamReader buffer limit serial_asyncio uses (asyncio's default).
_STREAM_LIMIT = 2**16

State = Literal["unopened", "open", "closed"]


class Source(Protocol):
    """An async source of byte chunks."""

    @property
    def device(self) -> str: ...

    @property
    def state(self) -> State: ...

    async def open(self) -> None: ...

    async def read(self, *, due: float | None = None, expect: int = 0) -> bytes:
        """Return the next chunk; ``b""`` only at the end of a finite source.

        :param due: event-loop time at which the caller expects bytes worth
            reading at once (a polled source reads then); a hint.
        :param expect: how many bytes make what is due complete; a polled
            source gathers that many (as they arrive) before returning.
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
    async def read(self, *, due: float | None = None, expect: int = 0) -> bytes: ...

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
    """A serial port, read as bytes arrive or polled.

    Waking the event loop for every burst a USB adapter (or the emulator)
    delivers costs more than parsing the bytes: an LD06 sends 375 packets a
    second, often a packet or two at a time. A polled source reads the same
    bytes in a few large chunks instead. A caller that knows when something
    important arrives (the packet completing a revolution) passes it as
    ``read(due=..., expect=...)``: the source sleeps until then, returns
    what has come by then (for the caller to digest while the rest is on its
    way), and from then on wakes as soon as bytes arrive, until *expect*
    bytes have come; so a revolution's last packets are read within a burst
    of arriving, with little left to parse. Whatever is due, it reads at least every :attr:`hold`
    seconds, well before the kernel's 4 KiB line buffer could fill; with
    nothing due it reads every *poll_interval*.

    :param port: a device path (``/dev/ttyUSB0``, a pty, a symlink) or a
        pyserial URL such as ``socket://host:port``.
    :param baudrate: the line speed; the STL-27L needs 921600.
    :param read_size: the largest chunk returned by :meth:`read`.
    :param poll_interval: seconds between reads while nothing is due;
        ``None`` reads through pyserial-asyncio as soon as bytes arrive
        (every burst wakes the loop).
    :param policy: what the port may name, decided at every open; the
        process's (:func:`container.devices.device_policy`) if not given.
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int,
        read_size: int = 4096,
        poll_interval: float | None = None,
        policy: DevicePolicy | None = None,
    ) -> None:
        super().__init__(port)
        self.policy = policy
        if poll_interval is not None and poll_interval <= 0:
            raise ValueError(f"poll_interval must be positive or None, got {poll_interval}")
        self.baudrate = baudrate
        self.poll_interval = poll_interval
        #: The longest wait between two reads: three quarters of the line
        #: buffer at full line rate (133 ms at 230400 baud, 33 ms at 921600).
        self.hold = max(poll_interval or 0.0, _LINE_BUFFER * 10 / baudrate)
        self._read_size = read_size
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._serial: Any = None
        self._fd: int | None = None
        self._last_read = 0.0
        self._last_gather = 0.0
        self._more = False

    async def open(self) -> None:
        """Open the port at :attr:`baudrate`, if the device policy admits what it names now.

        :raises DeviceRefused: the policy refuses it; nothing was opened,
            or what was opened was closed untouched.
        :raises DeviceError: the port does not exist, is busy, or refuses
            the settings.
        """
        self._require("unopened", "open")
        import serial
        import serial_asyncio

        loop = asyncio.get_running_loop()
        policy = self.policy if self.policy is not None else device_policy()
        # Off the event loop, and bounded: opening can block (a network URL
        # connecting, a device that does not answer its ioctls). Shielded:
        # a port the thread opens after the wait ended is closed, not leaked.
        opening = asyncio.ensure_future(asyncio.to_thread(_open_port, policy, self._device, self.baudrate))
        try:
            instance = await asyncio.wait_for(asyncio.shield(opening), OPEN_TIMEOUT)
        except BaseException as exc:
            self._state = "closed"
            if not opening.done():
                opening.add_done_callback(_close_late)
            if isinstance(exc, TimeoutError):
                raise DeviceError(f"opening took over {OPEN_TIMEOUT:g} s", device=self._device) from None
            if isinstance(exc, PortRefused):
                raise DeviceRefused(exc.reason, device=self._device) from exc
            if isinstance(exc, container.DeviceError):
                raise DeviceError(exc.reason, device=self._device) from exc
            if isinstance(exc, (serial.SerialException, OSError, ValueError)):
                raise DeviceError(f"cannot open at {self.baudrate} baud: {exc}", device=self._device) from exc
            raise
        if self.poll_interval is None:
            # What serial_asyncio.open_serial_connection builds, around the port opened above.
            reader = asyncio.StreamReader(limit=_STREAM_LIMIT, loop=loop)
            protocol = asyncio.StreamReaderProtocol(reader, loop=loop)
            transport = serial_asyncio.SerialTransport(loop, protocol, instance)
            self._reader, self._writer = reader, asyncio.StreamWriter(transport, protocol, reader, loop)
        else:
            self._serial = instance
            try:
                self._fd = self._serial.fileno()
            except (AttributeError, OSError, ValueError):
                self._fd = None  # a URL without a descriptor: retried instead of awaited
        self._last_read = self._last_gather = asyncio.get_running_loop().time()
        self._state = "open"

    async def read(self, *, due: float | None = None, expect: int = 0) -> bytes:
        """Return the next chunk of bytes (waiting for them).

        :param due, expect: see :meth:`Source.read`; only a polled source uses them.
        :raises DeviceError: the port vanished (unplugged adapter) or failed.
        """
        self._require("open", "read")
        if self.poll_interval is not None:
            return await self._poll(self.poll_interval, due, expect)
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

    async def _poll(self, interval: float, due: float | None, expect: int) -> bytes:
        loop = asyncio.get_running_loop()
        chunk = b""
        while True:
            now = loop.time()
            at_due = False
            if self._more:
                self._more = False  # the last read filled the chunk: more is waiting
            elif due is not None and due > now - self.hold:
                if due > now:
                    until = min(due, self._last_read + self.hold)
                    at_due = until == due
                    await asyncio.sleep(until - now)
                else:
                    # Due: the next bytes are the ones waited for.
                    await self._readable(min(self.hold, max(self._last_read + self.hold - now, 0.0)))
            else:
                wait = self._last_read + interval - now
                if wait > 0:
                    await asyncio.sleep(wait)
            try:
                chunk += self._read_now()
            except DeviceError:
                await self.close()
                raise
            now = loop.time()
            if not chunk:
                continue
            # The read at the due time returns what it got even if the
            # revolution is not complete yet: the caller digests that while
            # waiting for the rest, so less is left between the last byte
            # and the scan.
            if at_due or len(chunk) >= expect or due is None or due > now or now >= self._last_gather + self.hold:
                self._last_gather = now
                return chunk

    def _read_now(self) -> bytes:
        import serial

        if self._serial is None:
            raise DeviceError("cannot read: source is closed", device=self._device)
        self._last_read = asyncio.get_running_loop().time()
        try:
            data: bytes = self._serial.read(self._read_size)
        except (serial.SerialException, OSError) as exc:
            # pyserial reports a vanished device as "readiness to read
            # but no data", a pty whose other side closed as EIO.
            raise DeviceError(f"port failed: {exc}", device=self._device) from exc
        self._more = len(data) == self._read_size
        return data

    async def _readable(self, timeout: float) -> None:
        """Wait until the port has bytes to read, at most *timeout* seconds."""
        fd = self._fd
        loop = asyncio.get_running_loop()
        if fd is None:
            await asyncio.sleep(min(RETRY_INTERVAL, timeout))
            return
        ready = loop.create_future()

        def wake() -> None:
            if not ready.done():
                ready.set_result(None)

        loop.add_reader(fd, wake)
        timer = loop.call_later(timeout, wake)
        try:
            await ready
        finally:
            timer.cancel()
            loop.remove_reader(fd)

    async def close(self) -> None:
        """Close the port; safe to call in any state."""
        writer, self._writer, self._reader = self._writer, None, None
        port, self._serial, self._fd = self._serial, None, None
        self._state = "closed"
        # The port is gone either way; a close error has nowhere useful to go.
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()
        if writer is not None:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()


def _open_port(policy: DevicePolicy, port: str, baudrate: int) -> Any:
    """Open *port* as the policy allows and return the ``serial.Serial`` (on a worker thread).

    A device path is opened and checked by the policy, then handed to
    pyserial by descriptor; a pyserial URL (``socket://``) is checked, then
    opened by pyserial. Told apart as :meth:`DevicePolicy.check_port` tells
    them: whatever it takes for a path is opened as one.
    """
    import serial

    from ._pyserial import serial_on_descriptor

    if urlsplit(port).scheme and "://" in port:
        policy.check_port(port)
        return serial.serial_for_url(port, baudrate=baudrate, timeout=0)
    fd = policy.open_serial(port)
    try:
        return serial_on_descriptor(fd, baudrate=baudrate)
    finally:
        os.close(fd)


def _close_late(opening: asyncio.Future[Any]) -> None:
    """Close a port whose open finished after its caller stopped waiting."""
    if not opening.cancelled() and opening.exception() is None:
        with contextlib.suppress(Exception):
            opening.result().close()


class ReplaySource(_Base):
    """A capture file streamed at the pace its device sent it.

    Each data packet is released when the device's own clock says it was
    measured (its timestamps, unwrapped, with jumps of that clock replaced by
    the rotation's time as :meth:`DecodedStream.device_steps` does), scaled
    by *rate*; bytes between packets go with the packet after them. Replaying
    at the line rate instead would run a capture 1.31x fast (an LD06 fills
    only 76% of its line) and make stamps and ``scan_time`` disagree.

    :param path: the capture file.
    :param rate: 2.0 replays twice as fast, 0.5 at half speed; ``None``
        streams as fast as read.
    :param tick: packets due within this many seconds of each other go in
        one chunk, as a USB adapter delivers bursts.
    :param loop: start over at the end instead of ending.
    :param max_bytes: the largest capture read, below the policy's
        ``replay_max_bytes``; ``None``: the policy's.
    :param policy: where a capture may be and how big, decided at every
        open; the process's (:func:`container.devices.device_policy`) if not
        given.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        rate: float | None = 1.0,
        tick: float = 0.005,
        loop: bool = False,
        max_bytes: int | None = None,
        policy: DevicePolicy | None = None,
    ) -> None:
        super().__init__(os.fspath(path))
        self.policy = policy
        #: The largest capture read; ``None``: any size.
        self.max_bytes = max_bytes
        if rate is not None and not rate > 0:
            raise ValueError(f"rate must be positive or None, got {rate}")
        self.rate = rate
        self._tick = tick
        self._loop = loop
        self._data = b""
        self._ends: list[int] = []
        self._times: list[float] = []
        self._duration = 0.0
        self._pos = 0
        self._next = 0
        self._lap = 0
        self._begin = 0.0

    async def open(self) -> None:
        """Read the capture, if the device policy admits it now, and work out when each packet is due.

        :raises DeviceRefused: the policy refuses it (where it is, what it is, its size).
        :raises DeviceError: the file is missing or unreadable.
        """
        self._require("unopened", "open")
        policy = self.policy if self.policy is not None else device_policy()
        try:
            self._data = await asyncio.wait_for(
                asyncio.to_thread(_read_capture, policy, self._device, self.max_bytes), OPEN_TIMEOUT
            )
        except TimeoutError:
            self._state = "closed"
            raise DeviceError(f"reading the capture took over {OPEN_TIMEOUT:g} s", device=self._device) from None
        except PortRefused as exc:
            self._state = "closed"
            raise DeviceRefused(exc.reason, device=self._device) from exc
        except container.DeviceError as exc:
            self._state = "closed"
            raise DeviceError(exc.reason, device=self._device) from exc
        except OSError as exc:
            self._state = "closed"
            raise DeviceError(f"cannot read capture: {exc.strerror or exc}", device=self._device) from exc
        self._ends, self._times, self._duration = replay_schedule(self._data)
        self._begin = asyncio.get_running_loop().time()
        self._state = "open"

    async def read(self, *, due: float | None = None, expect: int = 0) -> bytes:
        """Return the next packets, waiting until the device would have sent them.

        :param expect: wait until the device would have sent this many bytes
            (one wake-up per revolution instead of one per burst).
        """
        self._require("open", "read")
        data, ends = self._data, self._ends
        if self._pos >= len(data):
            if not self._loop or not data:
                return b""
            self._pos = self._next = 0
            self._lap += 1
        if self.rate is None:
            chunk = data[self._pos :]
            self._pos = len(data)
            return chunk
        loop = asyncio.get_running_loop()
        offset = self._lap * self._duration
        last = self._next
        while last + 1 < len(ends) and ends[last] < self._pos + expect:
            last += 1
        target = self._begin + (self._times[last] + offset) / self.rate
        wait = target - loop.time()
        if wait > 0:
            await asyncio.sleep(wait)
        horizon = (loop.time() - self._begin + self._tick) * self.rate - offset
        while last + 1 < len(ends) and self._times[last + 1] <= horizon:
            last += 1
        chunk = data[self._pos : ends[last]]
        self._pos = ends[last]
        self._next = last + 1
        return chunk

    async def close(self) -> None:
        self._state = "closed"
        self._data = b""


def _read_capture(policy: DevicePolicy, path: str, max_bytes: int | None) -> bytes:
    """Read the capture at ``path``: a regular file the policy admits, of at most ``max_bytes``.

    Opened by the policy, without blocking, and checked on the open
    descriptor, so a named pipe or a device (``/dev/zero``) put there after
    any earlier check is refused before a single read, and never fills
    memory.
    """
    fd = policy.open_replay(path)
    try:
        info = os.fstat(fd)
        max_bytes = policy.replay_max_bytes if max_bytes is None else min(max_bytes, policy.replay_max_bytes)
        if info.st_size > max_bytes:
            raise OSError(errno.EFBIG, f"the capture is {info.st_size} bytes, over the {max_bytes} allowed")
        with os.fdopen(fd, "rb", closefd=True) as file:
            fd = -1
            data = file.read(max_bytes + 1)
    finally:
        if fd >= 0:
            os.close(fd)
    if len(data) > max_bytes:
        raise OSError(errno.EFBIG, f"the capture grew over the {max_bytes} bytes allowed")
    return data


def replay_schedule(data: bytes) -> tuple[list[int], list[float], float]:
    """Return where each packet of *data* ends, when it is due (s from the first) and the capture's length (s).

    Bytes before the first packet go with it and bytes after the last with
    it; a capture without packets is one chunk, due at once.
    """
    from ._bulk import decode_bytes
    from ._protocol import PACKET_SIZE

    decoded = decode_bytes(data)
    if not len(decoded):
        return [len(data)], [0.0], 0.0
    ends = (decoded.offsets + PACKET_SIZE).tolist()
    ends[-1] = len(data)
    steps = decoded.device_steps()
    times = [0.0, *(steps.cumsum() / 1000).tolist()]
    period = float(sorted(steps.tolist())[len(steps) // 2]) / 1000 if len(steps) else 0.0
    return ends, times, times[-1] + period


def open_source(
    url: str,
    *,
    baudrate: int,
    read_size: int = 4096,
    poll_interval: float | None = None,
    policy: DevicePolicy | None = None,
) -> SerialSource | ReplaySource:
    """Return an unopened source for *url*.

    ``file://path`` (or ``file:path``) replays a capture at the pace of the
    device's own timestamps; ``?rate=2`` replays it twice as fast, ``?loop=1``
    over and over. Anything else is a serial port or pyserial URL, read as
    :class:`SerialSource` with *poll_interval*. Either opens as *policy*
    allows (the process's device policy if not given).

    :raises DeviceError: a ``file:`` URL with a query it does not know.
    """
    parts = urlsplit(url)
    if parts.scheme == "file":
        path = unquote(parts.netloc + parts.path)
        options = parse_qs(parts.query, keep_blank_values=True)
        unknown = sorted(set(options) - {"rate", "loop"})
        try:
            if unknown:
                raise ValueError(f"unknown option(s) {', '.join(unknown)}; known: rate, loop")
            rate = float(options.get("rate", ["1"])[-1])
            looping = options.get("loop", ["0"])[-1] in ("1", "true", "yes")
            replay = ReplaySource(path, rate=rate, loop=looping, policy=policy)
        except ValueError as exc:
            raise DeviceError(f"bad replay URL: {exc}", device=url) from None
        return replay
    return SerialSource(url, baudrate=baudrate, read_size=read_size, poll_interval=poll_interval, policy=policy)
