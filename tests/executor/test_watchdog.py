"""The loop watchdog: an ``async def`` callback that blocks stalls no plain callback."""

from __future__ import annotations

import asyncio
import functools
import itertools
import logging
import threading
import time
from collections.abc import Iterator

import pytest
from rclpy.context import Context
from rclpy.node import Node
from std_msgs.msg import Int64

from container import AsyncioExecutor, ComponentManager, LifecycleManager
from container._session import Session, run_session
from container.demo import Talker
from container.executor._culprit import is_platform_node, working_for
from container.executor._watchdog import Stall
from tests.waiting import wait_until


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


class _Records(logging.Handler):
    """The watchdog's log lines, with a condition to wait for one on."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []
        self._changed = threading.Condition()
        #: Set by the first full report of a stall.
        self.reported = threading.Event()

    def emit(self, record: logging.LogRecord) -> None:
        with self._changed:
            self.records.append(record)
            self._changed.notify_all()
        if "event loop stuck" in record.getMessage():
            self.reported.set()

    def wait_for(self, text: str, timeout: float = 5.0) -> bool:
        with self._changed:
            return self._changed.wait_for(lambda: any(text in r.getMessage() for r in self.records), timeout)

    def lines(self, text: str) -> list[str]:
        return [r.getMessage() for r in self.records if text in r.getMessage()]


@pytest.fixture
def watchdog_log() -> Iterator[_Records]:
    """Every line the watchdog logs (``container.executor``, DEBUG and up)."""
    logger = logging.getLogger("container.executor")
    handler, level = _Records(), logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def _spin(executor: AsyncioExecutor) -> threading.Thread:
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    return spinner


def _stopped(executor: AsyncioExecutor, spinner: threading.Thread, *nodes: Node) -> None:
    executor.shutdown(timeout_sec=5.0)
    spinner.join(5.0)
    for node in nodes:
        node.destroy_node()


def test_a_stall_in_a_sessions_own_task_is_counted_not_reported(watchdog_log: _Records) -> None:
    """The container's start-up and a client command's imports run in the
    session's main task (``_guarded``): slow there is not stuck in a plugin."""
    seen: list[Stall | None] = []

    async def main(session: Session) -> int:
        watchdog = session.executor.watchdog
        assert watchdog is not None
        # Blocks the loop thread, as an import in the loop does.
        wait_until(lambda: watchdog.stall is not None, "the watchdog to count the stall", timeout=5.0)
        seen.append(watchdog.stall)
        return 0

    assert run_session(main, executor_options={"stall_after": 0.3}) == 0
    stall = seen[0]
    assert stall is not None and not stall.plugin, "counted, as the platform's"
    assert "_guarded" in stall.what
    assert not [r for r in watchdog_log.records if r.levelno >= logging.INFO], "a platform stall was reported"


def test_the_container_node_is_platform_and_plugin_nodes_are_not() -> None:
    assert is_platform_node(ComponentManager.__new__(ComponentManager))
    assert is_platform_node(LifecycleManager.__new__(LifecycleManager))
    assert not is_platform_node(Talker.__new__(Talker)), "the demo plugins are plugins"
    assert not is_platform_node(Node.__new__(Node)), "a node made of rclpy's class is a plugin's"


@pytest.mark.parametrize("where", ["callback", "task", "posted"])
def test_a_plugin_stall_is_reported_once_naming_node_callback_and_plugin_frame_first(
    context: Context, watchdog_log: _Records, where: str
) -> None:
    """``where="task"``: the blocking code runs in a task the callback
    created; ``"posted"``: in a task of a coroutine a plain callback posted
    to the loop, declared as the node's work (a ``change_state`` request's
    transition)."""
    executor = AsyncioExecutor(context=context, stall_after=0.3)
    node = Node("watchdog_plugin", context=context)
    ran = threading.Event()
    tasks: list[asyncio.Task[None]] = []

    async def stuck() -> None:
        watchdog_log.reported.wait(5.0)  # blocking code in an async def: the fault

    async def tick() -> None:
        if ran.is_set():
            return
        ran.set()
        if where == "task":
            tasks.append(asyncio.create_task(stuck()))
        else:
            watchdog_log.reported.wait(5.0)  # blocking code in an async def: the fault

    async def transition() -> None:
        with working_for(node, stuck):
            await asyncio.create_task(stuck())

    def post() -> None:
        if not ran.is_set():
            ran.set()
            asyncio.run_coroutine_threadsafe(transition(), executor.loop)

    # rclpy 9 annotates timer callbacks as plain
    node.create_timer(0.05, post if where == "posted" else tick)  # type: ignore[arg-type, unused-ignore]
    executor.add_node(node)
    spinner = _spin(executor)
    try:
        assert watchdog_log.wait_for("free again"), "the stall was not reported, or did not end"
    finally:
        _stopped(executor, spinner, node)
    [report] = watchdog_log.lines("event loop stuck")
    assert report.startswith("/watchdog_plugin: ")
    if where != "posted":
        assert "timer callback" in report and "tick" in report
    first = report.split("most recent call first:\n", 1)[1].splitlines()
    assert first[0].startswith(f'  File "{__file__}"'), "the plugin's own frame comes first"
    assert f"in {'tick' if where == 'callback' else 'stuck'}" in first[0] and "reported.wait(5.0)" in first[1]
    assert "platform frames omitted" in report and "asyncio" not in report.split("\n", 1)[1].split("omitted")[0]
    if where == "task":
        assert "started by timer callback" in report
    if where == "posted":
        assert "started by function callback" in report and report.split(": event loop")[0].endswith(".stuck")
    assert len(watchdog_log.lines("free again")) == 1


