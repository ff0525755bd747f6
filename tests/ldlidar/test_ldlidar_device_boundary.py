"""The LiDAR opens through the device policy every time: at configure, and at every reopen.

Real pseudo-terminals (the emulator's), real symlinks, files and named pipes;
what was opened is watched (:class:`OpenWatch`), not assumed.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from container import AsyncioExecutor
from container.devices import DevicePolicy, set_device_policy
from ldlidar import DeviceRefused, Emulator, Lidar, Scan, SerialSource
from ldlidar.plugin import LdLidarNode
from tests.device_support import OpenWatch
from tests.lifecycle_support import run
from tests.waiting import wait_until_async

LIMIT = 20.0  # seconds any one test may take


def repoint(link: Path, target: str | os.PathLike[str]) -> None:
    """``ln -sfn target link``, atomically."""
    new = link.with_name(link.name + ".new")
    with contextlib.suppress(FileNotFoundError):
        new.unlink()
    new.symlink_to(target)
    os.replace(new, link)


async def consume(scans: AsyncIterator[Scan], into: list[Scan]) -> None:
    async for scan in scans:
        into.append(scan)


@pytest.fixture
def default_policy() -> Iterator[DevicePolicy]:
    """The default device policy (no pseudo-terminal), instead of the tests' one."""
    policy = DevicePolicy()
    previous = set_device_policy(policy)
    yield policy
    set_device_policy(previous)


@pytest.mark.asyncio
async def test_a_link_repointed_while_the_device_is_away_is_refused_at_every_reopen(tmp_path: Path) -> None:
    """What the reconnect loop opened before: ``/etc/shadow``, a named pipe, ``/dev/zero``."""
    secret = tmp_path / "shadow"
    secret.write_text("root:$y$not-for-peers:\n")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    link = tmp_path / "ldlidar"
    events: list[tuple[str, str]] = []
    scans: list[Scan] = []

    def refused(words: str) -> Callable[[], bool]:
        return lambda: any(kind == "refused" and words in message for kind, message in events)

    async with asyncio.timeout(LIMIT), Emulator() as emu:
        link.symlink_to(emu.port)
        # The operator names this one link, explicitly: its pty is admitted through it.
        policy = DevicePolicy(serial=(str(link),), origin="the test's device policy")
        lidar = Lidar(
            str(link), timeout=0.5, reopen_interval=0.02, policy=policy, on_event=lambda *e: events.append(e)
        )
        await lidar.open()
        reader = asyncio.ensure_future(consume(lidar.scans(), scans))
        try:
            await wait_until_async(lambda: scans, "a first scan")
            targets = {
                secret: "a regular file",
                fifo: "a named pipe",
                Path("/dev/zero"): "not a terminal, never opened",
            }
            with OpenWatch() as watch:
                await emu.unplug()
                await wait_until_async(lambda: lidar.state == "reconnecting", "the device lost")
                for target, words in targets.items():
                    repoint(link, target)
                    await wait_until_async(refused(words), f"the reopen of {target} refused")
                    assert lidar.state == "reconnecting" and lidar.last_error is not None
                    assert words in lidar.last_error
            assert watch.opens_of(*map(str, targets)) == []
            assert watch.left_open_on(*map(str, targets)) == []
            # Once per reason: the loop retries every 20 ms without saying it again.
            assert sum(kind == "refused" for kind, _ in events) == len(targets)
            await emu.replug()
            repoint(link, emu.port)
            count = len(scans)
            await wait_until_async(lambda: lidar.state == "open" and len(scans) > count + 2, "scans again")
            assert any(kind == "reconnected" for kind, _ in events)
        finally:
            await lidar.close()
            await asyncio.wait([reader])


@pytest.mark.asyncio
async def test_a_source_refused_opens_nothing_and_says_why(tmp_path: Path) -> None:
    master, slave = os.openpty()
    pts = os.ttyname(slave)
    os.close(slave)
    try:
        for policy, words in (
            (DevicePolicy(), "not a serial device the default device policy allows"),
            (DevicePolicy(serial=("/dev/*",)), "a pseudo-terminal: opened only where"),
        ):
            source = SerialSource(pts, baudrate=230400, policy=policy)
            with OpenWatch() as watch, pytest.raises(DeviceRefused) as info:
                await source.open()
            assert words in str(info.value) and info.value.device == pts
            assert source.state == "closed"
            assert watch.opens_of(pts) == [] and watch.left_open_on(pts) == []
    finally:
        os.close(master)


def test_the_node_admits_its_own_emulator_and_no_other_pseudo_terminal(
    executor: AsyncioExecutor, host: Callable[..., Any], default_policy: DevicePolicy
) -> None:
    """``comm.serial_port: auto`` with no LiDAR attached runs on the default policy; a peer may not name that pty."""
    from tests.ldlidar.node_support import lidar_parameters

    class Unplugged(LdLidarNode):
        auto_port_patterns = ()  # no LiDAR attached, whatever this machine has

    async def scenario() -> None:
        own: LdLidarNode = host(Unplugged, "own", parameter_overrides=lidar_parameters("auto"))
        assert await own.transition("configure")
        emulator = own.emulator
        assert emulator is not None and own.lidar is not None and own.lidar.state == "open"
        for index, port in enumerate((emulator.port, emulator.link)):
            other: LdLidarNode = host(LdLidarNode, f"other{index}", parameter_overrides=lidar_parameters(port))
            with OpenWatch() as watch:
                assert not await other.transition("configure")
            assert other.lidar is None and other.emulator is None
            assert watch.opens_of(emulator.port) == []
        assert await own.transition("cleanup")

    run(executor, scenario(), timeout=LIMIT)
