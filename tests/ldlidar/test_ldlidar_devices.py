"""The emulator, the byte sources and the Lidar facade, over real pseudo-terminals."""

from __future__ import annotations

import asyncio
import math
import os
import re
import time
import tty
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from ldlidar import (
    DeviceError,
    DeviceRefused,
    Emulator,
    Lidar,
    LidarError,
    Replayer,
    ReplaySource,
    SerialSource,
    StreamParser,
    decode_bytes,
    open_source,
)
from ldlidar._cli import main
from ldlidar._protocol import POINTS_PER_PACKET

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


@pytest.mark.parametrize("batch", [7, 188])
def test_emulator_wakes_for_the_packets_that_end_a_revolution_by_the_decoders_rule(batch: int) -> None:
    # The emulator writes a revolution's end as soon as it is due (not on
    # its next tick): it must find the same ends as the decoder, across the
    # batches it makes packets in (a wrap between two batches included).
    emu = Emulator(scan_hz=9.3)  # revolutions that start anywhere in a batch
    while emu.generator.count < 3000:
        emu._generate(batch)
    starts = decode_bytes(emu._pending).wraps() // POINTS_PER_PACKET
    assert len(starts) > 60
    assert list(emu._turn_ends) == starts.tolist()


@pytest.mark.parametrize("scan_hz", [10.0, 9.3, 4.0])
def test_emulator_writes_at_most_a_tick_apart_and_on_every_revolutions_end(scan_hz: float) -> None:
    # The writer's schedule, driven as its thread drives it but without
    # sleeping: each write hands out what is due, then asks for the next time.
    emu = Emulator(scan_hz=scan_hz, tick=0.035)
    wakes, ends = [0.0], set()
    while wakes[-1] < 20.0:
        emu._due(wakes[-1])
        end = emu._next_end()
        if end is not None:
            ends.add(round(end, 9))
        wakes.append(emu._next_wake(wakes[-1]))
    steps = [b - a for a, b in pairwise(wakes)]
    assert max(steps) <= 0.035 + 1e-9
    # Each revolution's end (the packet after its last one) is written the moment it is due.
    written = {round(w, 9) for w in wakes}
    assert sorted(ends)[:-1] and set(sorted(ends)[:-1]) <= written
    # Evenly cut: no more writes than a tick's spacing needs (3 per LD06 revolution at 10 Hz).
    per_turn = math.ceil(1 / scan_hz / 0.035)
    assert len(wakes) / 20.0 <= scan_hz * per_turn * 1.02


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
async def test_replay_follows_the_devices_own_clock(capture: Path) -> None:
    """Paced by the capture's timestamps (2.275 s of device time), not the line rate (1.76 s)."""
    source = ReplaySource(capture, rate=4.0)
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(LIMIT):
        await source.open()
        begin = loop.time()
        data = b""
        while chunk := await source.read():
            data += chunk
        elapsed = loop.time() - begin
    assert data == capture.read_bytes()
    assert elapsed == pytest.approx(2.275 / 4, abs=0.05)


@pytest.mark.asyncio
async def test_replayer_plays_a_capture_on_a_pty_at_the_devices_pace(capture: Path) -> None:
    """``python -m ldlidar replay capture.bin --rate 4``: for any driver, at 4x the capture's own pace.

    The replay starts with the pty, and opening the port flushes what is
    already there (pyserial, as every serial driver), so the reader gets the
    capture from where it came in: a tail of it, byte for byte, paced by the
    device clock from that point on.
    """
    from ldlidar._sources import replay_schedule

    whole = capture.read_bytes()
    ends, times, duration = replay_schedule(whole)
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(LIMIT), Replayer(capture, rate=4.0) as player:
        source = SerialSource(player.link, baudrate=230400)
        await source.open()
        parser = StreamParser()
        received = bytearray()
        try:
            while not parser.feed(chunk := await source.read()):
                received += chunk
            received += chunk
            begin = loop.time()
            await player.finished.wait()
            elapsed = loop.time() - begin
            while not received.endswith(whole[ends[-2] :]):
                parser.feed(chunk := await source.read())
                received += chunk
        finally:
            await source.close()
    came_in = len(whole) - len(received)
    first = next(k for k, end in enumerate(ends) if end > came_in)
    assert whole.endswith(received) and first < len(ends) // 2, f"came in at byte {came_in}"
    assert parser.stats.crc_errors == 0 and parser.stats.packets >= len(ends) - first - 1
    assert elapsed == pytest.approx((duration - times[first]) / 4, abs=0.06)
    assert main(["replay", str(capture), "--rate", "0"]) == 2


