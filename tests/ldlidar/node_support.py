"""What the LiDAR node's tests share: its parameters, and recorders of what it publishes and logs."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

__all__ = ["ROSOUT_QOS", "Received", "Recorder", "lidar_parameters", "logged"]

ROSOUT_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def lidar_parameters(port: str, **more: Any) -> list[Parameter[Any]]:
    """Overrides for an LD06 on ``port``; keyword names use ``__`` for ``.``."""
    values = {"comm.serial_port": port, **{k.replace("__", "."): v for k, v in more.items()}}
    return [Parameter(name, value=value) for name, value in values.items()]


@dataclass(frozen=True)
class Received:
    at: float
    msg: Any


class Recorder:
    """Everything that arrives on one topic, with its monotonic arrival time."""

    def __init__(self, observer: Node, msg_type: Any, topic: str, qos: QoSProfile | int) -> None:
        self.items: list[Received] = []
        self._lock = threading.Lock()
        self.subscription = observer.create_subscription(msg_type, topic, self._record, qos)

    def _record(self, msg: Any) -> None:
        with self._lock:
            self.items.append(Received(time.monotonic(), msg))

    def __len__(self) -> int:
        with self._lock:
            return len(self.items)

    def since(self, index: int) -> list[Received]:
        with self._lock:
            return self.items[index:]

    def messages(self) -> list[Any]:
        with self._lock:
            return [item.msg for item in self.items]


def logged(rosout: Recorder, node: str) -> list[str]:
    return [msg.msg for msg in rosout.messages() if msg.name == node]
