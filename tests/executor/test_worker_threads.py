"""Worker threads (``_workers``): started when plain work finds none idle, gone once idle or past the pool's size."""

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
from container.executor import _lanes, _workers
from container.executor._tasks import TaskLaneHooks
from tests.waiting import wait_until

pytestmark = pytest.mark.timeout(30)


def test_an_idle_worker_thread_exits_and_work_starts_a_new_one(
    context: Context, executor: AsyncioExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(_workers, "WORKER_IDLE_S", 0.2)
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
    monkeypatch.setattr(_workers, "WORKER_IDLE_S", 0.02)
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

    def __init__(self, *, sees_work: bool = False) -> None:
        self.lingers = 0
        #: What each linger returns: whether work was handed over meanwhile.
        self.sees_work = sees_work

    def handed(self) -> None:
        pass

    def started(self) -> None:
        pass

    def finished(self) -> None:
        pass

    def linger(self, spin_ns: int) -> bool:
        self.lingers += 1
        return self.sees_work


class _LaneHooks(TaskLaneHooks):
    """The plain task lane's hooks, but for work handed over from "the loop's thread" through ``handoff``."""

    def __init__(self, handoff: _CountingHandoff) -> None:
        super().__init__(post=lambda callback, *args: callback(*args), progress=_no_progress)
        self.handoff = handoff  # type: ignore[assignment]
        self.workers = _workers.WorkerPool(name="linger", handoff=handoff, carries=False)  # type: ignore[arg-type]

    def on_loop_thread(self) -> bool:
        return True


def _no_progress() -> Any:
    raise AssertionError("plain work only")


def _inbox_get_line() -> int:
    """The line of ``WorkerPool._work`` where a worker waits in the pool's inbox (``inbox.get``)."""
    lines, first = inspect.getsourcelines(_workers.WorkerPool._work)
    return first + next(index for index, line in enumerate(lines) if "inbox.get(" in line)


def _in_inbox_get(thread: threading.Thread, line: int) -> bool:
    """Whether ``thread`` waits at ``line`` of ``WorkerPool._work`` (see :func:`_inbox_get_line`)."""
    frame = sys._current_frames().get(thread.ident or 0)
    return frame is not None and frame.f_code is _workers.WorkerPool._work.__code__ and frame.f_lineno == line


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

    monkeypatch.setattr(_workers, "WORKER_LINGER_NS", 200_000_000)  # 200 ms: far above any poll here
    handoff = _CountingHandoff()
    loop = asyncio.new_event_loop()
    hooks = _LaneHooks(handoff)
    lane = _lanes.Lane(name="linger", limit=1, loop=loop, hooks=hooks)
    done: list[object] = []

    def work() -> Work:
        return Work(object(), lambda: None, False, 1, lambda work, error: done.append(error))

    try:
        lane.submit(work())
        wait_until(lambda: done, "the first work")
        (worker,) = hooks.workers.threads
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
        hooks.workers.close(timeout=2.0)
        loop.close()


def test_closing_a_lane_waits_for_its_own_plain_callbacks_only() -> None:
    """Lanes share the pool's threads, so a lane closing waits for its plain callbacks
    running (counted, not by thread), never for another lane's on the same pool, and
    never for the callback of its own that closes it (that would wait out the timeout)."""
    from container.executor._engine import Work

    loop = asyncio.new_event_loop()
    hooks = TaskLaneHooks(post=lambda callback, *args: callback(*args), progress=_no_progress)
    mine, other, closing = (_lanes.Lane(name=name, limit=1, loop=loop, hooks=hooks) for name in "abc")
    started = threading.Semaphore(0)
    go_mine, go_other = threading.Event(), threading.Event()
    done: list[object] = []
    closed_itself: list[tuple[bool, float]] = []

    def blocking(go: threading.Event) -> Work:
        def call() -> None:
            started.release()
            go.wait(10.0)

        return Work(object(), call, False, 1, lambda work, error: done.append(error))

    def close_itself() -> None:
        began = time.monotonic()
        closed_itself.append((closing.close(timeout=5.0), time.monotonic() - began))

    try:
        mine.submit(blocking(go_mine))
        other.submit(blocking(go_other))
        for _ in range(2):
            assert started.acquire(timeout=5.0), "a blocking callback never started"
        assert len(hooks.workers.threads) == 2  # both busy: a thread each
        assert not mine.close(timeout=0.2), "closed while its callback still ran"
        go_mine.set()
        assert mine.close(timeout=5.0), "its callback returned, the other lane's still blocks"
        assert not go_other.is_set()
        closing.submit(Work(object(), close_itself, False, 1, lambda work, error: done.append(error)))
        wait_until(lambda: closed_itself, "the callback that closes its own lane")
        assert closed_itself[0][0] and closed_itself[0][1] < 1.0, closed_itself
    finally:
        go_mine.set()
        go_other.set()
        for lane in (mine, other, closing):
            lane.close(timeout=2.0)
        assert hooks.workers.close(timeout=2.0)
        loop.close()


@pytest.mark.parametrize("sees_work", [False, True], ids=["lingers-miss", "lingers-pay"])
def test_a_worker_whose_lingers_see_no_work_stops_lingering_for_a_while(
    monkeypatch: pytest.MonkeyPatch, sees_work: bool
) -> None:
    """The pool's top worker sees every lane's work, which often comes "quickly" by chance
    (ten nodes' 100 Hz timers): lingering then spins for nothing, and the ten-node load cost
    1.12x the CPU. After two lingers in a row that saw no work it skips the next 32; while
    lingers see work (a request and its answer) it lingers every time."""
    from container.executor._engine import Work

    monkeypatch.setattr(_workers, "WORKER_LINGER_NS", 1_000_000_000)  # every hand-over here is quick
    handoff = _CountingHandoff(sees_work=sees_work)
    loop = asyncio.new_event_loop()
    hooks = _LaneHooks(handoff)
    lane = _lanes.Lane(name="backoff", limit=1, loop=loop, hooks=hooks)
    done: list[object] = []
    try:
        line = _inbox_get_line()

        def hand_one(count: int) -> None:
            lane.submit(Work(object(), lambda: None, False, 1, lambda work, error: done.append(error)))
            wait_until(lambda: len(done) == count, f"work {count}")
            (worker,) = hooks.workers.threads
            wait_until(lambda: _in_inbox_get(worker, line), "the worker to wait for work")

        for count in range(1, 21):
            hand_one(count)
        # One linger after each of the 20 works while lingering pays; otherwise two, then 32 skipped.
        assert handoff.lingers == (20 if sees_work else _workers.WORKER_LINGER_MISSES), handoff.lingers
        assert done == [None] * 20
    finally:
        lane.close(timeout=2.0)
        hooks.workers.close(timeout=2.0)
        loop.close()


def test_a_burst_of_short_plain_callbacks_runs_on_the_pools_threads(
    context: Context, executor: AsyncioExecutor
) -> None:
    """40 groups' plain callbacks at once, each busy for a millisecond (the GIL held, not
    blocked): every worker is busy, the rest wait in the backlog and run as workers finish,
    on the pool's threads. A thread started per callback past the pool's size, each ending
    with its callback, made every burst (a hundred nodes' start-up) restart them."""
    nodes = [Node(f"burst_{index}", context=context) for index in range(40)]
    for node in nodes:
        executor.add_node(node)
    ran_on: set[threading.Thread] = set()

    def busy() -> None:
        ran_on.add(threading.current_thread())
        until = time.perf_counter() + 0.001
        while time.perf_counter() < until:
            pass

    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        calls: list[Any] = []
        for _ in range(3):
            calls[:] = [executor.run_in_group(node.default_callback_group, busy, node=node) for node in nodes]
            wait_until(lambda: all(call.done() for call in calls), "the burst run", timeout=10.0)
        # The pool's size; one more or two where the monitor found none finishing (a preempted machine).
        assert len(ran_on) <= _workers.POOL_SIZE + 2, f"{len(ran_on)} threads ran 40 callbacks at once"
    finally:
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)
        for node in nodes:
            node.destroy_node()