@pytest.mark.asyncio
async def test_file_url_options(tmp_path: Path) -> None:
    replay = open_source("file:///tmp/capture.bin?rate=2.5&loop=1", baudrate=230400)
    assert isinstance(replay, ReplaySource) and replay.rate == 2.5 and replay.device == "/tmp/capture.bin"
    assert isinstance(open_source("/dev/ttyUSB0", baudrate=921600), SerialSource)
    for bad in ("file:///x.bin?speed=2", "file:///x.bin?rate=fast", "file:///x.bin?rate=0"):
        with pytest.raises(DeviceError, match="bad replay URL"):
            open_source(bad, baudrate=230400)
    with pytest.raises(DeviceError, match="cannot read"):
        await open_source(f"file://{tmp_path}/nope.bin", baudrate=230400).open()
    # Outside the directories the device policy names: refused, exists or not.
    with pytest.raises(DeviceRefused, match="replays are allowed only of files under"):
        await open_source("file:///nope.bin", baudrate=230400).open()


def spliced_capture(capture: Path, tmp_path: Path) -> Path:
    """The real capture with 40 packets cut out (a gap) and the device clock set back 5.7 s after it."""
    from ldlidar import decode_bytes
    from ldlidar._bulk import crc_rows

    data = capture.read_bytes()
    decoded = decode_bytes(data)
    rows = np.frombuffer(data, dtype=np.uint8)[decoded.offsets[:, None] + np.arange(47)].copy()
    rows = np.concatenate((rows[:300], rows[340:]))
    stamps = rows[:, 44].astype(np.int64) | rows[:, 45].astype(np.int64) << 8
    stamps[500:] = (stamps[500:] - 5717) % 30000
    rows[:, 44], rows[:, 45] = stamps & 0xFF, stamps >> 8
    rows[:, 46] = crc_rows(rows)
    path = tmp_path / "spliced.bin"
    path.write_bytes(rows.tobytes())
    return path


# Replays seconds of a real capture at the device's pace.
@pytest.mark.slow
@pytest.mark.asyncio
@pytest.mark.parametrize("rate", [1.0, 3.0])
async def test_replayed_scans_keep_pace_across_gaps_and_clock_jumps(capture: Path, tmp_path: Path, rate: float) -> None:
    """Issue 14: at line rate stamps stepped 77 ms for a scan_time of 100 ms, and went back at gaps."""
    path = spliced_capture(capture, tmp_path)
    scans = []
    arrived = []
    async with asyncio.timeout(LIMIT), Lidar(f"file://{path}?rate={rate:g}", bins=455) as lidar:
        async for scan in lidar.scans():
            scans.append(scan)
            arrived.append(time.time())
    # Both a gap of over a turn and the clock set back are jumps: the rotation, not the stamps, tells the time.
    assert len(scans) >= 19 and lidar.assembler.clock.jumps == 2
    stamps = np.array([s.stamp for s in scans])
    steps = np.diff(stamps)
    assert np.all(steps > 0)
    # One revolution a step, in host seconds, as scan_time says; the gap is a whole turn or two.
    periods = np.array([s.scan_time for s in scans])
    assert periods == pytest.approx(0.1 / rate, rel=0.02)
    ordinary = steps[steps < 1.5 * periods[1:]]
    assert len(ordinary) >= len(steps) - 2
    assert ordinary == pytest.approx(periods[1 : len(ordinary) + 1], rel=0.05)
    assert np.all(np.array(arrived) - stamps < 0.1 / rate + 0.05)  # published right after each turn


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
            with pytest.raises(DeviceError, match=r"silent: not one byte within 0\.3 s"):
                await lidar.open()
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.asyncio
async def test_lidar_open_tells_garbage_from_silence() -> None:
    """Bytes that never form a packet (a wrong baud rate looks like this) get their own error."""
    master, slave = os.openpty()
    tty.setraw(slave)
    noise = np.random.default_rng(5).integers(0, 256, 3000, dtype=np.uint8).tobytes()

    async def babble() -> None:
        for i in range(0, len(noise), 100):
            os.write(master, noise[i : i + 100])
            await asyncio.sleep(0.01)

    try:
        lidar = Lidar(os.ttyname(slave), timeout=0.3)
        async with asyncio.timeout(LIMIT):
            writer = asyncio.ensure_future(babble())
            with pytest.raises(DeviceError, match=r"\d+ bytes within 0\.3 s but no valid packet") as info:
                await lidar.open()
            await writer
        assert "wrong baud rate" in str(info.value) and "silent" not in str(info.value)
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.asyncio
async def test_lidar_reopens_after_unplug() -> None:
    events: list[tuple[str, str]] = []
    async with asyncio.timeout(LIMIT), Emulator() as emu:
        lidar = Lidar(emu.link, timeout=0.5, reopen_interval=0.05, on_event=lambda *e: events.append(e))
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
        recovered = lidar.last_error
        await lidar.close()
    assert lidar.reopens == 1
    assert lidar.state == "closed"
    assert recovered is None  # recovery clears the last error
    kinds = [kind for kind, _ in events]
    assert kinds == ["lost", "reconnected"], events
    assert "device lost (port failed" in events[0][1]
    assert re.search(r"reconnected after 0\.\d s \(\d+ attempt\(s\)\)", events[1][1])


