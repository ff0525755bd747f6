"""``in_thread``: a thread of its own per call, reused once its call returned."""

from __future__ import annotations

import asyncio
import gc
import threading
import weakref

import pytest

from container.executor import Escaped, _spare, in_thread

pytestmark = pytest.mark.timeout(30)


def _named() -> tuple[threading.Thread, str]:
    thread = threading.current_thread()
    return thread, thread.name


async def test_a_call_after_another_returned_runs_on_the_same_thread_under_its_own_name() -> None:
    first, first_name = await in_thread(_named, name="construct:/a")
    second, second_name = await in_thread(_named, name="construct:/b")
    assert first is second and first is not threading.current_thread()
    assert (first_name, second_name) == ("construct:/a", "construct:/b")
    # Between calls it says it is free, not what it last ran.
    assert first.name == "spare"


async def test_a_call_that_blocks_keeps_its_thread_and_holds_up_no_other_call() -> None:
    release, started = threading.Event(), threading.Event()

    def blocked() -> threading.Thread:
        started.set()
        release.wait(10.0)
        return threading.current_thread()

    stuck = asyncio.ensure_future(in_thread(blocked, name="transition:/stuck"))
    try:
        # Blocked first: started after the other call, it could take that call's thread once free.
        assert await asyncio.to_thread(started.wait, 5.0)
        other, _ = await asyncio.wait_for(in_thread(_named, name="transition:/other"), 5.0)
        assert not stuck.done()
        release.set()
        assert await asyncio.wait_for(stuck, 5.0) is not other
    finally:
        release.set()


async def test_a_call_that_exits_reaches_its_caller_and_its_thread_serves_the_next() -> None:
    def exits() -> threading.Thread:
        ran_on.append(threading.current_thread())
        raise SystemExit(3)  # a constructor calling sys.exit(): only that call ends

    ran_on: list[threading.Thread] = []
    with pytest.raises(Escaped) as caught:
        await in_thread(exits, name="construct:/exits")
    assert isinstance(caught.value.error, SystemExit)
    thread, _ = await in_thread(_named, name="construct:/next")
    assert thread is ran_on[0]


async def test_an_idle_spare_thread_ends(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_spare, "SPARE_IDLE_S", 0.1)
    # A thread started now reads the patched wait.
    release = threading.Event()
    busy = asyncio.ensure_future(in_thread(lambda: release.wait(10.0), name="busy"))
    thread, _ = await in_thread(_named, name="short")
    release.set()
    await busy
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 5.0
    while thread.is_alive() and loop.time() < deadline:
        await asyncio.sleep(0.02)
    assert not thread.is_alive()


async def test_an_idle_spare_thread_keeps_nothing_of_the_call_it_ran() -> None:
    class Made:
        """What a call returns: a node a constructor made, say."""

    # Whoever awaited it let go of it (the node was unloaded): it is garbage,
    # though the thread that made it waits idle for the next call (3 s), once
    # that thread is past handing it over.
    made = weakref.ref(await in_thread(Made, name="construct:/made"))
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 1.0
    while gc.collect() >= 0 and made() is not None and loop.time() < deadline:
        await asyncio.sleep(0.01)
    assert made() is None