def test_repeated_stalls_of_one_callback_are_one_report_and_one_summary(
    context: Context, watchdog_log: _Records
) -> None:
    """An ``async def`` callback that blocks on every call: one full report,
    the rest counted (a summary at most once a minute, and at shutdown)."""
    executor = AsyncioExecutor(context=context, stall_after=0.3)
    node = Node("watchdog_repeat", context=context)
    finished: list[int] = []

    def stalls() -> int:
        watchdog = executor.watchdog
        return watchdog.stalls if watchdog is not None else 0

    async def on_trigger() -> None:
        n = len(finished) + 1
        # Blocks the loop until the watchdog counted this stall.
        wait_until(lambda: stalls() >= n, f"the watchdog to count stall {n}", timeout=5.0)
        finished.append(n)

    guard = node.create_guard_condition(on_trigger)  # type: ignore[arg-type, unused-ignore]  # Kilted types it plain
    executor.add_node(node)
    spinner = _spin(executor)
    def ended(n: int) -> bool:
        # The watchdog saw the stall end: the next one is a stall of its own.
        watchdog = executor.watchdog
        return len(finished) == n and watchdog is not None and watchdog.stall is None

    try:
        for n in (1, 2, 3):
            guard.trigger()
            wait_until(functools.partial(ended, n), f"stall {n} to end", timeout=5.0)
    finally:
        _stopped(executor, spinner, node)
    assert len(watchdog_log.lines("event loop stuck")) == 1
    assert len(watchdog_log.lines("free again")) == 1
    [summary] = watchdog_log.lines("more time")
    assert summary.startswith("/watchdog_repeat: guardcondition callback")
    assert "stuck 2 more times in the last" in summary and "longest" in summary
    assert len([r for r in watchdog_log.records if r.levelno >= logging.INFO]) == 3


def test_a_relief_asked_for_once_the_loop_is_back_at_its_wait_returns_at_once(context: Context) -> None:
    """The watchdog asks for a relief when it last saw the loop busy; by then
    the loop may be back in its own wait, holding the wait set for as long as
    that lasts (for good, idle). The relief used to queue behind it, and the
    watchdog with it: a stall that never ended (under load, 8 of 12 runs of
    the test above)."""
    executor = AsyncioExecutor(context=context)
    node = Node("watchdog_relief", context=context)
    executor.add_node(node)
    spinner = _spin(executor)
    dispatcher = executor._dispatcher
    returned = threading.Event()
    try:
        wait_until(lambda: dispatcher.loop_thread is not None and dispatcher.busy_since is None, "the loop's wait")

        def relieve() -> None:
            dispatcher.relieve(int(2e9))
            returned.set()

        threading.Thread(target=relieve, daemon=True).start()
        assert returned.wait(1.0), "the relief waited behind the loop's own wait"
    finally:
        _stopped(executor, spinner, node)


def test_with_reports_off_a_plugin_stall_is_relieved_and_counted_but_not_logged(
    context: Context, watchdog_log: _Records
) -> None:
    executor = AsyncioExecutor(context=context, stall_after=0.3, watchdog_reports=False)
    node = Node("watchdog_quiet", context=context)
    seen: list[Stall | None] = []
    done = threading.Event()

    async def tick() -> None:
        if done.is_set():
            return
        watchdog = executor.watchdog
        assert watchdog is not None
        wait_until(lambda: watchdog.stall is not None, "the watchdog to count the stall", timeout=5.0)
        seen.append(watchdog.stall)
        done.set()

    # rclpy 9 annotates timer callbacks as plain
    node.create_timer(0.05, tick)  # type: ignore[arg-type, unused-ignore]
    executor.add_node(node)
    spinner = _spin(executor)
    try:
        assert done.wait(5.0)
    finally:
        _stopped(executor, spinner, node)
    stall = seen[0]
    assert stall is not None and stall.plugin and stall.what.startswith("/watchdog_quiet: timer callback")
    assert watchdog_log.records == [], "reports are off, yet the watchdog logged"
