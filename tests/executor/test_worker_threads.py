"""Lane worker threads: started when plain work arrives, gone once idle."""

from __future__ import annotations

import threading

import pytest
from rclpy.context import Context
from rclpy.node import Node

from container import AsyncioExecutor
from container.executor import _lanes
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
