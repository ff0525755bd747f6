"""The emulator, the byte sources and the Lidar facade, over real pseudo-terminals."""

from __future__ import annotations

import asyncio
import os
import time
from itertools import pairwise
from pathlib import Path

import pytest

from ldlidar import (
    DeviceError,
    Emulator,
    Lidar,
    LidarError,
    ReplaySource,
    SerialSource,
    StreamParser,
    open_source,
)

LIMIT = 10.0  # seconds any one test may take


async def count_packets(source: SerialSource, seconds: float) -> tuple[int, StreamParser]:
    """Packets that arrive in *seconds*, counted from the first one."""
    parser = StreamParser()
    loop = asyncio.get_running_loop()
    while not parser.feed(await source.read()):
        pass
    begin = loop.time()
    count = 0
    while loop.time() - begin < seconds:
        count += len(parser.feed(await source.read()))
    return count, parser


@pytest.mark.asyncio
@pytest.mark.parametrize(("model", "rate"), [("LD06", 375), ("STL27L", 1800)])
async def test_emulator_sends_real_packets_at_the_model_rate(model: str, rate: int) -> None:
    async with asyncio.timeout(LIMIT), Emulator(model=model) as emu:
        assert emu.port.startswith("/dev/pts/")
        assert os.path.realpath(emu.link) == emu.port
        source = SerialSource(emu.port, baudrate=emu.model.baudrate)
        await source.open()
        try:
            count, parser = await count_packets(source, 1.0)
        finally:
            await source.close()
    assert count == pytest.approx(rate, rel=0.15)
    assert parser.stats.crc_errors == 0


@pytest.mark.asyncio
async def test_emulator_clock_wraps_at_30000_ms() -> None:
    async with (
        asyncio.timeout(LIMIT),
        Emulator(start_ms=29_900) as emu,
        SerialSource(emu.link, baudrate=230400) as source,
    ):
        parser = StreamParser()
        stamps: list[int] = []
        while not (stamps and stamps[-1] < 1000):
            stamps += [p.timestamp for p in parser.feed(await source.read())]
    assert max(stamps) >= 29_900
    assert stamps[-1] < 1000


@pytest.mark.asyncio
async def test_injected_faults_reach_the_parser_and_cost_no_packets() -> None:
    async with asyncio.timeout(LIMIT), Emulator() as emu, SerialSource(emu.port, baudrate=230400) as source:
        parser = StreamParser()
        while not parser.feed(await source.read()):
            pass
        emu.inject_health(5)
        emu.inject_garbage(100, seed=1)
        emu.inject_health(6)
        while parser.stats.health_frames < 2:
            parser.feed(await source.read())
        before = parser.stats.packets
        await asyncio.sleep(0.2)  # let packets after the faults flow
        parser.feed(await source.read())
    assert parser.stats.last_health_code == 6
    assert parser.stats.skipped_bytes >= 100
    assert parser.stats.packets > before


@pytest.mark.asyncio
async def test_unplug_is_a_device_error_and_replug_keeps_the_link() -> None:
    async with asyncio.timeout(LIMIT), Emulator() as emu:
        link = emu.link
        source = SerialSource(link, baudrate=230400)
        await source.open()
        assert await source.read()
        await emu.unplug()
        assert not os.path.lexists(link)
        with pytest.raises(DeviceError) as info:
            while True:
                await source.read()
        assert info.value.device == link
        assert source.state == "closed"
        with pytest.raises(DeviceError, match="cannot open"):
            await SerialSource(link, baudrate=230400).open()
        await emu.replug()
        async with SerialSource(link, baudrate=230400) as again:
            assert await again.read()


@pytest.mark.asyncio
async def test_source_states_are_guarded() -> None:
    source = SerialSource("/dev/does-not-exist", baudrate=230400)
    with pytest.raises(DeviceError, match="unopened"):
        await source.read()
    with pytest.raises(DeviceError, match="cannot open") as info:
        await source.open()
    assert info.value.device == "/dev/does-not-exist"
    assert isinstance(info.value.__cause__, Exception)
    with pytest.raises(DeviceError, match="closed"):
        await source.open()


