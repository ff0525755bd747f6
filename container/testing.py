"""Testing plugins with pytest: a container on the test's own event loop.

Installed with the package as a pytest plugin (entry point ``pytest11``), so
a plugin distribution's tests need no conftest of their own::

    async def test_greeter_greets(container_host):
        await container_host.load("greeter_nodes::Greeter", parameters={"name": "tests"})
        message = await container_host.wait_for_message(String, "/greeting")
        assert message.data == "Hello, tests!"

What the plugin provides:

* a random ``ROS_DOMAIN_ID`` and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``
  for the test session (either one already exported wins), so concurrent
  runs never see each other; the ini option ``container_isolate_ros = false``
  turns it off;
* the fixtures ``ros_context`` (a fresh rclpy context per test) and
  ``container_host`` (a :class:`ContainerHost` serving on the test's running
  loop, everything it loaded unloaded down its lifecycle afterwards).

The fixtures are ``async``: the test runs under pytest-asyncio (``async def``
tests, in its auto mode or marked ``@pytest.mark.asyncio``). Nothing of ROS
is imported until a fixture is used, so the plugin costs other test suites
in the same environment nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import importlib.util
import os
import random
import time
from collections.abc import AsyncIterator, Callable, Iterator, Mapping, MutableMapping, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

import pytest

if TYPE_CHECKING:
    from rclpy.client import Client
    from rclpy.context import Context
    from rclpy.node import Node

    from ._container import ComponentManager, LoadedNode
    from ._registry import PluginRegistry
    from .executor import AsyncioExecutor

__all__ = ["ContainerHost", "container_host", "isolate_ros", "open_container_host", "ros_context"]

T = TypeVar("T")
_ISOLATE_OPTION = "container_isolate_ros"


def isolate_ros(environ: MutableMapping[str, str] = os.environ) -> None:
    """Keep this process and its children to a ROS domain of their own, on this host.

    A ``ROS_DOMAIN_ID`` or discovery range already set wins. Also selects the
    project's Fast DDS profile (quick discovery) unless the user names one.
    """
    environ.setdefault("ROS_DOMAIN_ID", str(random.Random().randint(1, 200)))
    environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from ._runtime import use_fast_discovery

    use_fast_discovery()


class ContainerHost:
    """A component container serving on the running event loop, and a client node beside it.

    What a test of a plugin needs: load node types as a container would
    (the same registry, parameters and lifecycle bring-up), and observe them
    from another node over real DDS. Use :func:`open_container_host` (or the
    ``container_host`` fixture) to make one.

    :ivar executor: the executor every node here runs on.
    :ivar manager: the container's node (``/ComponentManager`` unless named).
    :ivar client: a plain node of the test's, for subscriptions and calls.
    """

    def __init__(self, *, executor: AsyncioExecutor, manager: ComponentManager, client: Node) -> None:
        self.executor = executor
        self.manager = manager
        self.client = client

    async def load(
        self,
        plugin: str,
        *,
        name: str | None = None,
        namespace: str | None = None,
        parameters: Mapping[str, Any] | Sequence[Mapping[str, Any]] = (),
        remap_rules: Sequence[str] = (),
        autostart: bool = True,
        timeout: float = 5.0,
    ) -> Node:
        """Load ``package::Type`` and, unless ``autostart`` is false, bring it up to active.

        :param parameters: parameter values by name (or several such mappings, later winning).
        :param timeout: seconds each lifecycle transition may take.
        :raises LoadError: the type is unknown or its constructor failed.
        :raises TransitionError: configure or activate failed (the node stays loaded).
        """
        from ._container import LoadRequest

        package, _, _ = plugin.partition("::")
        sources = [parameters] if isinstance(parameters, Mapping) else list(parameters)
        loaded = await self.manager.load_and_start(
            LoadRequest(
                package,
                plugin,
                name=name,
                namespace=namespace,
                parameters=sources,
                remap_rules=remap_rules,
                autostart=autostart,
            ),
            timeout=timeout,
        )
        return loaded.node

    async def unload(self, node: Node) -> None:
        """Take ``node`` down its lifecycle and destroy it, as an unload request would."""
        await self.manager.unload(self._loaded(node).unique_id)

    async def transition(self, node: Node, label: str, *, timeout: float = 5.0) -> None:
        """Carry out one lifecycle transition (``configure``, ``deactivate``, ...) of a loaded node.

        :raises TransitionError: it failed, raised or timed out.
        """
        from .lifecycle import transition

        await transition(self.executor, self._loaded(node).node, label, timeout=timeout)

    def state_of(self, node: Node) -> str:
        """The label of ``node``'s lifecycle state (``active``, ``inactive``, ...)."""
        from .lifecycle import state_of

        return state_of(node)

    async def wait_for_message(
        self,
        msg_type: type[T],
        topic: str,
        *,
        timeout: float = 5.0,
        where: Callable[[T], bool] | None = None,
        qos: int = 10,
    ) -> T:
        """The next message on ``topic`` (for which ``where`` holds), received by the client node.

        :raises TimeoutError: none arrived within ``timeout`` seconds.
        """
        from .executor import call_soon

        loop = asyncio.get_running_loop()
        received: asyncio.Future[T] = loop.create_future()

        def take(message: T) -> None:
            if where is None or where(message):
                call_soon(loop, _settle, received, message)

        subscription = self.client.create_subscription(msg_type, topic, take, qos)
        try:
            return await _within(received, timeout, f"no {_type_name(msg_type)} message on {topic!r}")
        finally:
            self.client.destroy_subscription(subscription)

    async def call(self, srv_type: type[Any], service: str, request: Any, *, timeout: float = 5.0) -> Any:
        """Call ``service`` from the client node once it is available; return the response.

        :raises TimeoutError: the service did not appear or answer within ``timeout`` seconds.
        """
        client: Client[Any, Any] = self.client.create_client(srv_type, service)
        try:
            deadline = time.monotonic() + timeout
            await self.wait_until(client.service_is_ready, timeout=timeout, what=f"service {service!r} available")
            left = max(deadline - time.monotonic(), 0.0)
            return await self.wait_for_future(client.call_async(request), timeout=left, what=f"answer from {service!r}")
        finally:
            self.client.destroy_client(client)

    async def wait_for_future(self, future: Any, *, timeout: float = 5.0, what: str = "result") -> Any:
        """The result of an rclpy future (a service call, an action goal or result), awaited on this loop.

        :raises TimeoutError: it was not done within ``timeout`` seconds.
        """
        from .executor import call_soon

        loop = asyncio.get_running_loop()
        done: asyncio.Future[Any] = loop.create_future()
        future.add_done_callback(lambda finished: call_soon(loop, _settle, done, finished.result()))
        return await _within(done, timeout, f"no {what}")

    async def wait_until(self, condition: Callable[[], bool], *, timeout: float = 5.0, what: str = "condition") -> None:
        """Poll ``condition`` on the loop (every 10 ms) until it holds.

        :raises TimeoutError: it did not hold within ``timeout`` seconds.
        """
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() >= deadline:
                raise TimeoutError(f"{what}: not within {timeout:g} s")
            await asyncio.sleep(0.01)

    def _loaded(self, node: Node) -> LoadedNode:
        for loaded in self.manager.loaded():
            if loaded.node is node:
                return loaded
        raise ValueError(f"{node.get_fully_qualified_name()} is not loaded in this container")