class _Running:
    """A stand-in lane: runs the work it is handed, a plain function."""

    @staticmethod
    def run_handed(work: Any) -> None:
        work()


def test_a_thread_started_while_every_worker_was_blocked_ends_once_the_others_work_again() -> None:
    """Every worker blocked, the monitor starts one more thread for the work waiting (a
    backlog of short calls, the GIL held). Once the workers are free again, that thread
    ends with its call, though the backlog still holds work for the others to take: kept
    while a backlog lasted, each thread the monitor started in a slow moment of an
    overloaded container stayed for as long as the overload (67 threads for a hundred
    demo nodes whose listeners logged every message)."""
    pool = _workers.WorkerPool(name="overload", handoff=None, carries=False, size=2)
    release = threading.Event()
    blocked_now: list[None] = []
    done: list[None] = []

    def blocked() -> None:
        blocked_now.append(None)
        release.wait(10.0)

    def busy() -> None:
        until = time.perf_counter() + 0.001
        while time.perf_counter() < until:
            pass
        done.append(None)

    def workers() -> int:
        return sum(not thread.name.endswith("monitor") for thread in pool.threads)

    lane: Any = _Running()
    # The stand-in lane runs plain functions as its work.
    blocked_work: Any = blocked
    busy_work: Any = busy
    try:
        for _ in range(2):
            pool.hand(lane, blocked_work, from_loop=False)
        wait_until(lambda: len(blocked_now) == 2, "every worker blocked")
        for _ in range(300):
            pool.hand(lane, busy_work, from_loop=False)
        wait_until(lambda: done, "a thread started for the work waiting behind blocked workers")
        assert workers() == 3
        release.set()
        wait_until(lambda: workers() <= 2, lambda: f"{workers()} workers, the pool's size 2", timeout=10.0)
        assert len(done) <= 250, f"the extra thread ended only with the backlog ({len(done)} of 300 done)"
        wait_until(lambda: len(done) == 300, "the backlog run", timeout=20.0)
    finally:
        release.set()
        pool.close(timeout=5.0)
