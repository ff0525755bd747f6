"""The container's own lines are ROS log lines: on ``/rosout``, in the log file, in rcutils' format.

A ``container run`` child with its log directory in the test's ``tmp_path``,
and the test's own subscriber on ``/rosout``: the watchdog's report, the
signals' lines and the exit summary are read back from all three places.
"""

from __future__ import annotations

import re
import signal
from collections.abc import Callable
from pathlib import Path

import pytest
from rcl_interfaces.msg import Log

from container import AsyncioExecutor
from tests.container_support import ContainerProcess
from tests.waiting import wait_until

#: A plugin's ``async def`` timer that blocks the loop for 1.5 s, once; reported after 0.3 s.
STALL = """
container: {watchdog_threshold: 0.3}
nodes:
  - {package: tests_faults, plugin: tests_faults::FaultyAsync, name: hog, autostart: true,
     parameters: [{fault: sleep, where: timer, forever: 1.5}]}
"""

#: A node whose deactivate awaits for a minute: shutting down lasts until a third signal.
HOLDING = """
container: {unload_timeout: 60.0}
nodes:
  - {package: tests_faults, plugin: tests_faults::FaultyAsync, name: holding, autostart: true,
     parameters: [{fault: await, where: deactivate, transition_timeout: 60.0}]}
"""

#: rcutils' console line, ``[SEVERITY] [seconds.nanoseconds] [logger]: message``, with ``text`` in its message.
ROS_LINE = r"^\[{severity}\] \[\d+\.\d+\] \[{name}\]: .*{text}"


@pytest.fixture
def logs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, see_plugin: Callable[..., None]) -> Path:
    """The child containers' ``ROS_LOG_DIR``; they see the ``tests-faults`` plugin."""
    see_plugin(distribution="tests-faults", module="tests.fault_plugin")
    directory = tmp_path / "ros_log"
    monkeypatch.setenv("ROS_LOG_DIR", str(directory))
    return directory


def heard_line(heard: list[Log], *, name: str, text: str) -> Callable[[], Log | None]:
    def find() -> Log | None:
        return next((log for log in heard if log.name == name and text in log.msg), None)

    return find


def line_in(lines: list[str], *, severity: str, name: str, text: str) -> bool:
    pattern = re.compile(ROS_LINE.format(severity=severity, name=re.escape(name), text=re.escape(text)))
    return any(pattern.search(line) for line in lines)


def log_file_lines(directory: Path, process: ContainerProcess) -> list[str]:
    """The lines of the log file rcl wrote for ``process`` (``<executable>_<pid>_<time>.log``)."""
    (path,) = directory.glob(f"*_{process.process.pid}_*.log")
    return path.read_text(encoding="utf-8").splitlines()


def test_the_watchdog_and_the_signal_reach_rosout_and_the_log_file(
    logs: Path,
    rosout: list[Log],
    run_container: Callable[..., ContainerProcess],
    executor: AsyncioExecutor,
) -> None:
    container = run_container(STALL)
    stuck = heard_line(rosout, name="ComponentManager.executor", text="event loop stuck for")
    wait_until(stuck, "the watchdog's report on /rosout", timeout=20.0, executor=executor)
    report = stuck()
    assert report is not None
    assert report.level == Log.ERROR
    assert "/hog" in report.msg and "_tick" in report.msg
    assert report.file.endswith("_watchdog.py") and report.function == "_begin_stall"
    freed = heard_line(rosout, name="ComponentManager.executor", text="event loop free again")
    wait_until(freed, "the end of the stall on /rosout", timeout=20.0, executor=executor)

    container.process.send_signal(signal.SIGINT)
    received = heard_line(rosout, name="ComponentManager", text="SIGINT received: shutting down")
    wait_until(received, "'SIGINT received' on /rosout", executor=executor)
    line = received()
    assert line is not None and line.level == Log.INFO
    assert container.process.wait(15.0) == 0, container.output()

    for lines in (container.lines, log_file_lines(logs, container)):
        assert line_in(lines, severity="INFO", name="ComponentManager", text="SIGINT received: shutting down")
        assert line_in(lines, severity="ERROR", name="ComponentManager.executor", text="event loop stuck for")
        assert line_in(lines, severity="INFO", name="ComponentManager", text="ready with 1 node(s)")


def test_a_third_sigint_is_a_ros_warning_line_and_in_the_log_file(
    logs: Path,
    rosout: list[Log],
    run_container: Callable[..., ContainerProcess],
    executor: AsyncioExecutor,
) -> None:
    container = run_container(HOLDING)
    container.process.send_signal(signal.SIGINT)
    container.wait_for_line("misbehaving: await in deactivate")  # shutting down, held there
    container.process.send_signal(signal.SIGINT)
    again = heard_line(rosout, name="ComponentManager", text="SIGINT again: already shutting down")
    wait_until(again, "the absorbed SIGINT on /rosout", executor=executor)
    line = again()
    assert line is not None and line.level == Log.WARN
    container.process.send_signal(signal.SIGINT)
    assert container.process.wait(5.0) == 130, container.output()
    container.close()

    message = "SIGINT a third time: exiting at once"
    # A warning (what the operator asked for), in the log file although the
    # process ends at once: rcl's file sink writes through only an ERROR by
    # itself; the signal's line is flushed.
    for lines in (container.lines, log_file_lines(logs, container)):
        assert line_in(lines, severity="WARN", name="ComponentManager", text=message), "\n".join(lines)
