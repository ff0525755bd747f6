"""Memory freed by unloaded nodes is given back to the system (``container/_memory.py``)."""

from __future__ import annotations

import asyncio
import os
import re
from collections.abc import Callable
from pathlib import Path

import pytest
from rclpy.node import Node

from container import AsyncioExecutor
from container._memory import MemoryReturn, Trimmed, resident_bytes
from tests.component_support import ContainerClient
from tests.container_support import ContainerProcess

#: Seconds a test's burst of unloads settles for, instead of the container's second.
SETTLE = 0.05


class _Trim:
    """A stand-in for ``malloc_trim``: counts its calls; blocks while :attr:`hold` is clear."""

    def __init__(self) -> None:
        self.calls = 0
        self.hold = asyncio.Event()
        self.loop = asyncio.get_running_loop()

    def __call__(self) -> None:
        self.calls += 1
        asyncio.run_coroutine_threadsafe(self.hold.wait(), self.loop).result(5.0)


async def _until(condition: Callable[[], bool], what: str) -> None:
    async with asyncio.timeout(5.0):
        while not condition():
            await asyncio.sleep(0.01)


async def test_a_burst_of_unloads_is_trimmed_once_after_its_last() -> None:
    trim = _Trim()
    trim.hold.set()
    logged: list[Trimmed] = []
    memory = MemoryReturn(log=logged.append, settle=SETTLE, trim=trim)
    for _ in range(5):
        memory.unloaded()
        await asyncio.sleep(SETTLE / 5)  # each within the last one's settling time
    assert trim.calls == 0
    await _until(lambda: bool(logged), "the trim logged")
    assert trim.calls == 1
    assert logged[0].unloads == 5
    assert logged[0].before > 0 and logged[0].after > 0
    assert "after 5 unloads" in logged[0].describe()


async def test_unloads_during_a_trim_are_trimmed_after_it() -> None:
    trim = _Trim()
    logged: list[Trimmed] = []
    memory = MemoryReturn(log=logged.append, settle=SETTLE, trim=trim)
    memory.unloaded()
    await _until(lambda: trim.calls == 1, "the first trim running")
    memory.unloaded()
    memory.unloaded()
    await asyncio.sleep(SETTLE * 4)
    assert trim.calls == 1  # one at a time
    trim.hold.set()
    await _until(lambda: len(logged) == 2, "the second trim logged")
    assert [trimmed.unloads for trimmed in logged] == [1, 2]
    assert trim.calls == 2


async def test_without_malloc_trim_nothing_is_scheduled() -> None:
    memory = MemoryReturn(log=lambda trimmed: pytest.fail("logged without a trim"), settle=SETTLE, trim=None)
    assert not memory.available
    memory.unloaded()
    await asyncio.sleep(SETTLE * 3)


async def test_closed_it_trims_nothing_more() -> None:
    trim = _Trim()
    trim.hold.set()
    memory = MemoryReturn(log=lambda trimmed: None, settle=SETTLE, trim=trim)
    memory.unloaded()
    memory.close()
    await asyncio.sleep(SETTLE * 3)
    assert trim.calls == 0


def _rss_kb(pid: int) -> int:
    status = Path(f"/proc/{pid}/status").read_text()
    return int(re.search(r"VmRSS:\s+(\d+)", status).group(1))  # type: ignore[union-attr]


def test_resident_bytes_is_this_process_rss() -> None:
    rss_kb = _rss_kb(os.getpid())
    assert abs(resident_bytes() / 1024 - rss_kb) < max(rss_kb * 0.05, 2048)


NODES = 40
_TALKER = "  - {{package: lifecycle_container, plugin: lifecycle_container::Talker, name: t{}, autostart: true}}\n"
MANY_TALKERS = "container:\n  name: ComponentManager\nnodes:\n" + "".join(_TALKER.format(i) for i in range(NODES))


def test_a_container_gives_back_what_its_unloaded_nodes_freed(
    run_container: Callable[..., ContainerProcess], client_node: Node, executor: AsyncioExecutor
) -> None:
    container = run_container(MANY_TALKERS)
    client = ContainerClient(client_node, executor, process=container)
    loaded = client.list()
    assert len(loaded) == NODES
    start = len(container.lines)
    for unique_id, _ in loaded:
        response = client.unload(unique_id)
        assert (response.success, response.error_message) == (True, "")
    line = container.wait_for_line("back to the system", start=start, timeout=20.0)
    found = re.search(r"after (\d+) unloads \(RSS (\d+) -> (\d+) MiB", line)
    assert found is not None, line
    unloads, before, after = (int(group) for group in found.groups())
    assert unloads == NODES  # one trim for the whole burst
    # 40 talkers freed tens of MiB (measured: about 2 MiB a talker loaded); a trim that gave
    # nothing back, or ran before the unloads ended, would not show it.
    assert before - after >= NODES // 4, line
    assert _rss_kb(container.process.pid) < (after + 8) * 1024
    assert sum("back to the system" in logged for logged in container.lines[start:]) == 1
