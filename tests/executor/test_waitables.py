"""A custom waitable whose own code keeps raising is reported once and set aside; the rest runs on.

rclpy 9 (Kilted) gave ``Waitable`` an ``__enter__`` that raises
``NotImplementedError`` unless a subclass defines it, so a waitable written
for Jazzy fails there on every wait. rclpy's executors raise that out of
``spin``; this executor logged it on every loop (32,687 records in 2 s)
before it set such a waitable aside.

One that raises only while it is half built (Kilted's ``ActionClient`` adds
itself to its node before it makes its lock) is tried again and runs.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any

import pytest
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.context import Context
from rclpy.guard_condition import GuardCondition
from rclpy.node import Node
from rclpy.waitable import NumberOfEntities, Waitable

from container import AsyncioExecutor

TIMEOUT = 10.0

#: The methods of a waitable the executor calls, each made to raise in turn.
FAILING = ("__enter__", "get_num_entities", "add_to_wait_set", "is_ready", "take_data")


class GuardWaitable(Waitable):  # type: ignore[type-arg, unused-ignore]  # generic from rclpy 9
    """A waitable over a guard condition of its own, written as rclpy's tests write one
    (no ``__enter__``/``__exit__``: what a waitable written for Jazzy looks like)."""

    def __init__(self, node: Node, *, failing: str | None = None) -> None:
        # rclpy 7's is untyped.
        super().__init__(MutuallyExclusiveCallbackGroup())  # type: ignore[no-untyped-call, unused-ignore]
        self.guard = GuardCondition(None, None, context=node.context)
        self.failing = failing
        self.calls: collections.Counter[str] = collections.Counter()
        self.index: int | None = None
        self.executed = 0

    def _call(self, name: str) -> None:
        self.calls[name] += 1
        if name == self.failing:
            raise RuntimeError(f"{name} is broken")

    def is_ready(self, wait_set: Any) -> bool:
        self._call("is_ready")
        return self.index is not None and bool(wait_set.is_ready("guard_condition", self.index))

    def take_data(self) -> Any:
        self._call("take_data")
        return "taken"

    async def execute(self, taken_data: Any) -> None:
        self.executed += 1

    def get_num_entities(self) -> NumberOfEntities:
        self._call("get_num_entities")
        return NumberOfEntities(0, 1, 0, 0, 0, 0)

    def add_to_wait_set(self, wait_set: Any) -> None:
        self._call("add_to_wait_set")
        self.index = wait_set.add_guard_condition(self.guard.handle)


class EnteringWaitable(GuardWaitable):
    """The same, with the context-manager methods rclpy 9 asks for."""

    def __enter__(self) -> None:
        self._call("__enter__")

    def __exit__(self, *exc_info: object) -> None:
        pass


def _rclpy_asks_for_enter() -> bool:
    """Whether rclpy's own ``Waitable.__enter__`` raises (rclpy 9 and later)."""
    try:
        Waitable.__enter__(object())  # type: ignore[arg-type]
    except NotImplementedError:
        return True
    return False


def _host(executor: AsyncioExecutor, node: Node, waitable: GuardWaitable, seconds: float) -> int:
    """Spin ``node`` with ``waitable`` for ``seconds``, triggering the waitable's guard
    all along from the node's own 100 Hz timer; how many times the timer ran.
    Everything is taken down afterwards."""
    ticks = [0]

    def tick() -> None:
        ticks[0] += 1
        waitable.guard.trigger()

    node.add_waitable(waitable)
    executor.add_node(node)
    timer = node.create_timer(0.01, tick)
    try:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
    finally:
        node.destroy_timer(timer)
        executor.remove_node(node)
        node.remove_waitable(waitable)
        waitable.guard.destroy()
        node.destroy_node()
    return ticks[0]


@pytest.mark.parametrize("failing", FAILING)
def test_a_waitable_that_raises_is_reported_once_and_set_aside(
    failing: str, context: Context, executor: AsyncioExecutor, capfd: pytest.CaptureFixture[str]
) -> None:
    node = Node("waitable_host", context=context)
    waitable = EnteringWaitable(node, failing=failing)
    ticks = _host(executor, node, waitable, 1.5)
    err = capfd.readouterr().err
    reports = [line for line in err.splitlines() if "EnteringWaitable raised RuntimeError" in line]
    assert len(reports) == 1, err[-3000:]
    assert "[waitable_host]" in reports[0] and f"in {failing}()" in reports[0], reports[0]
    assert "4 times in a row" in reports[0], reports[0]
    # Tried again three times (5 ms, 50 ms, 500 ms after), never called again once set aside.
    assert waitable.calls[failing] == 4, waitable.calls
    assert waitable.executed == 0
    assert ticks >= 60, ticks  # the node's timer ran on at its 100 Hz (about 150 in 1.5 s)


def test_a_waitable_written_for_jazzy_runs_or_is_set_aside_as_its_rclpy_asks(
    context: Context, executor: AsyncioExecutor, capfd: pytest.CaptureFixture[str]
) -> None:
    """No ``__enter__``: rclpy 7 (Jazzy) needs none, rclpy 9 raises NotImplementedError."""
    node = Node("jazzy_waitable_host", context=context)
    waitable = GuardWaitable(node)
    ticks = _host(executor, node, waitable, 1.5)
    reports = [line for line in capfd.readouterr().err.splitlines() if "GuardWaitable raised" in line]
    assert ticks >= 60, ticks
    if _rclpy_asks_for_enter():
        assert len(reports) == 1 and "NotImplementedError in __enter__()" in reports[0], reports
        assert waitable.executed == 0
    else:
        assert reports == []
        assert waitable.executed > 0


class HalfBuiltWaitable(EnteringWaitable):
    """Added to its node before it is whole, as Kilted's ``ActionClient`` is: until
    :meth:`finish` its ``get_num_entities`` raises ``AttributeError``."""

    def __init__(self, node: Node) -> None:
        super().__init__(node)
        self.tried = threading.Event()
        self.ran = threading.Event()

    def finish(self) -> None:
        self.lock = threading.Lock()

    # Held while a wait set holds it, as rclpy's own waitables hold their handles:
    # the guard is destroyed while the executor spins on another thread.
    def __enter__(self) -> None:
        super().__enter__()
        self.guard.handle.__enter__()

    def __exit__(self, *exc_info: object) -> None:
        self.guard.handle.__exit__(None, None, None)

    def get_num_entities(self) -> NumberOfEntities:
        self.tried.set()
        with self.lock:  # AttributeError until finish()
            return super().get_num_entities()

    async def execute(self, taken_data: Any) -> None:
        await super().execute(taken_data)
        self.ran.set()


def test_a_waitable_seen_half_built_is_tried_again_and_runs(
    context: Context, spinning: AsyncioExecutor, capfd: pytest.CaptureFixture[str]
) -> None:
    node = Node("half_built_host", context=context)
    spinning.add_node(node)
    waitable = HalfBuiltWaitable(node)
    try:
        node.add_waitable(waitable)  # the executor's rebuild sees it at once, on its own thread
        # Every call before finish() raised.
        assert waitable.tried.wait(TIMEOUT), "the executor never looked at the waitable"
        waitable.finish()
        waitable.guard.trigger()  # level-triggered: seen by the first wait that holds it
        assert waitable.ran.wait(TIMEOUT), waitable.calls
        reports = [line for line in capfd.readouterr().err.splitlines() if "HalfBuiltWaitable raised" in line]
        assert reports == []
    finally:
        spinning.remove_node(node)
        node.remove_waitable(waitable)
        waitable.guard.destroy()
        node.destroy_node()