@pytest.mark.asyncio
async def test_emulator_states_are_guarded() -> None:
    emu = Emulator()
    with pytest.raises(LidarError):
        emu.port  # noqa: B018
    with pytest.raises(LidarError):
        await emu.unplug()
    async with asyncio.timeout(LIMIT):
        await emu.start()
        with pytest.raises(LidarError):
            await emu.start()
        with pytest.raises(LidarError):
            await emu.replug()
        await emu.stop()
        await emu.stop()
    assert emu.state == "closed"


@pytest.mark.asyncio
async def test_replay_streams_a_capture_at_line_rate(capture: Path) -> None:
    size = capture.stat().st_size
    source = ReplaySource(capture, bytes_per_second=size * 4, chunk_size=1000)  # a quarter second
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(LIMIT):
        await source.open()
        begin = loop.time()
        data = b""
        while chunk := await source.read():
            data += chunk
        elapsed = loop.time() - begin
    assert data == capture.read_bytes()
    assert elapsed >= 0.2


@pytest.mark.asyncio
async def test_file_url_opens_a_replay_at_the_baud_rate(capture: Path) -> None:
    source = open_source(f"file://{capture}", baudrate=230400)
    assert isinstance(source, ReplaySource)
    assert source.bytes_per_second == 23040
    assert isinstance(open_source("/dev/ttyUSB0", baudrate=921600), SerialSource)
    with pytest.raises(DeviceError, match="cannot read"):
        await open_source("file:///nope.bin", baudrate=230400).open()


@pytest.mark.asyncio
async def test_lidar_yields_scans_from_the_emulator() -> None:
    async with asyncio.timeout(LIMIT), Emulator() as emu, Lidar(emu.link, model="LD06", bins=455) as lidar:
        scans = []
        async for scan in lidar.scans():
            scans.append(scan)
            if len(scans) == 3:
                break
    assert all(len(s.ranges) == 455 for s in scans)
    assert scans[1].stamp - scans[0].stamp == pytest.approx(0.1, abs=0.01)
    assert all(s.scan_time == pytest.approx(0.1, abs=0.005) for s in scans)


@pytest.mark.asyncio
async def test_lidar_open_fails_cleanly_without_a_port() -> None:
    lidar = Lidar("/dev/does-not-exist", timeout=0.5)
    with pytest.raises(DeviceError):
        await lidar.open()
    assert lidar.state == "closed"


@pytest.mark.asyncio
async def test_lidar_open_times_out_on_a_silent_port() -> None:
    master, slave = os.openpty()
    try:
        lidar = Lidar(os.ttyname(slave), timeout=0.3)
        async with asyncio.timeout(LIMIT):
            with pytest.raises(DeviceError, match=r"no valid packet within 0\.3 s"):
                await lidar.open()
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.asyncio
async def test_lidar_reopens_after_unplug() -> None:
    async with asyncio.timeout(LIMIT), Emulator() as emu:
        lidar = Lidar(emu.link, timeout=0.5, reopen_interval=0.05)
        await lidar.open()
        scans = 0
        unplugged = False
        async for _ in lidar.scans():
            scans += 1
            if scans == 2 and not unplugged:
                await emu.unplug()
                unplugged = True
                asyncio.get_running_loop().call_later(0.3, lambda: asyncio.ensure_future(emu.replug()))
            if lidar.reopens and scans >= 4:
                break
        await lidar.close()
    assert lidar.reopens == 1
    assert lidar.state == "closed"


@pytest.mark.asyncio
async def test_lidar_without_reopen_raises_on_unplug() -> None:
    async with asyncio.timeout(LIMIT), Emulator() as emu:
        lidar = Lidar(emu.link, reopen=False)
        await lidar.open()
        with pytest.raises(DeviceError):
            async for _ in lidar.scans():
                await emu.unplug()
        assert lidar.state == "closed"


@pytest.mark.asyncio
async def test_close_during_a_read_ends_scans_without_reopening() -> None:
    async with asyncio.timeout(LIMIT), Emulator() as emu:
        lidar = Lidar(emu.link, reopen_interval=0.01)
        await lidar.open()
        scans = []

        async def consume() -> None:
            async for scan in lidar.scans():
                scans.append(scan)

        task = asyncio.ensure_future(consume())
        while not scans:
            await asyncio.sleep(0.01)
        await lidar.close()
        await asyncio.wait_for(task, 2.0)
    assert lidar.state == "closed"
    assert lidar.reopens == 0


