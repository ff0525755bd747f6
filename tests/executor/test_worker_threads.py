"""Lane worker threads: started when plain work arrives, gone once idle."""

from __future__ import annotations

import asyncio
import inspect
import sys
import threading
import time
from typing import Any

import pytest
from rclpy.context import Context
from rclpy.node import Node

from container import AsyncioExecutor
from container.executor import _lanes
from container.executor._tasks import TaskLaneHooks
from tests.waiting import wait_until

pytestmark = pytest.mark.timeout(30)


def test_an_idle_worker_thread_exits_and_work_starts_a_new_one(
    context: Context, executor: AsyncioExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_lanes, "WORKER_IDLE_S", 0.2)
    node = Node("idle_worker", context=context)
    ran_on: list[threading.Thread] = []

    def tick() -> None:
        ran_on.append(threading.current_thread())
        timer.cancel()  # once per reset

    timer = node.create_timer(0.01, tick)
    executor.add_node(node)
    try:
        wait_until(lambda: ran_on, "the first tick", executor=executor)
        assert ran_on[0] is not threading.current_thread()  # a worker's, not the loop's
        assert ran_on[0] in executor.threads()
        wait_until(lambda: not executor.threads(), "the idle worker to exit", executor=executor, timeout=5.0)
        assert not ran_on[0].is_alive()

        timer.reset()
        wait_until(lambda: len(ran_on) == 2, "the tick after the worker left", executor=executor)
        assert ran_on[1] is not ran_on[0]
        assert executor.threads() == [ran_on[1]]
    finally:
        executor.remove_node(node)
        node.destroy_node()


def test_a_worker_with_work_handed_to_it_does_not_exit(
    context: Context, executor: AsyncioExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Work that arrives every idle period or so keeps its lane's one thread:
    never a second thread, never a lost callback."""
    monkeypatch.setattr(_lanes, "WORKER_IDLE_S", 0.02)
    node = Node("busy_worker", context=context)
    ran_on: list[threading.Thread] = []
    timer = node.create_timer(0.02, lambda: ran_on.append(threading.current_thread()))
    executor.add_node(node)
    try:
        wait_until(lambda: len(ran_on) >= 30, "30 ticks", executor=executor)
        assert len(executor.threads()) <= 1
    finally:
        timer.cancel()
        executor.remove_node(node)
        node.destroy_node()


class _CountingHandoff:
    """A hand-over that counts a worker's lingers (and returns from each at once)."""

    spin = True

    def __init__(self) -> None:
        self.lingers = 0

    def handed(self) -> None:
        pass

    def started(self) -> None:
        pass

    def finished(self) -> None:
        pass

    def linger(self, spin_ns: int) -> bool:
        self.lingers += 1
        return False


class _LaneHooks(TaskLaneHooks):
    """The plain task lane's hooks, but for work handed over from "the loop's thread" through ``handoff``."""

    def __init__(self, handoff: _CountingHandoff) -> None:
        super().__init__(post=lambda callback, *args: callback(*args), progress=_no_progress)
        self.handoff = handoff  # type: ignore[assignment]

    def on_loop_thread(self) -> bool:
        return True


def _no_progress() -> Any:
    raise AssertionError("plain work only")


def _inbox_get_line() -> int:
    """The line of ``Lane._worker`` where a worker waits in its lane's inbox (``inbox.get``)."""
    lines, first = inspect.getsourcelines(_lanes.Lane._worker)
    return first + next(index for index, line in enumerate(lines) if "inbox.get(" in line)


def _in_inbox_get(thread: threading.Thread, line: int) -> bool:
    """Whether ``thread`` waits at ``line`` of ``Lane._worker`` (see :func:`_inbox_get_line`)."""
    frame = sys._current_frames().get(thread.ident or 0)
    return frame is not None and frame.f_code is _lanes.Lane._worker.__code__ and frame.f_lineno == line


def test_a_worker_handed_work_soon_after_it_was_free_lingers_however_late_it_woke(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Whether a worker lingers for its next work is decided by how soon the
    work was handed to it after it was free, not by how long its wait took:
    once asleep, its own wake-up (here held back by the GIL) made every wait
    long, and a worker that slept once never lingered again however fast
    its work came (plain service calls' rate then swung 0.8x-1.2x between
    equal runs)."""
    from container.executor._engine import Work

    monkeypatch.setattr(_lanes, "WORKER_LINGER_NS", 200_000_000)  # 200 ms: far above any poll here
    handoff = _CountingHandoff()
    loop = asyncio.new_event_loop()
    lane = _lanes.Lane(name="linger", limit=1, loop=loop, hooks=_LaneHooks(handoff))
    done: list[object] = []

    def work() -> Work:
        return Work(object(), lambda: None, False, 1, lambda work, error: done.append(error))

    try:
        lane.submit(work())
        wait_until(lambda: done, "the first work")
        (worker,) = lane._threads
        line = _inbox_get_line()
        wait_until(lambda: _in_inbox_get(worker, line), "the worker to wait for work")
        before = handoff.lingers  # after its first work, handed before the thread started: 1
        interval = sys.getswitchinterval()
        sys.setswitchinterval(5.0)
        try:
            lane.submit(work())  # at once: well within the bound after the worker was free
            until = time.monotonic() + 0.4  # the GIL held: the worker's wait ends 400 ms after
            while time.monotonic() < until:
                pass
        finally:
            sys.setswitchinterval(interval)
        wait_until(lambda: len(done) == 2, "the second work")
        wait_until(lambda: handoff.lingers == before + 1, "the worker to linger before its next work", timeout=5.0)
        assert done == [None, None]
    finally:
        lane.close(timeout=2.0)
        loop.close()
