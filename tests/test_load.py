"""The per-node load told the ROS way: ``~/load`` while someone listens, ``/diagnostics`` per node."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from lifecycle_container_interfaces.msg import ContainerLoad
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from container import AsyncioExecutor, _load
from container._diagnostics import LoopDiagnostics
from container._errors import ConfigError
from container._load import LoadReporter
from tests.component_support import burn
from tests.waiting import wait_until

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def reporting(context: Context, executor: AsyncioExecutor) -> Iterator[tuple[Node, LoadReporter]]:
    """A container-like node reporting every 0.1 s, and a node burning 5 ms every 20 ms beside it."""
    owner = Node("owner", context=context, parameter_overrides=[Parameter("load_period", value=0.1)])
    burner = Node("burner", context=context)
    burner.create_timer(0.02, lambda: burn(0.005))
    accounting = executor.accounting
    assert accounting is not None
    reporter = LoadReporter(owner, accounting)
    for node in (owner, burner):
        executor.add_node(node)
    yield owner, reporter
    reporter.close()
    for node in (owner, burner):
        executor.remove_node(node)
        node.destroy_node()


def test_load_is_built_and_published_only_while_something_subscribes(
    executor: AsyncioExecutor,
    reporting: tuple[Node, LoadReporter],
    client_node: Node,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _, reporter = reporting
    built: list[ContainerLoad] = []
    to_message = _load.to_message

    def counting(*args: object, **kwargs: object) -> ContainerLoad:
        message = to_message(*args, **kwargs)  # type: ignore[arg-type]
        built.append(message)
        return message

    monkeypatch.setattr(_load, "to_message", counting)
    windows: list[object] = []

    def five_windows() -> bool:
        if reporter.latest is not None and all(reporter.latest is not seen for seen in windows):
            windows.append(reporter.latest)
        return len(windows) >= 5

    wait_until(five_windows, "five windows", executor=executor)
    assert built == []  # nobody listened: no message was even built

    heard: list[ContainerLoad] = []
    client_node.create_subscription(ContainerLoad, "/owner/load", heard.append, 5)
    wait_until(lambda: len(heard) >= 2, "two load messages", executor=executor)
    message = heard[-1]
    assert message.container == "/owner"
    assert message.period == pytest.approx(0.1, rel=0.5)
    assert message.stamp.sec > 0
    names = [node.name for node in message.nodes]
    assert names[0] == "/burner", names
    burner = message.nodes[0]
    assert burner.cpu == pytest.approx(0.25, rel=0.5)
    assert burner.callbacks and burner.callbacks[0].kind == "timer"
    assert burner.groups[0].name == "default"
    assert message.cpu >= message.callbacks_cpu * 0.9


def test_diagnostics_carry_one_status_per_node(
    executor: AsyncioExecutor, reporting: tuple[Node, LoadReporter], client_node: Node
) -> None:
    owner, reporter = reporting
    diagnostics = LoopDiagnostics(owner, executor, load=reporter)
    reports: list[DiagnosticArray] = []
    client_node.create_subscription(DiagnosticArray, "/diagnostics", reports.append, 10)
    try:
        wait_until(
            lambda: any(len(report.status) > 1 for report in reports), "a report with node statuses",
            executor=executor,
        )
        report = next(report for report in reports if len(report.status) > 1)
        by_name = {status.name: status for status in report.status}
        assert "/owner: event loop" in by_name
        burner = by_name["/owner: node /burner"]
        assert burner.level == DiagnosticStatus.OK
        values = {value.key: value.value for value in burner.values}
        assert float(values["cpu (% of a core)"]) > 5
        assert float(values["callbacks/s"]) > 10
        assert {"lateness p99 (ms)", "duration p99 (ms)", "dropped", "stuck", "stuck for (s)"} <= set(values)
    finally:
        diagnostics.close()


@pytest.mark.parametrize("period", [0.0, -1, "1 s", True])
def test_a_period_that_is_not_a_positive_number_is_refused(
    context: Context, executor: AsyncioExecutor, period: object
) -> None:
    owner = Node("owner", context=context, parameter_overrides=[Parameter("load_period", value=period)])
    accounting = executor.accounting
    assert accounting is not None
    try:
        with pytest.raises(ConfigError, match="load_period must be a positive number of seconds"):
            LoadReporter(owner, accounting)
    finally:
        owner.destroy_node()


def test_a_whole_number_of_seconds_is_a_period_too(context: Context, executor: AsyncioExecutor) -> None:
    owner = Node("owner", context=context, parameter_overrides=[Parameter("load_period", value=2)])
    accounting = executor.accounting
    assert accounting is not None
    reporter = LoadReporter(owner, accounting)
    try:
        assert reporter.period == 2.0
    finally:
        reporter.close()
        owner.destroy_node()