@contextlib.asynccontextmanager
async def open_container_host(
    *,
    context: Context | None = None,
    registry: PluginRegistry | None = None,
    name: str = "ComponentManager",
) -> AsyncIterator[ContainerHost]:
    """A :class:`ContainerHost` on the running loop; on exit every node is unloaded
    down its lifecycle and the executor shut down.

    :param registry: the node types that may be loaded; the installed plugins by default.
    """
    from rclpy.node import Node

    from ._container import ComponentManager
    from ._registry import PluginRegistry
    from .executor import AsyncioExecutor

    executor = AsyncioExecutor(context=context)
    manager = ComponentManager(
        registry=registry if registry is not None else PluginRegistry(), executor=executor, name=name, context=context
    )
    client = Node("container_test_client", context=context)
    executor.add_node(manager)
    executor.add_node(client)
    spinning = asyncio.ensure_future(executor.spin_async())
    try:
        yield ContainerHost(executor=executor, manager=manager, client=client)
        await manager.unload_all()
    finally:
        executor.shutdown(timeout_sec=5.0)
        await spinning
        for node in (client, manager):
            node.destroy_node()


async def _within(future: asyncio.Future[T], timeout: float, what: str) -> T:
    try:
        return await asyncio.wait_for(future, timeout)
    except TimeoutError:
        raise TimeoutError(f"{what} within {timeout:g} s") from None


def _settle(future: asyncio.Future[T], value: T) -> None:
    if not future.done():
        future.set_result(value)


def _type_name(msg_type: type[Any]) -> str:
    return f"{msg_type.__module__.partition('.')[0]}/{msg_type.__name__}"


# -- the pytest plugin ----------------------------------------------------------------


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addini(
        _ISOLATE_OPTION,
        "give the test session a random ROS_DOMAIN_ID and keep discovery on this host",
        type="bool",
        default=True,
    )


def pytest_configure(config: pytest.Config) -> None:
    if config.getini(_ISOLATE_OPTION):
        isolate_ros()


@pytest.fixture
def ros_context() -> Iterator[Context]:
    """A fresh rclpy context, shut down after the test."""
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions
    from rclpy.utilities import try_shutdown

    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    try:
        yield context
    finally:
        try_shutdown(context=context)
        # Nodes the test left to the garbage collector go now, with the
        # context's DDS participant. Collected later, in another test, the
        # participant's destruction can deadlock Fast DDS 2.14 (seen once in
        # CI): it waits for its discovery listener while holding the mutex
        # that listener needs, when another participant of the process is
        # announcing endpoints at that moment; the GIL stays held, so not
        # even pytest-timeout ends the hang.
        gc.collect()
        # And the participant goes now, before the next test makes its own,
        # not whenever the last reference to the context goes; a node the
        # test still holds keeps it (rclpy finalises the context once
        # nothing of it holds it any more).
        context.destroy()


# The plugin loads in every pytest run of the environment: never break one
# that lacks pytest-asyncio.
if importlib.util.find_spec("pytest_asyncio") is not None:
    import pytest_asyncio

    @pytest_asyncio.fixture
    async def container_host(ros_context: Context) -> AsyncIterator[ContainerHost]:
        """A container serving on the test's loop, with the installed plugins' node types."""
        async with open_container_host(context=ros_context) as host:
            yield host

else:

    @pytest.fixture
    def container_host() -> None:
        """Needs pytest-asyncio, which is not installed."""
        pytest.fail("the container_host fixture needs pytest-asyncio: pip install pytest-asyncio")
