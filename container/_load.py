"""What each node costs, told the ROS way: ``~/load`` and ``/diagnostics``.

The executor's accounting (``container.executor.Accounting``) measures every
callback; here the container node closes a window every ``load_period``
seconds and

* publishes the window as ``lifecycle_container_interfaces/ContainerLoad`` on
  ``~/load`` while something subscribes (``container top`` does), building
  no message otherwise;
* keeps it for :class:`~container._diagnostics.LoopDiagnostics`, which adds
  one status per node to the container's ``/diagnostics`` report.

The timer is plain, so a window closes on its lane's thread even while an
``async def`` callback holds the event loop: that is when the figures matter.
"""

from __future__ import annotations

from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from lifecycle_container_interfaces.msg import (
    CallbackLoad as CallbackLoadMsg,
)
from lifecycle_container_interfaces.msg import (
    ContainerLoad as ContainerLoadMsg,
)
from lifecycle_container_interfaces.msg import (
    GroupLoad as GroupLoadMsg,
)
from lifecycle_container_interfaces.msg import (
    NodeLoad as NodeLoadMsg,
)
from lifecycle_container_interfaces.msg import (
    UnattributedLoad as UnattributedLoadMsg,
)
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.timer import Timer

from ._errors import ConfigError
from .executor import Accounting, ContainerLoad, NodeLoad

__all__ = ["LOAD_TOPIC", "LoadReporter", "to_message"]

#: The topic, relative to the container node.
LOAD_TOPIC = "~/load"
#: The container node's parameter: seconds per window.
PERIOD_PARAMETER = "load_period"
DEFAULT_PERIOD = 1.0


class LoadReporter:
    """Close an accounting window every period; publish it while anyone listens.

    :raises ConfigError: ``load_period`` is not a positive number of seconds.
    """

    def __init__(self, node: Node, accounting: Accounting) -> None:
        self._node = node
        self._accounting = accounting
        period: object = node.declare_parameter(
            PERIOD_PARAMETER,
            DEFAULT_PERIOD,
            ParameterDescriptor(
                description="Seconds per window of the per-node load on ~/load and /diagnostics",
                read_only=True,
                dynamic_typing=True,  # load_period:=2 is as good as 2.0
            ),
        ).value
        if not isinstance(period, float | int) or isinstance(period, bool) or period <= 0:
            raise ConfigError(f"{PERIOD_PARAMETER} must be a positive number of seconds, not {period!r}")
        self.period = float(period)
        self._publisher = node.create_publisher(ContainerLoadMsg, LOAD_TOPIC, QoSProfile(depth=5))
        #: The latest window, for the diagnostics (``None`` before the first).
        self.latest: ContainerLoad | None = None
        accounting.sample()  # the first window starts now
        self._timer: Timer | None = node.create_timer(self.period, self._close_window)

    def _close_window(self) -> None:
        load = self._accounting.sample()
        self.latest = load
        if self._publisher.get_subscription_count() > 0:
            message = to_message(load, container=self._node.get_fully_qualified_name())
            message.stamp = self._node.get_clock().now().to_msg()
            self._publisher.publish(message)

    def statuses(self) -> list[DiagnosticStatus]:
        """One ``/diagnostics`` status per node of the latest window."""
        load = self.latest
        if load is None:
            return []
        owner = self._node.get_fully_qualified_name()
        return [_status(owner, node) for node in load.nodes]

    def close(self) -> None:
        if self._timer is not None:
            self._node.destroy_timer(self._timer)
            self._node.destroy_publisher(self._publisher)
            self._timer = None


def _status(owner: str, node: NodeLoad) -> DiagnosticStatus:
    if node.stuck_for > 0:
        level = DiagnosticStatus.ERROR
        stuck = max(node.callbacks, key=lambda c: c.stuck_for)
        message = f"stuck for {node.stuck_for:.1f} s in {stuck.name}"
    elif node.stuck:
        level, message = DiagnosticStatus.WARN, f"{node.stuck} callback(s) stuck in the last window"
    else:
        level = DiagnosticStatus.OK
        message = f"{node.cpu * 100:.1f}% CPU, {node.rate:.1f} callbacks/s"
    values = {
        "cpu (% of a core)": f"{node.cpu * 100:.2f}",
        "callbacks/s": f"{node.rate:.1f}",
        "lateness p99 (ms)": f"{node.lateness_p99 * 1e3:.3f}",
        "duration p99 (ms)": f"{node.duration_p99 * 1e3:.3f}",
        "dropped": str(node.dropped),
        "stuck": str(node.stuck),
        "stuck for (s)": f"{node.stuck_for:.1f}",
        "cpu total (s)": f"{node.cpu_seconds_total:.3f}",
    }
    return DiagnosticStatus(
        level=level,
        name=f"{owner}: node {node.name}",
        message=message,
        hardware_id=owner,
        values=[KeyValue(key=key, value=text) for key, text in values.items()],
    )


def _copied(message_type: Any, source: object, **given: Any) -> Any:
    """A ``message_type`` whose fields other than ``given`` are ``source``'s attributes of the same names
    (the message files name their fields as the accounting's records do)."""
    fields = {name: getattr(source, name) for name in message_type.get_fields_and_field_types() if name not in given}
    return message_type(**fields, **given)


def to_message(load: ContainerLoad, *, container: str) -> ContainerLoadMsg:
    """``load`` as the message ``~/load`` carries (without its stamp)."""
    nodes = [
        _copied(
            NodeLoadMsg,
            node,
            groups=[_copied(GroupLoadMsg, group) for group in node.groups],
            callbacks=[_copied(CallbackLoadMsg, callback) for callback in node.callbacks],
        )
        for node in load.nodes
    ]
    unattributed = [_copied(UnattributedLoadMsg, item) for item in load.unattributed]
    message: ContainerLoadMsg = _copied(
        ContainerLoadMsg, load, stamp=Time(), container=container, nodes=nodes, unattributed=unattributed
    )
    return message
