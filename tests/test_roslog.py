"""Python log records as ROS log lines: their severities and logger names (``container._roslog``)."""

from __future__ import annotations

import logging

import pytest
from rclpy.context import Context
from rclpy.impl.logging_severity import LoggingSeverity
from rclpy.node import Node

from container._roslog import ROOT_NAME, RosLogHandler, severity_of


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
