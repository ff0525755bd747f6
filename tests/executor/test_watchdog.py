"""The loop watchdog: an ``async def`` callback that blocks stalls no plain callback."""

from __future__ import annotations

import itertools
import logging
import threading
import time

import pytest
from rclpy.context import Context
from rclpy.node import Node
from std_msgs.msg import Int64

from container import AsyncioExecutor


@pytest.mark.parametrize("via", ["timer", "message"])
def test_a_blocking_async_callback_is_reported_and_plain_callbacks_keep_their_rate(
    context: Context, caplog: pytest.LogCaptureFixture, via: str
) -> None:
    """``via="message"``: the blocking callback is a subscription's, reached by
    a message another callback published in this process, which the compiled
    path (``Express``) runs: reported and relieved all the same."""
    executor = AsyncioExecutor(context=context, stall_after=0.5)
    stuck = Node("watchdog_stuck", context=context)
    steady = Node("watchdog_steady", context=context)
    ticks: list[float] = []
    blocked = threading.Event()
    unblock = threading.Event()

    calls = [0]

    async def block(*_: object) -> None:
        calls[0] += 1
        # Via a message, not the first: its lane has an idle runner by then,
        # which the compiled path needs.
        if not blocked.is_set() and (via == "timer" or calls[0] >= 5):
            blocked.set()
            unblock.wait(10.0)  # blocking code in an async def: the fault

    if via == "timer":
        # rclpy 9 annotates timer callbacks as plain
        stuck.create_timer(0.05, block)  # type: ignore[arg-type, unused-ignore]
    else:
        chain = stuck.create_publisher(Int64, "watchdog_chain", 10)
        stuck.create_subscription(Int64, "watchdog_chain", block, 10)  # type: ignore[arg-type]  # rclpy types only plain callbacks

        async def kick() -> None:
            chain.publish(Int64())

        # rclpy 9 annotates timer callbacks as plain
        stuck.create_timer(0.05, kick)  # type: ignore[arg-type, unused-ignore]
    steady.create_timer(0.1, lambda: ticks.append(time.monotonic()))
    executor.add_node(stuck)
    executor.add_node(steady)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    caplog.set_level(logging.WARNING, logger="container.executor")
    spinner.start()
    try:
        assert blocked.wait(10.0)
        express = executor._dispatcher._hot._express
        expressed = express.expressed if express is not None else 0
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
    if via == "message":
        assert expressed > 0, "the blocking callback did not run on the compiled path"


def test_one_watchdog_thread_serves_every_spin_and_still_reports(
    context: Context, caplog: pytest.LogCaptureFixture
) -> None:
    """A ``spin_once()`` loop, rclpy's usual pattern, started and joined a
    watchdog thread on every call (about 150 us each, most of the call)."""
    executor = AsyncioExecutor(context=context, stall_after=0.3)
    node = Node("watchdog_spin_once", context=context)
    executor.add_node(node)

    def watchdogs() -> list[threading.Thread]:
        return [t for t in threading.enumerate() if t.name == "loop-watchdog"]

    try:
        executor.spin_once(timeout_sec=0)
        first = watchdogs()
        assert len(first) == 1
        for _ in range(20):
            executor.spin_once(timeout_sec=0)
            assert executor.watchdog is None, "the watchdog is the executor's only while it spins"
        assert watchdogs() == first, "a spin started a watchdog thread of its own"
        blocked: list[float] = []

        async def block() -> None:
            if not blocked:
                blocked.append(time.monotonic())
                time.sleep(0.8)  # blocking code in an async def: the fault

        caplog.set_level(logging.WARNING, logger="container.executor")
        # rclpy 9 annotates timer callbacks as plain
        node.create_timer(0.01, block)  # type: ignore[arg-type, unused-ignore]
        executor.spin_once(timeout_sec=10.0)
        assert blocked, "the timer did not run"
        assert any("event loop stuck" in r.message and "block" in r.message for r in caplog.records)
    finally:
        executor.shutdown(timeout_sec=5.0)
        node.destroy_node()
    assert watchdogs() == [], "shutdown left the watchdog thread behind"
