"""A peer's megabyte costs the log and the answer a few hundred characters.

Any participant on the domain may load the LiDAR node with parameters of its
choosing, through the container's ``load_node`` service. A 1 MB
``comm.serial_port`` once made a 1,000,119-character ERROR line; here it goes
to a ``container run`` process over real DDS, and both the answer and every
line the container prints stay bounded and say how long the value was.
"""

from __future__ import annotations

from collections.abc import Callable

from rclpy.node import Node

from container import AsyncioExecutor
from tests.component_support import ContainerClient, load_request, parameter
from tests.container_support import ContainerProcess

MEGABYTE = 1024 * 1024
#: Longer than the bound of any line or answer (800 characters and the words around them), far shorter than a value.
BOUND = 1000
#: Why the device policy refuses it (said after the clipped value): no path is that long.
REASON = "a path of 1048576 bytes: longer than the 4095 a path may have"


def test_a_megabyte_port_is_answered_and_logged_clipped_with_its_length(
    run_container: Callable[..., ContainerProcess], client_node: Node, executor: AsyncioExecutor
) -> None:
    container = run_container("container:\n  name: ComponentManager\n")
    client = ContainerClient(client_node, executor, process=container)
    port = "/dev/" + "a" * (MEGABYTE - 5)

    answer = client.load(
        load_request(
            "ldlidar",
            "ldlidar::LdLidarNode",
            name="huge",
            parameters=[parameter("comm.serial_port", port)],
            extra_arguments=[parameter("autostart", True)],
        )
    )

    assert not answer.success
    assert len(answer.error_message) < BOUND, answer.error_message[:BOUND]
    # Clipped where it is echoed, so the reason after it survives.
    assert f"port '/dev/{'a' * 195}…' (1048576 characters): {REASON}" in answer.error_message
    node_line = container.wait_for_line("Cannot configure: port '/dev/aaa")
    container_line = container.wait_for_line("autostart failed")
    for line in (node_line, container_line):
        assert f"(1048576 characters): {REASON}" in line, line[:BOUND]
    assert max(len(line) for line in container.lines) < BOUND
    # The container serves on.
    assert client.list() == [(answer.unique_id, "/huge")]
