"""Python log records as ROS log lines: their severities and logger names (``container._roslog``)."""

from __future__ import annotations

import logging
import os
import signal
from collections.abc import Iterator

import pytest
from rclpy.context import Context
from rclpy.impl.logging_severity import LoggingSeverity
from rclpy.node import Node

from container._roslog import ROOT_NAME, RosLogHandler, say_now, severity_of


@pytest.mark.parametrize(
    ("level", "severity"),
    [
        (logging.DEBUG, LoggingSeverity.DEBUG),
        (logging.INFO, LoggingSeverity.INFO),
        (logging.WARNING, LoggingSeverity.WARN),
        (logging.ERROR, LoggingSeverity.ERROR),
        (logging.CRITICAL, LoggingSeverity.FATAL),
        (logging.INFO + 5, LoggingSeverity.INFO),
    ],
)
def test_python_levels_map_to_rcutils_severities(level: int, severity: LoggingSeverity) -> None:
    assert severity_of(level) == severity


def test_without_a_node_the_python_names_stay_one_per_part() -> None:
    handler = RosLogHandler()
    assert handler.ros_name(ROOT_NAME) == "container"
    assert handler.ros_name("root") == "container"
    assert handler.ros_name("container.executor._dispatch") == "container.executor"
    assert handler.ros_name("serial.tools") == "serial.tools"


def test_a_node_attached_names_its_children_until_detached(context: Context) -> None:
    node = Node("roslog_probe", namespace="/roslog", context=context)
    handler = RosLogHandler()
    try:
        handler.attach(node.get_logger())
        assert handler.root_name == "roslog.roslog_probe"
        assert handler.ros_name(ROOT_NAME) == "roslog.roslog_probe"
        assert handler.ros_name("container.executor._watchdog") == "roslog.roslog_probe.executor"
        assert handler.ros_name("container.plugins") == "roslog.roslog_probe.plugins"
        assert handler.ros_name("serial.tools") == "roslog.roslog_probe.serial.tools"
    finally:
        handler.attach(None)
        node.destroy_node()
    assert handler.ros_name("container.executor._watchdog") == "container.executor"


class _Interrupted(RosLogHandler):
    """Sends the process SIGUSR1 in the middle of its own emit, with its lock held."""

    def emit(self, record: logging.LogRecord) -> None:
        os.kill(os.getpid(), signal.SIGUSR1)  # Python runs the handler at the next bytecode: here
        super().emit(record)


@pytest.fixture
def interrupted_logger() -> Iterator[logging.Logger]:
    logger = logging.getLogger("container.tests_roslog")
    handler = _Interrupted()
    logger.addHandler(handler)
    logger.propagate = False
    yield logger
    logger.removeHandler(handler)
    logger.propagate = True


def test_a_signal_handler_says_its_line_while_the_code_it_interrupted_logs(
    interrupted_logger: logging.Logger, capfd: pytest.CaptureFixture[str]
) -> None:
    said: list[int] = []

    def on_signal(signum: int, frame: object) -> None:
        say_now(logging.ERROR, "said from a signal handler")
        said.append(signum)

    previous = signal.signal(signal.SIGUSR1, on_signal)
    try:
        interrupted_logger.warning("the interrupted line")
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert said == [signal.SIGUSR1]
    lines = capfd.readouterr().err.splitlines()

    def index(ending: str) -> int:
        return next(i for i, line in enumerate(lines) if line.endswith(ending))

    handler_line = index("[container]: said from a signal handler")
    interrupted = index("[container.tests_roslog]: the interrupted line")
    assert lines[handler_line].startswith("[ERROR] [") and lines[interrupted].startswith("[WARN] [")
    assert handler_line < interrupted, "said at once, inside the interrupted call"
