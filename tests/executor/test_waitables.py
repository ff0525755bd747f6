"""A custom waitable whose own code raises is reported once and set aside; the rest runs on.

rclpy 9 (Kilted) gave ``Waitable`` an ``__enter__`` that raises
``NotImplementedError`` unless a subclass defines it, so a waitable written
for Jazzy fails there on every wait. rclpy's executors raise that out of
``spin``; this executor logged it on every loop (32,687 records in 2 s)
before it set such a waitable aside.
"""

from __future__ import annotations

import collections
import time
from typing import Any

import pytest
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.context import Context
from rclpy.guard_condition import GuardCondition
from rclpy.node import Node
from rclpy.waitable import NumberOfEntities, Waitable

from container import AsyncioExecutor

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
    ticks = _host(executor, node, waitable, 1.0)
    err = capfd.readouterr().err
    reports = [line for line in err.splitlines() if "EnteringWaitable raised RuntimeError" in line]
    assert len(reports) == 1, err[-3000:]
    assert "[waitable_host]" in reports[0] and f"in {failing}()" in reports[0], reports[0]
    assert waitable.calls[failing] == 1, waitable.calls  # never called again once set aside
    assert waitable.executed == 0
    assert ticks >= 40, ticks  # the node's timer ran on at its 100 Hz (about 100 in 1 s)


def test_a_waitable_written_for_jazzy_runs_or_is_set_aside_as_its_rclpy_asks(
    context: Context, executor: AsyncioExecutor, capfd: pytest.CaptureFixture[str]
) -> None:
    """No ``__enter__``: rclpy 7 (Jazzy) needs none, rclpy 9 raises NotImplementedError."""
    node = Node("jazzy_waitable_host", context=context)
    waitable = GuardWaitable(node)
    ticks = _host(executor, node, waitable, 1.0)
    reports = [line for line in capfd.readouterr().err.splitlines() if "GuardWaitable raised" in line]
    assert ticks >= 40, ticks
    if _rclpy_asks_for_enter():
        assert len(reports) == 1 and "NotImplementedError in __enter__()" in reports[0], reports
        assert waitable.executed == 0
    else:
        assert reports == []
        assert waitable.executed > 0
