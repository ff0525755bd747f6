"""A container node's logger: rclpy's lines, call sites and filters, at a fraction of the cost.

Read back from ``/rosout`` over DDS, where each line carries the function,
file and line rcutils was given: what rclpy's own logger reports for the
same call is what :class:`container._logger.FastLogger` must report.
"""

from __future__ import annotations

import inspect
import os
import time
from collections.abc import Callable
from typing import Any

import pytest
import rclpy.logging
from rcl_interfaces.msg import Log
from rclpy.impl.logging_severity import LoggingSeverity
from rclpy.impl.rcutils_logger import RcutilsLogger

from container import AsyncioExecutor, LifecycleNode
from container._logger import FastLogger
from tests.waiting import wait_until


@pytest.fixture
def talker(host: Callable[..., Any]) -> LifecycleNode:
    node: LifecycleNode = host(LifecycleNode, "logging_node")
    return node


def heard(lines: list[Log], text: str) -> Callable[[], list[Log]]:
    return lambda: [line for line in lines if line.msg == text]


def said_by_fast(logger: RcutilsLogger, text: str) -> int:
    """Log ``text``; return the line it was logged from."""
    logger.info(text)
    return _caller_line() - 1


def said_by_rclpy(logger: RcutilsLogger, text: str) -> int:
    logger.info(text)
    return _caller_line() - 1


def _caller_line() -> int:
    frame = inspect.currentframe()
    assert frame is not None and frame.f_back is not None
    return frame.f_back.f_lineno


def test_a_line_names_its_call_site_as_rclpys_logger_does(
    talker: LifecycleNode, rosout: list[Log], executor: AsyncioExecutor
) -> None:
    fast = talker.get_logger()
    assert isinstance(fast, FastLogger) and talker.get_logger() is fast
    plain = rclpy.logging.get_logger(fast.name)
    assert type(plain) is RcutilsLogger
    fast_line = said_by_fast(fast, "from the fast logger")
    plain_line = said_by_rclpy(plain, "from rclpy's logger")

    for text in ("from the fast logger", "from rclpy's logger"):
        wait_until(heard(rosout, text), f"'{text}' on /rosout", executor=executor)
    (mine,) = heard(rosout, "from the fast logger")()
    (theirs,) = heard(rosout, "from rclpy's logger")()
    assert (mine.name, mine.level, mine.file) == (theirs.name, theirs.level, theirs.file) == (
        "logging_node",
        Log.INFO,
        os.path.abspath(__file__),
    )
    assert (mine.function, mine.line) == ("said_by_fast", fast_line)
    assert (theirs.function, theirs.line) == ("said_by_rclpy", plain_line)


def test_filters_keep_their_state_per_call_site(
    talker: LifecycleNode, rosout: list[Log], executor: AsyncioExecutor
) -> None:
    """``once`` goes through rclpy's own search for the call site, which must look past
    the fast logger's frames: were they the call site, the second site would be silent."""
    logger = talker.get_logger()

    def first() -> None:
        logger.info("first site, once", once=True)

    def second() -> None:
        logger.info("second site, once", once=True)

    for _ in range(3):
        first()
        second()
    logger.info("after the filtered lines")
    wait_until(heard(rosout, "after the filtered lines"), "the last line on /rosout", executor=executor)
    firsts = heard(rosout, "first site, once")()
    seconds = heard(rosout, "second site, once")()
    assert len(firsts) == len(seconds) == 1
    assert (firsts[0].function, seconds[0].function) == ("first", "second")


def test_a_child_logger_is_fast_and_reaches_rosout_under_its_name(
    talker: LifecycleNode, rosout: list[Log], executor: AsyncioExecutor
) -> None:
    child = talker.get_logger().get_child("part")
    assert isinstance(child, FastLogger) and child.name == "logging_node.part"
    child.warning("from the child")
    wait_until(heard(rosout, "from the child"), "the child's line on /rosout", executor=executor)
    (line,) = heard(rosout, "from the child")()
    assert (line.name, line.level) == ("logging_node.part", Log.WARN)


def test_the_threshold_is_rcutils(talker: LifecycleNode, rosout: list[Log], executor: AsyncioExecutor) -> None:
    logger = talker.get_logger()
    logger.set_level(LoggingSeverity.WARN)
    try:
        assert logger.info("below the threshold") is False
        assert logger.warning("at the threshold") is True
    finally:
        logger.set_level(LoggingSeverity.INFO)
    logger.debug("below the default threshold")
    logger.info("at the default threshold")
    wait_until(heard(rosout, "at the default threshold"), "the last line on /rosout", executor=executor)
    assert heard(rosout, "at the threshold")()
    assert not heard(rosout, "below the threshold")()
    assert not heard(rosout, "below the default threshold")()


def test_a_line_costs_a_fraction_of_rclpys(talker: LifecycleNode) -> None:
    """rclpy reads the caller's source and resolves its file on every line (0.4-4 ms on
    the project's VM); the fast logger reads the frame (about 10 us): a 40x margin."""
    fast = talker.get_logger()
    plain = rclpy.logging.get_logger(fast.name)

    def cost(logger: RcutilsLogger) -> float:
        best = float("inf")
        for _ in range(5):
            start = time.perf_counter()
            for _ in range(20):
                logger.debug("a line")
            best = min(best, time.perf_counter() - start)
        return best

    fast.set_level(LoggingSeverity.DEBUG)
    try:
        assert cost(fast) * 5 < cost(plain)
    finally:
        fast.set_level(LoggingSeverity.INFO)
