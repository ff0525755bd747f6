"""Test plugin nodes for intra-process communication in a container process.

``Camera`` hands 640x480 rgb8 images over (zero copy) on ``image`` at
``rate`` Hz once active, numbering them in ``header.frame_id``; ``Viewer``
counts what arrives and whether it is the very object the camera handed over
(only in-process delivery can do that), and logs a summary line every
``report`` frames. Both live in one module, so one process shares
``HANDED_OVER``.

Not 1080p: a 6 MB frame goes to a reader in another process as about 95
fragments sent at once. When that reader shares one CPU with the container
and a busy process, it is not run while they are sent and loses some; the
resent fragments of such frames are lost the same way while the camera goes
on sending, and keep-last 30 overwrites them. Beside a busy loop on one CPU
the process outside got only the 30 frames the writer still held at the
end, every time, with heartbeats every 3 s or every 100 ms (a plain rclpy
publisher lost some too); 640x480 frames (15 fragments) all arrived.
"""

from __future__ import annotations

import array
import collections
import threading
from typing import Any

from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.timer import Timer
from sensor_msgs.msg import Image

from container import LifecycleNode, RegisterNodeType, hand_over, hookimpl

#: The images the camera of this process handed over, by id (kept alive, so ids stay theirs).
HANDED_OVER: collections.OrderedDict[int, Image] = collections.OrderedDict()
_lock = threading.Lock()


class Camera(LifecycleNode):
    default_node_name = "camera"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("rate", 30.0)
        self.declare_parameter("frames", 60)
        # Frames published before a subscriber is matched are lost, as over
        # DDS for any volatile publisher: start once this many are.
        self.declare_parameter("subscribers", 1)
        self._publisher: Publisher[Any] | None = None
        self._timer: Timer | None = None
        self._sent = 0
        self._buffer = array.array("B", bytes(640 * 480 * 3))

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        # A reader in another process may lag behind on a loaded machine:
        # a reliable writer resends what its history still holds.
        self._publisher = self.create_publisher(Image, "image", 30)
        self._timer = self.create_timer(1.0 / float(self.get_parameter("rate").value), self._tick)
        return TransitionCallbackReturn.SUCCESS

    def _tick(self) -> None:
        if self._publisher is None or self._sent >= int(self.get_parameter("frames").value):
            return
        if self._publisher.get_subscription_count() < int(self.get_parameter("subscribers").value):
            return
        image = Image(height=480, width=640, encoding="rgb8", step=640 * 3)
        image.data = self._buffer
        image.header.frame_id = str(self._sent)
        with _lock:
            HANDED_OVER[id(image)] = image
            while len(HANDED_OVER) > 1000:
                HANDED_OVER.popitem(last=False)
        hand_over(self._publisher, image)
        self._sent += 1
        if self._sent == int(self.get_parameter("frames").value):
            self.get_logger().info(f"camera sent {self._sent}")


class Viewer(LifecycleNode):
    default_node_name = "viewer"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("report", 60)
        self._frames: list[str] = []
        self._same_object = 0
        on_image: Any = self._on_image  # rclpy's annotation knows no coroutines
        self.create_subscription(Image, "image", on_image, 100)

    async def _on_image(self, image: Image) -> None:
        with _lock:
            if HANDED_OVER.get(id(image)) is image:
                self._same_object += 1
        self._frames.append(image.header.frame_id)
        if len(self._frames) % int(self.get_parameter("report").value) == 0:
            self.get_logger().info(
                f"viewer got {len(self._frames)} frames, {len(set(self._frames))} distinct, "
                f"{self._same_object} handed over in process"
            )


@hookimpl
def register_node_types(register: RegisterNodeType) -> None:
    register(Camera)
    register(Viewer)
