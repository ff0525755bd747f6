"""Helpers for the container-service tests: a test plugin, service calls, the graph.

This module is also the test plugin itself: ``install_test_plugin`` writes a
distribution ``test-nodes`` whose entry point names this module, so a
``container run`` child process registers ``test_nodes::Exploding`` and
``test_nodes::Busy`` (and ``Burner``, ``Idle``) exactly like an installed plugin's types.
"""

from __future__ import annotations

import time
import weakref
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from rcl_interfaces.msg import Parameter as ParameterMsg
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.client import Client
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import String
from std_srvs.srv import Trigger

from container import AsyncioExecutor
from container._hookspecs import RegisterNodeType, hookimpl

if TYPE_CHECKING:
    from tests.process_support import LoggedProcess

#: The directory that makes ``tests.component_support`` importable in a child process.
IMPORT_ROOT = Path(__file__).resolve().parents[1]

#: Every Busy node ever constructed; an entry outliving its unload is a leak.
BUSY_NODES: weakref.WeakSet[Busy] = weakref.WeakSet()


class Exploding(LifecycleNode):
    """A node type whose constructor raises."""

    def __init__(self, node_name: str = "exploding", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        raise RuntimeError("boom from the constructor")


class Busy(LifecycleNode):
    """Owns one of everything an unload must remove: timers, a subscription,
    a service, an async callback (a task) and plain callbacks (a thread)."""

    default_node_name = "busy"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        BUSY_NODES.add(self)
        group = ReentrantCallbackGroup()
        self.ticks = 0
        # rclpy 9 annotates timer callbacks as plain
        self.create_timer(0.01, self._tick_async, callback_group=group)  # type: ignore[arg-type, unused-ignore]
        self.create_timer(0.01, self._tick)
        self.create_subscription(String, "busy_in", self._hear, 10)
        self.create_service(Trigger, "~/poke", self._poke, callback_group=group)

    async def _tick_async(self) -> None:
        self.ticks += 1

    def _tick(self) -> None:
        self.ticks += 1

    def _hear(self, message: String) -> None:
        self.ticks += 1

    def _poke(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success = True
        return response

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.get_logger().info(f"shutting down from {state.label}")
        return TransitionCallbackReturn.SUCCESS


def burn(seconds: float) -> None:
    """Spend ``seconds`` of this thread's CPU time (not wall time: a preempted burn still burns that much)."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


class Burner(Node):
    """A timer that burns a known amount of CPU: ``burn_ms`` of thread CPU time every ``period`` s."""

    default_node_name = "burner"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.burn_s = float(self.declare_parameter("burn_ms", 20.0).value) / 1e3
        self.create_timer(float(self.declare_parameter("period", 0.1).value), lambda: burn(self.burn_s))


class Idle(Node):
    """A timer that does nothing, once a second."""

    default_node_name = "idle"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.create_timer(1.0, lambda: None)


@hookimpl
def register_node_types(register: RegisterNodeType) -> None:
    """Register the test node types."""
    register(Exploding)
    register(Busy)
    register(Burner)
    register(Idle)


def install_test_plugin(
    site: Path, *, distribution: str = "test-nodes", module: str = "tests.component_support"
) -> Path:
    """Write a distribution whose entry point is ``module`` into ``site``.

    :return: ``site``; a child process needs it and :data:`IMPORT_ROOT` on PYTHONPATH.
    """
    package = distribution.replace("-", "_")
    info = site / f"{package}-0.1.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(
        f"Metadata-Version: 2.1\nName: {distribution}\nVersion: 0.1\n", encoding="utf-8"
    )
    (info / "entry_points.txt").write_text(
        f"[container.plugins]\n{package} = {module}\n", encoding="utf-8"
    )
    return site


def parameter(name: str, value: Any) -> ParameterMsg:
    return Parameter(name, value=value).to_parameter_msg()


def load_request(
    package: str = "lifecycle_container",
    plugin: str = "lifecycle_container::Talker",
    *,
    name: str = "",
    namespace: str = "",
    remap_rules: Sequence[str] = (),
    parameters: Sequence[ParameterMsg] = (),
    extra_arguments: Sequence[ParameterMsg] = (),
    log_level: int = 0,
) -> LoadNode.Request:
    return LoadNode.Request(
        package_name=package,
        plugin_name=plugin,
        node_name=name,
        node_namespace=namespace,
        remap_rules=list(remap_rules),
        parameters=list(parameters),
        extra_arguments=list(extra_arguments),
        log_level=log_level,
    )


class ContainerClient:
    """Synchronous calls to a container's services, served by ``executor``.

    :param process: the container's process, whose last lines a call that
        gets no answer prints (what the container made of the request).
    """

    def __init__(
        self,
        node: Node,
        executor: AsyncioExecutor,
        container: str = "/ComponentManager",
        *,
        process: LoggedProcess | None = None,
    ) -> None:
        self.node = node
        self.executor = executor
        self.process = process
        self.load_client: Client[Any, Any] = node.create_client(LoadNode, f"{container}/_container/load_node")
        self.unload_client: Client[Any, Any] = node.create_client(UnloadNode, f"{container}/_container/unload_node")
        self.list_client: Client[Any, Any] = node.create_client(ListNodes, f"{container}/_container/list_nodes")
        for client in (self.load_client, self.unload_client, self.list_client):
            assert client.wait_for_service(timeout_sec=20.0), f"{client.srv_name} never appeared"

    def call(self, client: Client[Any, Any], request: Any, *, timeout: float = 30.0) -> Any:
        future = client.call_async(request)
        self.executor.spin_until_future_complete(future, timeout_sec=timeout)
        if not future.done():
            log = f"\n{self.process.output()}" if self.process is not None else ""
            raise AssertionError(f"no answer from {client.srv_name} within {timeout} s{log}")
        return future.result()

    def load(self, request: LoadNode.Request) -> LoadNode.Response:
        return self.call(self.load_client, request)

    def unload(self, unique_id: int) -> UnloadNode.Response:
        return self.call(self.unload_client, UnloadNode.Request(unique_id=unique_id))

    def list(self) -> list[tuple[int, str]]:
        response = self.call(self.list_client, ListNodes.Request())
        return list(zip(response.unique_ids, response.full_node_names, strict=True))


def graph_nodes(node: Node) -> set[str]:
    return {
        f"{namespace.rstrip('/')}/{name}" for name, namespace in node.get_node_names_and_namespaces()
    }
