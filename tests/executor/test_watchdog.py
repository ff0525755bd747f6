"""The loop watchdog: an ``async def`` callback that blocks stalls no plain callback."""

from __future__ import annotations

import itertools
import logging
import threading
import time

import pytest
from rclpy.context import Context
from rclpy.node import Node

from container import AsyncioExecutor


def test_a_blocking_async_callback_is_reported_and_plain_callbacks_keep_their_rate(
    context: Context, caplog: pytest.LogCaptureFixture
) -> None:
    executor = AsyncioExecutor(context=context, stall_after=0.5)
    stuck = Node("watchdog_stuck", context=context)
    steady = Node("watchdog_steady", context=context)
    ticks: list[float] = []
    blocked = threading.Event()
    unblock = threading.Event()

    async def block() -> None:
        if not blocked.is_set():
            blocked.set()
            unblock.wait(10.0)  # blocking code in an async def: the fault

    stuck.create_timer(0.05, block)
    steady.create_timer(0.1, lambda: ticks.append(time.monotonic()))
    executor.add_node(stuck)
    executor.add_node(steady)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    caplog.set_level(logging.WARNING, logger="container.executor")
    spinner.start()
    try:
        assert blocked.wait(10.0)
        stalled_at = time.monotonic()
        deadline = stalled_at + 10.0
        while not any("event loop stuck" in r.message for r in caplog.records) and time.monotonic() < deadline:
            time.sleep(0.05)  # the watchdog logs from its own thread; no event to wait on
        reported = time.monotonic() - stalled_at
        during = len(ticks)
        while len(ticks) < during + 10 and time.monotonic() < deadline:
            time.sleep(0.05)
        unblock.set()
    finally:
        unblock.set()
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)
        stuck.destroy_node()
        steady.destroy_node()
    report = next(r.message for r in caplog.records if "event loop stuck" in r.message)
    assert reported < 0.5 + 1.0, "reported within a second of the threshold"
    assert "block" in report and "watchdog_stuck" in report and "unblock.wait" in report
    gaps = [b - a for a, b in itertools.pairwise(ticks)]
    assert max(gaps) < 3 * 0.1, "the plain timer kept its rate through the stall"
    assert any("free again" in r.message for r in caplog.records)
