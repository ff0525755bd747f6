"""The admission state every lane and the spin_once gate share (``fastpath/lanes.c``, ``_pyengine/lanes.py``).

Pure data-structure tests, run against both engines: no ROS. The
executor-level tests exercise the same rules through real callbacks (a
busy mutually exclusive group keeps a subscription's depth of messages,
spin_once starts one callback per call).
"""

from __future__ import annotations

import asyncio
import contextvars
from types import ModuleType
from typing import Any

import pytest

from tests.engine_support import engines

pytestmark = pytest.mark.parametrize("engine", engines())


def work(engine: ModuleType, entity: object, *, depth: int = 2, node: object = None) -> Any:
    token = engine.Token(node) if node is not None else None
    return engine.Work(entity, lambda: None, False, depth, lambda w, e: None, token)


def test_keep_last_keeps_order_and_at_most_depth_per_entity(engine: ModuleType) -> None:
    kept = engine.KeepLast()
    a, b = object(), object()
    assert [kept.push(item, entity, 2) for item, entity in (("a1", a), ("b1", b), ("a2", a), ("a3", a))] == [
        False, False, False, True,
    ]
    assert kept.items() == ["b1", "a2", "a3"] and len(kept) == 3
    assert [kept.pop() for _ in range(3)] == ["b1", "a2", "a3"]
    with pytest.raises(IndexError):
        kept.pop()
    # Counts follow pops: a fresh entity budget after its items left.
    assert not kept.push("a4", a, 1) and kept.push("a5", a, 1) and kept.items() == ["a5"]
    kept.clear()
    assert len(kept) == 0 and not kept.push("a6", a, 1)


def test_keep_last_stays_bounded_over_a_long_run(engine: ModuleType) -> None:
    kept = engine.KeepLast()
    entity = object()
    for index in range(10_000):
        kept.push(index, entity, 3)
        if index % 2:
            kept.pop()
    assert kept.items() == [9998, 9999]  # after each pop, the last two pushed


def test_slots_admit_up_to_the_limit_then_keep_last_per_entity(engine: ModuleType) -> None:
    slots = engine.Slots(2)
    sub, timer = object(), object()
    first, second = work(engine, sub), work(engine, sub)
    assert slots.admit(first) and slots.admit(second) and slots.running == 2
    waiting = [work(engine, sub, depth=2) for _ in range(3)] + [work(engine, timer, depth=1) for _ in range(2)]
    assert [slots.admit(w) for w in waiting] == [False] * 5
    assert slots.waiting == 3 and slots.dropped == 2  # one of the subscription's, one of the timer's
    assert slots.busy()
    # A finished one hands its slot to the oldest waiting work that was kept.
    assert slots.next(first) is waiting[1]
    assert slots.next(second) is waiting[2]
    assert slots.next(waiting[1]) is waiting[4]
    assert slots.next(waiting[2]) is None and slots.running == 1
    assert slots.next(waiting[4]) is None and slots.running == 0 and not slots.busy()


def test_slots_close_drops_what_waits_and_admits_nothing(engine: ModuleType) -> None:
    slots = engine.Slots(1)
    entity = object()
    running = work(engine, entity)
    assert slots.admit(running) and not slots.admit(work(engine, entity))
    slots.close()
    assert slots.closed and slots.waiting == 0
    assert not slots.admit(work(engine, entity))
    assert slots.next(running) is None and slots.running == 0


def test_slots_retire_takes_out_a_nodes_waiting_work_and_lists_its_running_work(engine: ModuleType) -> None:
    slots = engine.Slots(1)
    mine, other = object(), object()
    running = work(engine, object(), node=mine)
    assert slots.admit(running)
    waiting = [work(engine, object(), node=mine), work(engine, object(), node=other), work(engine, object(), node=mine)]
    for item in waiting:
        slots.admit(item)
    assert slots.retire(mine) == [waiting[0], waiting[2]]
    assert slots.waiting == 1 and slots.of(mine) == [running] and slots.of(other) == []
    assert slots.next(running) is waiting[1]


def test_limit_is_at_least_one_and_work_checks_its_arguments(engine: ModuleType) -> None:
    slots = engine.Slots(1)
    slots.limit = 3
    assert slots.limit == 3
    with pytest.raises(ValueError):
        slots.limit = 0
    for limit in (0, -1):
        with pytest.raises(ValueError, match="at least 1"):
            engine.Slots(limit)
    with pytest.raises(TypeError):
        slots.admit("not work")
    with pytest.raises(TypeError):
        engine.Work(object(), print, False, 1, print, token="no token")
    item = engine.Work(object(), print, True, 5, print, None, (1, 2))
    assert (item.is_async, item.depth, item.args, item.token) == (True, 5, (1, 2), None)
    token = engine.Token("node")
    token.retired = True
    assert token.retired and token.node == "node"


def test_runner_holds_its_task_and_context(engine: ModuleType) -> None:
    async def main() -> Any:
        task = asyncio.current_task()
        runner = engine.Runner(task, contextvars.copy_context())
        assert runner.idle is None and runner.current is None
        runner.current = work(engine, object())
        return runner.task is task

    assert asyncio.run(main())
    with pytest.raises(TypeError):
        engine.Runner(None, "not a context")


def test_slots_park_idle_runners_and_give_the_last_pending_one(engine: ModuleType) -> None:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        task = asyncio.current_task()
        slots = engine.Slots(1)
        runners = [engine.Runner(task, contextvars.copy_context(), loop.create_future()) for _ in range(3)]
        assert slots.idle_runner() is None and slots.idle == 0
        for runner in runners:
            slots.park(runner)
        assert slots.idle == 3 and slots.idle_runner() is runners[2] and slots.idle == 3  # left parked
        runners[2].idle.cancel()  # cancelled while idle: dropped on the way
        runners[1].idle = None  # woken: not idle
        assert slots.idle_runner() is runners[0] and slots.idle == 1
        assert slots.unpark(runners[0]) and not slots.unpark(runners[0]) and slots.idle == 0
        with pytest.raises(TypeError):
            slots.park(object())
        work_item = work(engine, object())
        slots.activate(work_item)
        assert slots.busy() is False and slots.next(work_item) is None  # activated without a slot count

    asyncio.run(main())
