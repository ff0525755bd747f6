"""Helpers shared by the lifecycle tests: running coroutines, recording transition events."""

from __future__ import annotations

import asyncio
import functools
import threading
import time
from collections.abc import Coroutine
from dataclasses import dataclass
from typing import Any, TypeVar

from lifecycle_msgs.msg import TransitionEvent
from rclpy.node import Node
from rclpy.qos import QoSProfile

from container import AsyncioExecutor
from tests.waiting import wait_until, wait_until_async

T = TypeVar("T")


def run(executor: AsyncioExecutor, coro: Coroutine[Any, Any, T], *, timeout: float = 20.0) -> T:
    """Run ``coro`` on the executor's loop while it serves the nodes; fail on timeout."""
    result: list[T] = []

    async def main() -> None:
        result.append(await coro)

    executor.spin_until_future_complete(main(), timeout_sec=timeout)
    assert result, f"did not finish within {timeout} s"
    return result[0]


@dataclass(frozen=True)
class Event:
    node: str
    start: str
    goal: str
    received: float


class TransitionLog:
    """Every ``transition_event`` of some nodes, in the order they arrived (any thread)."""

    def __init__(self, observer: Node, nodes: list[str]) -> None:
        self.events: list[Event] = []
        self._changed = threading.Condition()
        self._subscriptions = {
            name: observer.create_subscription(
                TransitionEvent,
                f"{name}/transition_event",
                functools.partial(self._record, name),
                QoSProfile(depth=100),
            )
            for name in nodes
        }

    def _record(self, name: str, msg: TransitionEvent) -> None:
        with self._changed:
            self.events.append(
                Event(name, msg.start_state.label, msg.goal_state.label, time.monotonic())
            )
            self._changed.notify_all()

    def _unmatched(self) -> list[str]:
        return [name for name, sub in self._subscriptions.items() if sub.get_publisher_count() == 0]

    def _unmatched_text(self) -> str:
        return f"transition_event publishers of {self._unmatched()}"

    def wait_matched(self, *, timeout: float = 10.0) -> None:
        """Block until each node's ``transition_event`` publisher is discovered."""
        wait_until(lambda: not self._unmatched(), self._unmatched_text, timeout=timeout)

    async def wait_matched_async(self, *, timeout: float = 10.0) -> None:
        """:meth:`wait_matched` from the executor's loop, which must keep running meanwhile."""
        await wait_until_async(lambda: not self._unmatched(), self._unmatched_text, timeout=timeout)

    def pairs(self, node: str | None = None) -> list[tuple[str, str]]:
        with self._changed:
            return [(e.start, e.goal) for e in self.events if node is None or e.node == node]

    def steps(self) -> list[tuple[str, str]]:
        """``(node, goal)`` of every event, in arrival order."""
        with self._changed:
            return [(e.node, e.goal) for e in self.events]

    def wait_for(
        self, node: str, goal: str, *, after: int = 0, timeout: float = 10.0
    ) -> Event:
        """Block until ``node`` reports reaching ``goal`` (among events from index ``after``)."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                for event in self.events[after:]:
                    if event.node == node and event.goal == goal:
                        return event
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise AssertionError(
                        f"{node} did not reach {goal} within {timeout} s; events: "
                        f"{[(e.node, e.start, e.goal) for e in self.events]}"
                    )
                self._changed.wait(remaining)

    async def wait_for_async(
        self, node: str, goal: str, *, after: int = 0, timeout: float = 10.0
    ) -> Event:
        """:meth:`wait_for` from the executor's loop, which must keep running meanwhile."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                return self.wait_for(node, goal, after=after, timeout=0)
            except AssertionError:
                if time.monotonic() > deadline:
                    raise
            await asyncio.sleep(0.01)

    def __len__(self) -> int:
        with self._changed:
            return len(self.events)