@pytest.mark.asyncio
async def test_reopen_attempts_back_off_up_to_the_maximum(monkeypatch: pytest.MonkeyPatch) -> None:
    async with asyncio.timeout(LIMIT), Emulator() as emu:
        lidar = Lidar(emu.link, reopen_interval=0.05, reopen_max_interval=0.2)
        await lidar.open()
        loop = asyncio.get_running_loop()
        attempts: list[float] = []
        connect = lidar._connect

        async def counted() -> None:
            attempts.append(loop.time())
            await connect()

        async def replug_after_six_attempts() -> None:
            while len(attempts) < 6:
                await asyncio.sleep(0.01)
            await emu.replug()

        monkeypatch.setattr(lidar, "_connect", counted)
        await emu.unplug()
        replug = asyncio.ensure_future(replug_after_six_attempts())
        async for _ in lidar.scans():
            if lidar.reopens:
                break
        await lidar.close()
        await replug
    gaps = [b - a for a, b in pairwise(attempts)]
    assert len(attempts) >= 6
    for gap, least in zip(gaps[:5], [0.1, 0.2, 0.2, 0.2, 0.2], strict=True):
        assert gap >= least * 0.99, gaps
    assert lidar.last_error is not None


@pytest.mark.asyncio
async def test_polled_source_reads_everything_in_few_large_chunks() -> None:
    async with asyncio.timeout(LIMIT), Emulator() as emu:
        source = SerialSource(emu.port, baudrate=230400, poll_interval=0.05)
        await source.open()
        try:
            parser = StreamParser()
            while not parser.feed(await source.read()):
                pass
            loop = asyncio.get_running_loop()
            begin, reads, count = loop.time(), 0, 0
            while loop.time() - begin < 1.0:
                count += len(parser.feed(await source.read()))
                reads += 1
        finally:
            await source.close()
    assert count == pytest.approx(375, rel=0.15)
    assert 10 <= reads <= 22  # one read per 50 ms, not one per burst (about 180)
    assert parser.stats.crc_errors == 0


@pytest.mark.asyncio
async def test_polled_source_reports_an_unplug() -> None:
    async with asyncio.timeout(LIMIT), Emulator() as emu:
        source = SerialSource(emu.link, baudrate=230400, poll_interval=0.01)
        await source.open()
        assert await source.read()
        await emu.unplug()
        with pytest.raises(DeviceError, match="port failed") as info:
            while True:
                await source.read()
        assert info.value.device == emu.link
        assert source.state == "closed"
    with pytest.raises(ValueError):
        SerialSource("/dev/null", baudrate=230400, poll_interval=0)


@pytest.mark.asyncio
async def test_polled_source_reads_early_when_something_is_due() -> None:
    async with (
        asyncio.timeout(LIMIT),
        Emulator() as emu,
        SerialSource(emu.port, baudrate=230400, poll_interval=0.5) as source,
    ):
        loop = asyncio.get_running_loop()
        await source.read()
        begin = loop.time()
        assert await source.read(due=begin + 0.05)
        early = loop.time() - begin
        begin = loop.time()
        assert await source.read()
        regular = loop.time() - begin
    assert 0.04 <= early < 0.25
    assert regular >= 0.45


@pytest.mark.asyncio
async def test_polled_lidar_yields_each_revolution_soon_after_it_completes() -> None:
    """Polling every 30 ms, a turn still comes out within a few ms of its last packet."""
    async with asyncio.timeout(LIMIT), Emulator() as emu, Lidar(emu.link, poll_interval=0.03) as lidar:
        delays: list[float] = []
        async for scan in lidar.scans():
            # stamp + scan_time: the next turn's first ray, i.e. this one's end.
            delays.append(time.time() - (scan.stamp + scan.scan_time))
            if len(delays) == 25:
                break
    delays = sorted(delays[5:])  # the clock mapping settles over the first turns
    assert delays[len(delays) // 2] < 0.012, delays  # polling alone: about 15 ms + the emulator's 5 ms
