"""The two engines behave the same: one scripted scenario, run on each, gives one trace.

Each scenario below runs on the compiled engine (``_fastpath``) and on the
Python one (``_pyengine``) and records what it observes, addresses and
objects replaced by names; the two traces must be equal, and match what
the scenario expects. At the object level: the lanes' admission state
(keep-last, drops, arrived times, retiring, closing), a callback's
metering, the first step's outcomes, the async chain's timers, and the
takes, answers and waits on real rclpy entities. At the executor level,
small scenarios (``engine_scenarios.py``) run in a child process per engine
and their event logs must be equal. Last, the choice of the engine: a
compiled engine that cannot be imported leaves the Python one, said in one
warning line, as is an unknown ``CONTAINER_EXECUTOR_ENGINE``.

What only the compiled engine has (rmw's new-data callbacks, polls that keep
the GIL, spinning hand-overs) is not compared here: see
``docs/executor/engines.md``.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import functools
import json
import os
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from rclpy.context import Context
from rclpy.guard_condition import GuardCondition
from rclpy.node import Node
from std_msgs.msg import Int64
from std_srvs.srv import SetBool

from container._compat import enter_task, leave_task
from container.executor import HAS_PUBLISHER_GID, _engine, _fastpath, _message_info, _pyengine

Trace = list[Any]

#: The two engines, in the order their traces are compared.
BOTH = (_fastpath, _pyengine)

TIMEOUT = 10.0


def _same_on_both(scenario: Callable[[ModuleType], Trace]) -> Trace:
    """Run ``scenario`` on each engine: its trace, which must be the same on both."""
    compiled, python = (scenario(engine) for engine in BOTH)
    assert python == compiled
    return compiled


def _raised(call: Callable[[], object]) -> list[str]:
    """What ``call`` raised, as ``[type, message]`` (``[]``: nothing)."""
    try:
        call()
    except BaseException as error:
        return [type(error).__name__, str(error)]
    return []


def _until(condition: Callable[[], bool]) -> None:
    deadline = time.monotonic() + TIMEOUT
    while not condition():
        assert time.monotonic() < deadline, "not within the timeout"
        time.sleep(0.001)


def _done(work: object, error: BaseException | None) -> None:
    """A ``done`` that nobody reads."""


# -- keep-last and slots ---------------------------------------------------------------------


def _keep_last(engine: ModuleType) -> Trace:
    kept = engine.KeepLast()
    a, b = object(), object()
    trace: Trace = [
        [kept.push(item, entity, 2) for item, entity in (("a1", a), ("b1", b), ("a2", a), ("a3", a), ("b2", b))],
        kept.items(),
        len(kept),
        kept.pop(),
        kept.push("a4", a, 1),  # a smaller depth: the oldest of its two waiting goes (one a push)
        kept.items(),
    ]
    for index in range(200):  # long enough for the lists to be compacted as they drain
        kept.push(index, b, 1000)
    trace += [[kept.pop() for _ in range(150)][-3:], len(kept), kept.items()[:3]]
    kept.clear()
    trace += [len(kept), _raised(kept.pop), _raised(lambda: kept.push("x", a, "two")), kept.push("a5", a, 0)]
    return trace


def test_keep_last_keeps_the_same_items_on_both_engines() -> None:
    trace = _same_on_both(_keep_last)
    assert trace[0] == [False, False, False, True, False]
    assert trace[1:6] == [["b1", "a2", "a3", "b2"], 4, "b1", True, ["a3", "b2", "a4"]]
    assert trace[-1] is False  # depth 0 drops nothing: nothing of its own waits


def _arrived(engine: ModuleType) -> Trace:
    """A newer invocation that replaces a waiting one inherits its arrival (a timer's first missed firing)."""
    slots, meter, entity = engine.Slots(1), engine.Meter(), object()

    def work(arrived: int, *, metered: bool = True) -> Any:
        return engine.Work(entity, _done, False, 1, _done, meter=meter if metered else None, arrived=arrived)

    running, older, newer = work(1000), work(2000), work(3000)
    trace: Trace = [slots.admit(running), slots.admit(older), slots.admit(newer), newer.arrived, older.arrived]
    unmetered = work(0, metered=False)
    trace += [unmetered.arrived, slots.admit(unmetered), unmetered.arrived]  # 0: nothing to inherit from it
    later = work(5000)
    trace += [slots.admit(later), later.arrived]  # the one it replaced knew no arrival
    earlier = work(4000)  # arrived before the one waiting (a message taken late): its own stays
    trace += [slots.admit(earlier), earlier.arrived, slots.dropped, meter.take()[10]]
    stamped = engine.Work(entity, _done, False, 1, _done, meter=meter)
    trace += [stamped.arrived > 0, engine.Work(entity, _done, False, 1, _done).arrived]
    return trace


def test_a_replacing_invocation_inherits_the_waiting_ones_arrival_on_both_engines() -> None:
    trace = _same_on_both(_arrived)
    assert trace[:5] == [True, False, False, 2000, 2000]
    assert trace[5:] == [0, False, 0, False, 5000, False, 4000, 4, 3, True, 0]  # the unmetered drop is no meter's


def _slots(engine: ModuleType) -> Trace:
    mine, other = object(), object()
    names: dict[int, str] = {}

    def work(name: str, entity: object, node: object | None = None, *, depth: int = 2) -> Any:
        made = engine.Work(entity, _done, False, depth, _done, engine.Token(node) if node is not None else None)
        names[id(made)] = name
        return made

    def named(items: list[Any] | None) -> Any:
        return None if items is None else sorted(names[id(item)] for item in items)

    slots = engine.Slots(2)
    sub, timer = object(), object()
    r1, r2 = work("r1", sub, mine), work("r2", sub, other)
    trace: Trace = [slots.admit(r1), slots.admit(r2), slots.running, slots.busy(), slots.waiting]
    waiting = [work("w1", sub, mine), work("w2", sub, other), work("w3", sub, mine), work("t1", timer, mine, depth=1),
               work("t2", timer, other, depth=1)]  # fmt: skip
    trace += [[slots.admit(item) for item in waiting], slots.waiting, slots.dropped]
    trace += [named(slots.of(mine)), named(slots.of(other)), named(slots.retire(mine)), slots.waiting]
    started = slots.next(r1)  # the oldest kept, its slot handed on
    trace += [names[id(started)], slots.running, named(slots.of(mine)), named(slots.of(other))]
    last = slots.next(r2)
    trace += [names[id(last)], slots.next(started), slots.running]
    slots.limit = 3
    trace += [slots.limit, _raised(lambda: setattr(slots, "limit", 0)), slots.limit]
    trace += [_raised(lambda: slots.admit("not work")), _raised(lambda: slots.activate(object()))]
    extra = work("extra", sub, mine)
    slots.activate(extra)  # a suspended first step's work, its slot taken already
    trace += [named(slots.of(mine)), slots.running]
    pending = work("pending", sub, other)
    trace += [slots.admit(work("third", sub, other)), slots.admit(work("fourth", sub, other)), slots.admit(pending)]
    trace += [slots.waiting]
    slots.close()
    trace += [slots.closed, slots.waiting, slots.busy(), slots.admit(work("late", sub, mine))]
    trace += [slots.next(extra), slots.next(last), slots.running, slots.busy()]
    return trace


def test_slots_admit_drop_retire_and_close_alike_on_both_engines() -> None:
    trace = _same_on_both(_slots)
    assert trace[:5] == [True, True, 2, True, 0]
    assert trace[5:8] == [[False] * 5, 3, 2]  # the subscription keeps two, the timer one
    assert trace[8:12] == [["r1"], ["r2"], ["w3"], 2]  # the node's waiting work retired
    assert trace[12:19] == ["w2", 2, [], ["r2", "w2"], "t2", None, 1]
    refused = ["TypeError", "a lane admits Work only"]
    assert trace[19:24] == [3, ["ValueError", "a lane's limit is at least 1"], 3, refused, refused]
    assert trace[24:] == [["extra"], 1, True, True, False, 1, True, 0, True, False, None, None, 1, True]


def _runners(engine: ModuleType) -> Trace:
    loop = asyncio.new_event_loop()
    try:
        slots = engine.Slots(1)
        runners = [engine.Runner(object(), contextvars.copy_context(), loop.create_future()) for _ in range(4)]
        index = {id(runner): number for number, runner in enumerate(runners)}

        def which(runner: Any) -> int | None:
            return None if runner is None else index[id(runner)]

        trace: Trace = [which(slots.idle_runner()), slots.idle]
        for runner in runners:
            slots.park(runner)
        trace += [slots.idle, which(slots.idle_runner()), slots.idle]
        runners[3].idle.cancel()  # cancelled while idle: dropped on the way
        runners[2].idle = None  # woken: not idle
        trace += [which(slots.idle_runner()), slots.idle, slots.unpark(runners[1]), slots.unpark(runners[1])]
        trace += [which(slots.idle_runner()), slots.idle, _raised(lambda: slots.park(object()))]
        trace += [_raised(lambda: engine.Runner(None, "not a context"))]
        return trace
    finally:
        loop.close()


def test_idle_runners_are_parked_and_found_alike_on_both_engines() -> None:
    trace = _same_on_both(_runners)
    assert trace[:5] == [None, 0, 4, 3, 4]
    assert trace[5:9] == [1, 2, True, False]


# -- metering ------------------------------------------------------------------------------


@contextlib.contextmanager
def _stuck_after(engine: ModuleType, ns: int) -> Iterator[None]:
    engine.stuck_after(ns)
    try:
        yield
    finally:
        engine.stuck_after(1_000_000_000)


def _metering(engine: ModuleType) -> Trace:
    """Plain runs and coroutine steps, timed: what each window's figures say of them."""
    meter = engine.Meter()
    variable: contextvars.ContextVar[str] = contextvars.ContextVar("engines")
    context = contextvars.copy_context()
    context.run(variable.set, "the context's")
    seen: list[object] = []

    def plain(value: int) -> int:
        seen.append(variable.get("unset"))
        variable.set("set inside")
        return value * 2

    work = engine.Work("entity", plain, False, 1, _done, None, (21,), meter=meter, arrived=time.monotonic_ns())
    trace: Trace = [work.run(context), seen, context[variable], work.started > 0]  # run in it: its set stays
    figures = meter.take()
    trace += [figures[:2], figures[10:], figures[4] <= figures[5] <= figures[6], figures[7] <= figures[9]]
    failing = engine.Work("entity", lambda: 1 / 0, False, 1, _done, meter=meter)
    trace += [_raised(lambda: failing.run(contextvars.copy_context())), meter.take()[:2]]
    trace += [_raised(lambda: work.run("not a context"))]

    async def two_steps() -> str:
        await asyncio.sleep(0)
        return "done"

    coroutine = engine.Work("entity", two_steps, True, 1, _done, meter=meter)
    coro = two_steps()
    trace += [coroutine.started, coroutine.step(coro.send, None), coroutine.started > 0, meter.take()[:2]]
    trace += [_raised(lambda: coroutine.step(coro.send, None)), meter.take()[:2]]
    unmetered = engine.Work("entity", two_steps, True, 1, _done)
    other = two_steps()
    trace += [unmetered.step(other.send, None), unmetered.started]
    other.close()
    with _stuck_after(engine, 2_000_000):
        running: list[Any] = []

        def slow_callback() -> None:
            running.append(meter.take())
            time.sleep(0.01)

        slow = engine.Work("entity", slow_callback, False, 1, _done, meter=meter)
        slow.run(contextvars.copy_context())
        after = meter.take()
        # The window taken inside the step had its start counted: the next has its end.
        trace += [running[0][11], running[0][12] >= 0, after[:2], after[11], after[3] <= after[2]]
    trace += [_raised(lambda: engine.stuck_after(0))]
    return trace


def _metered_calls(engine: ModuleType) -> Trace:
    """``Meter.call``: a loop handle's run, timed as one callback run (``_loop``)."""
    meter = engine.Meter()
    arrived = time.monotonic_ns() - 5_000_000  # due 5 ms ago
    trace: Trace = [meter.call(arrived, lambda a, b: a + b, 1, 2)]
    runs, finished, busy, _, late50, _, late_max, *_ = meter.take()
    trace += [(runs, finished), busy > 0, 4_000_000 <= late50 <= late_max]
    trace += [meter.call(0, time.sleep, 0.002), meter.take()[:2]]
    trace += [_raised(lambda: meter.call(0, lambda: 1 / 0)), meter.take()[:2]]
    trace += [meter.take()[4], _raised(lambda: meter.call(0)), _raised(lambda: meter.call(1.5, print))]
    trace += [_raised(lambda: meter.call(0, "not callable")), meter.take()[:2]]
    inside: list[int] = []
    trace += [meter.running, meter.call(0, lambda: inside.append(meter.running)), inside[0] > 0, meter.running]
    return trace


class _Owner:
    """An owner as ``HandleMeter`` asks one: each kind's account, with a meter, made on first use."""

    def __init__(self, engine: ModuleType, name: str) -> None:
        self.name = name
        self.asked: list[str] = []
        self.meter = engine.Meter()
        self.call = self.meter.call

    def account(self, kind: str) -> _Owner:
        self.asked.append(f"{self.name} {kind}")
        return self


def _handle_meters(engine: ModuleType) -> Trace:
    """``HandleMeter.call_soon``: which handles go through as they are and which are metered, as whose."""
    owner_var: contextvars.ContextVar[object] = contextvars.ContextVar("engines_owner", default=None)
    executor, node, nobody = object(), _Owner(engine, "node"), _Owner(engine, "nobody")

    class Loop(engine.HandleMeter, asyncio.SelectorEventLoop):  # type: ignore[misc, name-defined]
        def __init__(self) -> None:
            soon, at = asyncio.SelectorEventLoop.call_soon, asyncio.SelectorEventLoop.call_at
            engine.HandleMeter.__init__(self, owner_var, executor, asyncio.Task, soon, at, nobody)
            asyncio.SelectorEventLoop.__init__(self)

    ran: list[object] = []
    trace: Trace = []
    loop = Loop()
    # A handle whose context is no context fails as asyncio runs it: told here, not logged.
    loop.set_exception_handler(lambda _, context: ran.append(f"failed: {type(context.get('exception')).__name__}"))
    ours = contextvars.copy_context()
    ours.run(owner_var.set, executor)
    theirs = contextvars.copy_context()
    theirs.run(owner_var.set, node)
    ours.run(loop.call_soon, ran.append, "the executor's")
    loop.call_soon(ran.append, "the node's", context=theirs)
    theirs.run(loop.call_soon, ran.append, "the node's, scheduled in its context")
    loop.call_soon(ran.append, "nobody's")
    loop.call_soon(ran.append, "nobody's, in no context", context="not a context")  # type: ignore[arg-type]

    async def step() -> None:
        ran.append("a task's step")

    task = theirs.run(loop.create_task, step())
    # A function or a partial is metered like any handle; a function whose own attributes
    # name a task as its __self__ is told a task's step, as getattr tells it.
    loop.call_soon(lambda: ran.append("the node's function"), context=theirs)
    loop.call_soon(functools.partial(ran.append, "the node's partial"), context=theirs)

    def posing() -> None:
        ran.append("a function posing as a task's step")

    posing.__self__ = task  # type: ignore[attr-defined]
    loop.call_soon(posing, context=theirs)
    due = loop.time() - 0.005  # due 5 ms ago: that late, at least
    loop.call_at(due, ran.append, "the node's timer", context=theirs)
    theirs.run(loop.call_later, 0, ran.append, "the node's call_later")
    ours.run(loop.call_at, due, ran.append, "the executor's timer")
    trace += [node.asked, nobody.asked]
    loop.call_soon(loop.stop, context=ours)
    loop.run_forever()
    figures = node.meter.take()
    trace += [sorted(str(item) for item in ran), figures[:2], figures[6] >= 5_000_000, nobody.meter.take()[:2]]
    trace += [_raised(lambda: loop.call_soon()), _raised(lambda: loop.call_at(1.0))]  # type: ignore[call-arg]
    trace += [_raised(lambda: engine.HandleMeter(1, 2, 3, 4, 5, 6))]
    trace += [_raised(lambda: engine.HandleMeter(owner_var, executor, asyncio.Task, len, len))]
    loop.close()

    class Uninitialised(engine.HandleMeter, asyncio.SelectorEventLoop):  # type: ignore[misc, name-defined]
        def __init__(self) -> None:
            asyncio.SelectorEventLoop.__init__(self)

    bare = Uninitialised()
    trace += [_raised(lambda: bare.call_soon(print))]
    bare.close()
    return trace


def test_a_loops_handles_are_metered_as_whose_alike_on_both_engines() -> None:
    trace = _same_on_both(_handle_meters)
    # Asked once per owner and kind: the last owner's account is kept.
    assert trace[:2] == [["node loop_callback", "node loop_timer"], ["nobody loop_callback"]]
    assert trace[2] == sorted(
        [
            "the executor's", "the node's", "the node's, scheduled in its context", "nobody's", "a task's step",
            "the node's function", "the node's partial", "a function posing as a task's step",
            "the node's timer", "the node's call_later", "the executor's timer",
            "failed: AttributeError",  # a context that is none: in asyncio, as it would unmetered
        ]
    )  # fmt: skip
    assert trace[3:6] == [(6, 6), True, (1, 1)], "the node's four soon and two timers; one late 5 ms at least"
    assert [error[0] for error in trace[6:8]] == ["TypeError", "TypeError"]  # the loop's own methods say
    usage = "HandleMeter(owner: ContextVar, executor, task_type: type, call_soon: callable, call_at: callable, "
    assert trace[8:] == [
        ["TypeError", usage + "unattributed)"],
        ["TypeError", "HandleMeter() takes exactly 6 arguments (5 given)"],
        ["TypeError", "HandleMeter.__init__ was not called"],
    ]


def _kept_accounts(engine: ModuleType) -> Trace:
    """Ten owners' handles in turn, three rounds, then a seventeenth owner's: who was asked for
    an account, in order."""
    owner_var: contextvars.ContextVar[object] = contextvars.ContextVar("engines_owner", default=None)
    owners = [_Owner(engine, f"n{index}") for index in range(17)]
    asked: list[str] = []

    class Loop(engine.HandleMeter, asyncio.SelectorEventLoop):  # type: ignore[misc, name-defined]
        def __init__(self) -> None:
            soon, at = asyncio.SelectorEventLoop.call_soon, asyncio.SelectorEventLoop.call_at
            engine.HandleMeter.__init__(self, owner_var, object(), asyncio.Task, soon, at, _Owner(engine, "nobody"))
            asyncio.SelectorEventLoop.__init__(self)

    loop = Loop()
    contexts = []
    for owner in owners:
        context = contextvars.copy_context()
        context.run(owner_var.set, owner)
        contexts.append(context)

    def schedule(indexes: range) -> None:
        for index in indexes:
            loop.call_soon(len, "", context=contexts[index])
            loop.call_at(loop.time(), len, "", context=contexts[index])
        for owner in owners:
            asked.extend(owner.asked)
            owner.asked.clear()

    for _ in range(3):
        schedule(range(10))
    trace: Trace = [list(asked)]
    asked.clear()
    schedule(range(10, 17))  # sixteen kept: the seventeenth lets the oldest (n0) go
    schedule(range(2))  # n0 is asked again, and lets n1 go
    trace.append(list(asked))
    loop.close()
    return trace


def test_each_of_the_last_sixteen_owners_is_asked_for_its_account_once_alike_on_both_engines() -> None:
    """Ten nodes' tasks sleeping in turn each hit the kept accounts: no Python call a handle."""
    trace = _same_on_both(_kept_accounts)
    assert trace[0] == [f"n{index} {kind}" for index in range(10) for kind in ("loop_callback", "loop_timer")]
    assert trace[1] == [
        *(f"n{index} {kind}" for index in range(10, 17) for kind in ("loop_callback", "loop_timer")),
        "n0 loop_callback", "n0 loop_timer", "n1 loop_callback", "n1 loop_timer",
    ]  # fmt: skip


def test_a_metered_call_is_one_run_alike_on_both_engines() -> None:
    trace = _same_on_both(_metered_calls)
    assert trace == [
        3, (1, 1), True, True, None, (1, 1), ["ZeroDivisionError", "division by zero"], (1, 1),
        0, ["TypeError", "call(arrived, call, *args)"],
        ["TypeError", "'float' object cannot be interpreted as an integer"],
        ["TypeError", "'str' object is not callable"], (1, 1), 0, None, True, 0,
    ]  # fmt: skip


def test_work_is_metered_alike_on_both_engines() -> None:
    trace = _same_on_both(_metering)
    assert trace[:8] == [42, ["the context's"], "set inside", True, (1, 1), (0, 0, 0), True, True]
    assert trace[8:11] == [
        ["ZeroDivisionError", "division by zero"], (1, 1), ["TypeError", "run(context): a contextvars.Context"]
    ]
    assert trace[11:19] == [0, None, True, (1, 0), ["StopIteration", "done"], (0, 1), None, 0]
    assert trace[19:] == [0, True, (0, 1), 1, True, ["ValueError", "stuck_after: a positive number of nanoseconds"]]


# -- the first step ------------------------------------------------------------------------


@contextlib.contextmanager
def _loop_and_runner(engine: ModuleType) -> Iterator[tuple[asyncio.AbstractEventLoop, Any]]:
    """A loop that is not running and an idle runner of it (whose task never started)."""
    loop = asyncio.new_event_loop()
    idle = loop.create_future()

    async def runner_task() -> None:
        await idle

    task = loop.create_task(runner_task())
    try:
        yield loop, engine.Runner(task, contextvars.copy_context(), idle)
    finally:
        task.cancel()
        loop.run_until_complete(asyncio.gather(task, return_exceptions=True))
        loop.close()


def _first_steps(engine: ModuleType) -> Trace:
    variable: contextvars.ContextVar[str] = contextvars.ContextVar("engines_first_step")
    trace: Trace = []
    with _loop_and_runner(engine) as (loop, runner):
        runner.context.run(variable.set, "the runner's")
        meter = engine.Meter()

        def step(callback: Callable[..., Any], *args: Any, metered: bool = False) -> Any:
            work = engine.Work("entity", callback, True, 1, _done, None, args, meter=meter if metered else None)
            outcome = engine.first_step(loop, enter_task, leave_task, asyncio.CancelledError, runner, work)
            return outcome, work

        inside: list[object] = []

        async def done(a: int, b: int) -> int:
            inside.extend([asyncio.current_task(loop) is runner.task, runner.current is not None, a + b])
            inside.append(variable.get())
            variable.set("set by the callback")
            return a + b

        outcome, work = step(done, 1, 2, metered=True)
        trace += [outcome, inside, runner.current, runner.context[variable], work.started > 0, meter.take()[:2]]

        async def fails() -> None:
            raise ValueError("the callback's own")

        outcome, _ = step(fails)
        trace += [type(outcome).__name__, str(outcome), outcome.__traceback__ is not None]

        async def cancels_itself() -> None:
            raise asyncio.CancelledError

        trace += [step(cancels_itself)[0]]

        async def interrupted() -> None:
            raise KeyboardInterrupt

        trace += [_raised(lambda: step(interrupted))]
        future = loop.create_future()

        async def suspends() -> str:
            variable.set("before the await")
            await future
            return variable.get()

        outcome, work = step(suspends, metered=True)
        coro, yielded, context = outcome
        trace += [asyncio.iscoroutine(coro), yielded is future, context[variable], runner.context[variable]]
        trace += [meter.take()[:2], work.started > 0]
        future.set_result(None)
        trace += [_raised(lambda: context.run(coro.send, None))]

        def not_a_coroutine() -> None:
            return None

        outcome, _ = step(not_a_coroutine)
        trace += [type(outcome).__name__, str(outcome)]
        trace += [_raised(lambda: engine.first_step(loop, enter_task, leave_task, asyncio.CancelledError, "runner",
                                                    engine.Work("entity", done, True, 1, _done)))]  # fmt: skip

        def refuse(loop: object, task: object) -> None:
            raise RuntimeError("the task cannot be entered")

        broken = engine.Work("entity", done, True, 1, _done, None, (1, 1))
        trace += [
            _raised(lambda: engine.first_step(loop, refuse, leave_task, asyncio.CancelledError, runner, broken)),
            runner.current,
        ]
    return trace


def test_the_first_step_ends_alike_on_both_engines() -> None:
    """Done, failed, cancelled by the callback itself, interrupted, suspended: in the
    runner's task, in a copy of its context, with what it carries set meanwhile."""
    trace = _same_on_both(_first_steps)
    assert trace[:6] == [None, [True, True, 3, "the runner's"], None, "the runner's", True, (1, 1)]
    assert trace[6:9] == ["ValueError", "the callback's own", True]
    assert trace[9:11] == [None, ["KeyboardInterrupt", ""]]
    assert trace[11:15] == [True, True, "before the await", "the runner's"]
    assert trace[15:17] == [(1, 0), True]  # begun, not finished
    assert trace[17] == ["StopIteration", "before the await"]
    assert trace[18:20] == ["AttributeError", "'NoneType' object has no attribute 'send'"]
    assert trace[-2:] == [["RuntimeError", "the task cannot be entered"], None]


# -- the async chain's timers --------------------------------------------------------------


def _express_timers(engine: ModuleType, context: Context) -> Trace:
    """Timers the chain calls (``call_timers``) and runs (``run_fired``): through a runner,
    or handed back (no idle runner, a failure, a suspension); other timers left to Python."""
    node = Node(f"engines_express_{engine.__name__.rpartition('.')[2]}", context=context)
    guard = GuardCondition(callback=None, callback_group=None, context=context)
    told: Trace = []
    calls: list[str] = []
    behaviour = ["done"]

    async def callback() -> None:
        calls.append(behaviour[0])
        if behaviour[0] == "fails":
            raise ValueError("the timer's callback failed")
        if behaviour[0] == "suspends":
            await asyncio.sleep(0)

    class Holder:
        """The entity whose ``callback`` attribute the chain reads."""

    holder = Holder()
    holder.callback = callback  # type: ignore[attr-defined]
    timer = node.create_timer(0.001, lambda: None)
    quiet = node.create_timer(100.0, lambda: None)
    try:
        with _loop_and_runner(engine) as (loop, runner):
            slots = engine.Slots(1)
            marker = engine.Work(holder, callback, True, 1, _done)
            route = engine.Route(
                first=timer.handle, entry="entry", lane="lane", slots=slots, marker=marker, entity=holder,
                token=engine.Token(node), callback="callback",
            )  # fmt: skip

            def record(name: str) -> Callable[..., None]:
                return lambda *args: told.append([name, *(arg if isinstance(arg, str | None) else type(arg).__name__
                                                         for arg in args)])  # fmt: skip

            express = engine.Express(
                notifier=engine.Notifier(guard=guard.handle), routes=engine.Routes(), take_lock=engine.Lock(),
                loop=loop, ready_queue=[], eager=[], run_eager=record("run_eager"), enter_task=enter_task,
                leave_task=leave_task, on_done=record("on_done"), done_waiters=[], slow=record("slow"),
                suspended=record("suspended"), failed=record("failed"), release_pending=record("release_pending"),
                take_rest=record("take_rest"), cancelled_error=asyncio.CancelledError,
            )  # fmt: skip
            routes = {timer.handle.pointer: route}

            def fire() -> list[str]:
                _until(timer.handle.is_timer_ready)
                rest = express.call_timers(routes, [timer.handle.pointer, quiet.handle.pointer])
                express.run_fired()
                return ["quiet" if address == quiet.handle.pointer else "other" for address in rest]

            told.append(["rest", fire()])  # no idle runner: handed back
            slots.park(runner)
            for behaviour[0] in ("done", "fails", "suspends"):
                told.append(["rest", fire(), slots.running, express.expressed])
                if behaviour[0] != "done":
                    slots.next(marker)  # what the lane would do with the slot it was handed
            timer.cancel()
            told.append(["cancelled", express.call_timers(routes, [timer.handle.pointer]) == [timer.handle.pointer]])
            express.run_fired()
            told.append([calls, express.expressed, _raised(lambda: express.call_timers([], []))])
    finally:
        guard.destroy()
        node.destroy_node()
    return told


def test_the_chains_timers_are_called_and_run_alike_on_both_engines(context: Context) -> None:
    compiled, python = (_express_timers(engine, context) for engine in BOTH)
    assert python == compiled
    assert compiled == [
        ["slow", "entry", None],
        ["rest", ["quiet"]],
        ["rest", ["quiet"], 0, 1],  # ran through the runner, its slot given back
        ["failed", "entry", None, "ValueError"],
        ["rest", ["quiet"], 1, 2],  # the slot is the lane's to give back (failed)
        ["suspended", "entry", None, "Runner", "coroutine", None, "Context", "int"],
        ["rest", ["quiet"], 1, 3],
        ["cancelled", True],
        [["done", "fails", "suspends"], 3, ["TypeError", "call_timers(routes: dict, ready: iterable)"]],
    ]


# -- takes, answers and waits on real entities ---------------------------------------------


@pytest.fixture
def node(context: Context) -> Iterator[Node]:
    made = Node("engines", context=context)
    yield made
    made.destroy_node()


def _takes(engine: ModuleType, node: Node, name: str) -> Trace:
    publisher = node.create_publisher(Int64, f"engines_take_{name}", 10)
    subscription = node.create_subscription(Int64, f"engines_take_{name}", lambda msg: None, 10)
    _until(lambda: publisher.get_subscription_count() >= 1)
    taker = engine.Taker(subscription=subscription.handle, message_type=Int64, publisher_gid=HAS_PUBLISHER_GID)
    trace: Trace = [taker.take()]
    for n in (1, 2, 3):
        publisher.publish(Int64(data=n))
    first = taker.take()
    pair = taker.take_with_info()
    third = taker.take()
    assert pair is not None
    message, info = pair
    trace += [first, message, sorted(info), info["reception_sequence_number"], third, taker.take()]
    plain = engine.Taker(subscription=subscription.handle, message_type=Int64)
    publisher.publish(Int64(data=4))
    pair = plain.take_with_info()
    assert pair is not None
    trace += [pair[0], "publisher_gid" in pair[1]]
    taker.close()
    plain.close()
    trace += [_raised(taker.take), _raised(lambda: engine.Taker(subscription=0, message_type=Int64))]
    trace += [_raised(lambda: engine.Taker(subscription=subscription.handle, message_type=str))]
    node.destroy_publisher(publisher)
    node.destroy_subscription(subscription)
    return trace


def test_takes_give_the_same_messages_and_info_on_both_engines(node: Node) -> None:
    compiled, python = (_takes(engine, node, name) for engine, name in zip(BOTH, ("c", "p"), strict=True))
    assert python == compiled
    keys = ["publication_sequence_number", "received_timestamp", "reception_sequence_number", "source_timestamp"]
    assert compiled[:5] == [None, Int64(data=1), Int64(data=2), sorted(keys + ["publisher_gid"] * HAS_PUBLISHER_GID),
                            None]  # fmt: skip
    assert compiled[5:9] == [Int64(data=3), None, Int64(data=4), False]
    assert compiled[9] == ["RuntimeError", "Taker not initialised, or closed"]


def _answers(engine: ModuleType, node: Node, name: str) -> Trace:
    service: Any = node.create_service(SetBool, f"engines_serve_{name}", lambda request, response: response)
    client: Any = node.create_client(SetBool, f"engines_serve_{name}")
    assert client.wait_for_service(timeout_sec=TIMEOUT)
    server = engine.Server(service=service.handle, srv_type=SetBool)
    caller = engine.Caller(client=client.handle, srv_type=SetBool)
    trace: Trace = [server.take(), caller.take(), server.closed]
    first = client.call_async(SetBool.Request(data=True))
    second = client.call_async(SetBool.Request(data=False))
    taken: list[Any] = []

    def take_request() -> bool:
        request = server.take()
        if request is not None:
            taken.append(request)
        return len(taken) == 2

    _until(take_request)
    trace += [[request.data for request, _ in taken]]
    trace += [_raised(lambda: server.send("not a response", taken[0][1]))]
    trace += [_raised(lambda: server.send(SetBool.Response(), b"not a header"))]
    trace += [server.send(SetBool.Response(success=False, message="second, answered first"), taken[1][1])]
    trace += [server.send(SetBool.Response(success=True, message="first"), taken[0][1], True)]
    answers: list[Any] = []

    def take_response() -> bool:
        answer = caller.take()
        if answer is not None:
            answers.append(answer)
        return len(answers) == 2

    _until(take_response)
    by_call = {id(client.get_pending_request(sequence)): response for sequence, response in answers}
    trace += [by_call[id(first)], by_call[id(second)], caller.take()]
    trace += [[sequence - answers[0][0] for sequence, _ in answers]]
    for future in (first, second):
        client.remove_pending_request(future)
    server.close()
    caller.close()
    trace += [server.closed, _raised(server.take), _raised(lambda: server.send(SetBool.Response(), taken[0][1]))]
    trace += [_raised(caller.take), _raised(lambda: engine.Server(service=service.handle, srv_type=Int64))]
    node.destroy_service(service)
    node.destroy_client(client)
    return trace


def test_requests_answers_and_responses_are_the_same_on_both_engines(node: Node) -> None:
    compiled, python = (_answers(engine, node, name) for engine, name in zip(BOTH, ("c", "p"), strict=True))
    assert python == compiled
    assert compiled[:4] == [None, None, False, [True, False]]
    assert compiled[4] == ["TypeError", "a service callback returned str, not SetBool_Response"]
    assert compiled[5] == ["ValueError", "not a header from take()"]
    assert compiled[6:11] == [
        True, True, SetBool.Response(success=True, message="first"),
        SetBool.Response(success=False, message="second, answered first"), None,
    ]  # fmt: skip
    closed = ["RuntimeError", "Server not initialised, or closed"]
    assert compiled[12:16] == [True, closed, closed, ["RuntimeError", "Caller not initialised, or closed"]]


def _waits(engine: ModuleType, context: Context, node: Node) -> Trace:
    guard = GuardCondition(callback=None, callback_group=None, context=context)
    quiet = GuardCondition(callback=None, callback_group=None, context=context)
    timer = node.create_timer(0.05, lambda: None)
    names = {guard.handle.pointer: "guard", quiet.handle.pointer: "quiet", timer.handle.pointer: "timer"}

    def named(ready: tuple[list[int], ...]) -> Any:
        return [[names[address] for address in kind] for kind in ready] if ready else ready

    try:
        wait_set = engine.WaitSet(context.handle, guard_conditions=[guard.handle, quiet.handle], timers=[timer.handle])
        trace: Trace = [named(wait_set.wait(1_000_000)), named(wait_set.wait(0, True))]
        guard.trigger()
        trace += [named(wait_set.wait(int(TIMEOUT * 1e9)))]
        trace += [named(wait_set.wait(int(TIMEOUT * 1e9)))]  # the timer's period is the wait's
        wait_set.close()
        wait_set.close()  # again: nothing left to let go
        trace += [_raised(lambda: wait_set.wait(0)), _raised(lambda: engine.WaitSet(0))]
        trace += [_raised(lambda: engine.WaitSet(context.handle, timers=[timer.handle.pointer]))]
        trace += [_raised(lambda: engine.WaitSet(context.handle, notifier="not a notifier"))]
        trace += [_raised(lambda: engine.poll(0, 0))]
    finally:
        quiet.destroy()
        guard.destroy()
        node.destroy_timer(timer)
    return trace


def test_waits_report_the_same_on_both_engines(context: Context, node: Node) -> None:
    compiled, python = (_waits(engine, context, node) for engine in BOTH)
    assert python == compiled
    assert compiled[:4] == [(), (), [[], ["guard"], [], [], [], []], [[], [], ["timer"], [], [], []]]
    assert compiled[4] == ["RuntimeError", "WaitSet not initialised, or closed"]
    assert compiled[5] == ["TypeError", "an rclpy handle is needed (the entity's .handle), not int"]


@pytest.mark.skipif(not HAS_PUBLISHER_GID, reason="rclpy 7's message info has no publisher_gid")
def test_a_publishers_gid_in_the_graph_is_the_one_its_handle_has(node: Node) -> None:
    """What the Python engine reads from the ROS graph (``_message_info``) is the compiled engine's gid."""
    publisher = node.create_publisher(Int64, "engines_gid", 10)
    node.create_publisher(Int64, "engines_gid_other", 10)
    assert _message_info._gid_in_graph(node, publisher.topic_name) == _fastpath.publisher_gid(publisher.handle)
    assert _raised(lambda: _pyengine.publisher_gid(publisher.handle))[0] == "NotImplementedError"
    node.create_publisher(Int64, "engines_gid", 10)  # two of one node on the topic: which is which is unknown
    assert _message_info._gid_in_graph(node, publisher.topic_name) is None


# -- the executor on each engine, in child processes ----------------------------------------

SCENARIOS = Path(__file__).with_name("engine_scenarios.py")

_KEYS = ["publication_sequence_number", "received_timestamp", "reception_sequence_number", "source_timestamp"]
_INFO = sorted(_KEYS + ["publisher_gid"] * HAS_PUBLISHER_GID)

#: What each scenario's log must be (on both engines).
EXPECTED: dict[str, list[Any]] = {
    "exclusive_group": [
        ["plain start", 1, 1], ["plain end", 1], ["async start", 1, 1], ["async end", 1],
        ["plain start", 2, 1], ["plain end", 2],
    ],
    "keep_last": [["waiting", 2, "dropped", 3], ["got", 1, 5, 6]],
    "spin_once": [["ran", [1]], ["ran", [2]], ["ran", [3]], ["ran", []]],
    "service_chain_plain": [entry for n in range(1, 6) for entry in (["served", n], ["answered", f"call {n}"])],
    "service_chain_async": [entry for n in range(1, 6) for entry in (["served", n], ["answered", f"call {n}"])],
    "intra_process": [[n, n, True, _INFO] for n in (1, 2, 3)],
}  # fmt: skip


def _run(scenario: str, engine: str) -> dict[str, Any]:
    result = subprocess.run(
        [sys.executable, str(SCENARIOS), scenario],
        env=os.environ | {_engine.VARIABLE: engine},
        capture_output=True,
        text=True,
        timeout=90,
        check=False,
    )
    lines = [line for line in result.stdout.splitlines() if line.startswith("{")]
    assert result.returncode == 0 and lines, result.stderr[-3000:]
    outcome: dict[str, Any] = json.loads(lines[-1])
    return outcome


@pytest.mark.slow  # two child processes per scenario, each starting ROS
@pytest.mark.parametrize("scenario", sorted(EXPECTED))
def test_the_executor_logs_the_same_events_on_both_engines(scenario: str) -> None:
    compiled, python = (_run(scenario, engine) for engine in ("compiled", "python"))
    assert (compiled["engine"], python["engine"]) == ("compiled", "python")
    assert python["log"] == compiled["log"]
    assert compiled["log"] == EXPECTED[scenario]


# -- choosing the engine ---------------------------------------------------------------------

#: A child that cannot import the compiled engine (a meta path finder refuses
#: it), runs an executor (a timer, a message), and says which engine ran.
_NO_COMPILED = textwrap.dedent(
    """
    import importlib.abc, sys, threading

    class Refuse(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name == "container.executor._fastpath":
                raise ImportError("no compiled engine in this process")
            return None

    if sys.argv[1] == "refuse":
        sys.meta_path.insert(0, Refuse())
    import rclpy
    from rclpy.node import Node
    from std_msgs.msg import Int64
    from container import AsyncioExecutor
    from container.executor import _engine

    rclpy.init()
    node = Node("engines_fallback")
    got = threading.Event()
    publisher = node.create_publisher(Int64, "engines_fallback", 10)
    node.create_subscription(Int64, "engines_fallback", lambda msg: got.set(), 10)
    node.create_timer(0.01, lambda: publisher.publish(Int64(data=1)))
    executor = AsyncioExecutor()
    AsyncioExecutor().shutdown()  # a second executor: said once all the same
    executor.add_node(node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    print("ran on", _engine.ENGINE, got.wait(10.0), flush=True)
    executor.shutdown(timeout_sec=5.0)
    thread.join(5.0)
    rclpy.try_shutdown()
    """
)


def _choose(how: str, value: str | None) -> tuple[str, list[str]]:
    """The child's answer and the lines of its log that name the engine."""
    env = {key: item for key, item in os.environ.items() if key != _engine.VARIABLE}
    if value is not None:
        env[_engine.VARIABLE] = value
    result = subprocess.run(
        [sys.executable, "-c", _NO_COMPILED, how], env=env, capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout.strip(), [line for line in result.stderr.splitlines() if "engine" in line]


@pytest.mark.slow  # a child process starting ROS
def test_without_the_compiled_engine_the_python_one_runs_and_says_why_once() -> None:
    answer, lines = _choose("refuse", None)
    assert answer == "ran on python True"
    assert lines == [
        "the compiled engine could not be imported (no compiled engine in this process):"
        " the executor runs on the python engine"
    ]


@pytest.mark.slow  # a child process starting ROS
def test_an_unknown_engine_is_said_in_one_line_and_the_compiled_one_runs() -> None:
    answer, lines = _choose("allow", "turbo")
    assert answer == "ran on compiled True"
    assert lines == [
        "CONTAINER_EXECUTOR_ENGINE='turbo' is not one of compiled, python: the executor runs on the compiled engine"
    ]


@pytest.mark.slow  # a child process starting ROS
def test_the_engine_asked_for_runs_without_a_word() -> None:
    assert _choose("allow", "python") == ("ran on python True", [])
