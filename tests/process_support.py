"""For the tests that start the container the way ROS tools do.

An executable found through the ament index, launch_ros's argument list, a
network namespace, rather than ``python -m container run FILE``: any command
as a :class:`LoggedProcess` (shared with ``container_support``), and the times
its log lines carry.
"""

from __future__ import annotations

import re

from tests.container_support import LoggedProcess

__all__ = ["LoggedProcess", "log_time"]

#: rcutils' console format: ``[INFO] [1795457363.349322609] [logger]: message``.
_STAMP = re.compile(r"^\[\w+\] \[(\d+\.\d+)\]")


def log_time(line: str) -> float:
    """The wall-clock time an rcutils log line carries."""
    match = _STAMP.match(line)
    if match is None:
        raise AssertionError(f"not an rcutils log line with a time stamp: {line!r}")
    return float(match.group(1))