# A stall of 0.4 s, and the scans around it.
@pytest.mark.slow
@pytest.mark.asyncio
@pytest.mark.parametrize("poll", [0.02, None], ids=["polled", "on-arrival"])
async def test_a_short_stall_is_reported_with_its_length(poll: float | None) -> None:
    """No data for 0.4 s (less than the 1 s timeout): not lost, but never quiet."""
    events: list[tuple[str, str]] = []
    async with (
        asyncio.timeout(LIMIT),
        Emulator() as emu,
        Lidar(emu.link, poll_interval=poll, on_event=lambda *e: events.append(e)) as lidar,
    ):
        scans = 0
        async for _ in lidar.scans():
            scans += 1
            if scans == 3:
                emu.pause()
                asyncio.get_running_loop().call_later(0.4, emu.resume)
            if scans == 8:
                break
    assert [kind for kind, _ in events] == ["stalled"], events
    seconds = float(re.search(r"no data for (\d\.\d+) s", events[0][1]).group(1))  # type: ignore[union-attr]
    assert 0.35 <= seconds < 0.6
    assert lidar.stalls == 1 and lidar.reopens == 0


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


# Waits out the reopen back-off.
@pytest.mark.slow
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
    assert lidar.last_error is None  # recovered


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
async def test_polled_source_hands_over_what_came_by_the_due_time_then_waits_for_the_rest() -> None:
    """The caller digests the bulk of a revolution while its last bytes are on their way."""
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        async with (
            asyncio.timeout(LIMIT),
            SerialSource(os.ttyname(slave), baudrate=230400, poll_interval=2.0) as source,
        ):
            loop = asyncio.get_running_loop()
            os.write(master, b"a" * 10)
            assert await source.read() == b"a" * 10
            os.write(master, b"b" * 100)
            # Due before the next poll, 1,000 bytes expected: what is there
            # comes back at the due time, not once the rest came (or 2 s passed).
            async with asyncio.timeout(1.0):
                assert await source.read(due=loop.time() + 0.01, expect=1000) == b"b" * 100
            # Past due: woken by the rest as it arrives.
            async with asyncio.timeout(1.0):
                pending = asyncio.ensure_future(source.read(due=loop.time() - 0.001, expect=900))
                os.write(master, b"c" * 900)
                assert await pending == b"c" * 900
    finally:
        os.close(master)
        os.close(slave)


# Seconds of revolutions at the device's pace.
@pytest.mark.slow
@pytest.mark.asyncio
async def test_polled_lidar_yields_each_revolution_soon_after_it_completes() -> None:
    """Polling every 30 ms, a turn still comes out within a few ms of its last packet."""
    async with asyncio.timeout(LIMIT), Emulator() as emu, Lidar(emu.link, poll_interval=0.03) as lidar:
        delays: list[float] = []
        async for scan in lidar.scans():
            # Upright, ray 0 is the turn's last measured: its end.
            delays.append(time.time() - scan.stamp)
            if len(delays) == 25:
                break
    delays = sorted(delays[5:])  # the clock mapping settles over the first turns
    assert delays[len(delays) // 2] < 0.012, delays  # polling alone: about 15 ms + the emulator's 5 ms
