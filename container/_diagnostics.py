"""The container's own health on ``/diagnostics``: is the event loop free?

One ``diagnostic_msgs/DiagnosticArray`` a second from the container node:
level OK while the loop is free, WARN once it has been stuck, ERROR while it
is stuck now (with what it is stuck in), and the counts. The timer callback
is plain, so the report goes out from its lane's thread even while an
``async def`` callback holds the loop.

Every stall counts here, the container's own included: the watchdog logs
only stalls in a plugin's work (the container's start-up on a loaded
machine is no plugin's fault), but a loop stuck in our own code still
holds every ``async def`` callback back, which is what this status says.
``whose`` tells the two apart.

With the per-node load (:class:`~container._load.LoadReporter`), the same
report carries one status per node of its latest window: ERROR while one of
its callbacks is stuck, WARN when one was in that window.
"""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.timer import Timer

from ._load import LoadReporter
from .executor import AsyncioExecutor

__all__ = ["LoopDiagnostics"]

#: Seconds between two reports.
PERIOD = 1.0


class LoopDiagnostics:
    """Publish the executor's loop health for ``node`` until :meth:`close`."""

    def __init__(self, node: Node, executor: AsyncioExecutor, *, load: LoadReporter | None = None) -> None:
        self._node = node
        self._executor = executor
        self._load = load
        self._publisher = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._timer: Timer | None = node.create_timer(PERIOD, self._report)

    def status(self) -> DiagnosticStatus:
        watchdog = self._executor.watchdog
        stall = watchdog.stall if watchdog is not None else None
        stalls = watchdog.stalls if watchdog is not None else 0
        longest = watchdog.longest if watchdog is not None else 0.0
        if stall is not None:
            level = DiagnosticStatus.ERROR
            message = f"event loop stuck for {time.monotonic() - stall.since:.1f} s in {stall.what}"
        elif stalls:
            level, message = DiagnosticStatus.WARN, f"event loop was stuck {stalls} time(s)"
        else:
            level, message = DiagnosticStatus.OK, "event loop free"
        values = {
            "stalls": str(stalls),
            "longest stall (s)": f"{longest:.1f}",
            "stuck in": stall.what if stall is not None else "nothing",
            "whose": ("plugin" if stall.plugin else "container") if stall is not None else "nobody",
            "watchdog": "on" if watchdog is not None else "off",
        }
        return DiagnosticStatus(
            level=level,
            name=f"{self._node.get_fully_qualified_name()}: event loop",
            message=message,
            hardware_id=self._node.get_fully_qualified_name(),
            values=[KeyValue(key=key, value=text) for key, text in values.items()],
        )

    def _report(self) -> None:
        statuses = [self.status()]
        if self._load is not None:
            statuses += self._load.statuses()
        report = DiagnosticArray(status=statuses)
        report.header.stamp = self._node.get_clock().now().to_msg()
        self._publisher.publish(report)

    def close(self) -> None:
        if self._timer is not None:
            self._node.destroy_timer(self._timer)
            self._node.destroy_publisher(self._publisher)
            self._timer = None
