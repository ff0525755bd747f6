"""A running container process: registry, executor, container node, nodes.

``run_container`` is what ``container run`` does. It installs its own
SIGINT/SIGTERM handling on the event loop (rclpy's own handlers would shut
the context down under the nodes' feet) and, on either signal, unloads every
node through its lifecycle, destroys the container node and releases the
executor, so the process exits with no thread left behind.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import threading
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

import rclpy
from rclpy.context import Context
from rclpy.signals import SignalHandlerOptions

from ._config import ContainerConfig
from ._container import ComponentManager, requests_from_specs
from ._errors import ContainerError
from .executor import AsyncioExecutor
from .lifecycle import contain_fault
from ._params import node_parameters
from ._registry import PluginRegistry
from ._runtime import use_fast_discovery
from ._services import ContainerServices

__all__ = ["ContainerApp", "run_container"]

#: Extensions started after the configured nodes load (the lifecycle manager);
#: each returns a coroutine to await on shutdown.
Extension = Callable[["ContainerApp"], Awaitable[None]]


@dataclass
class ContainerApp:
    """Everything one container process owns, built from its configuration.

    The container node serves the ``composition_interfaces`` services from
    the start, so ``container load`` and ``ros2 component load`` work on it.
    """

    config: ContainerConfig
    context: Context
    registry: PluginRegistry
    executor: AsyncioExecutor
    manager: ComponentManager
    services: ContainerServices
    stopping: asyncio.Event = field(default_factory=asyncio.Event)

    @classmethod
    def create(cls, config: ContainerConfig, *, context: Context) -> ContainerApp:
        registry = PluginRegistry(
            allow=config.plugins_allow, block=config.plugins_block, trace=config.trace_hooks
        )
        executor = AsyncioExecutor(
            context=context,
            reentrant_limit=config.reentrant_limit,
            on_callback_error=contain_fault,
        )
        namespace = config.namespace if config.namespace.startswith("/") else f"/{config.namespace}"
        full_name = f"{namespace.rstrip('/')}/{config.name}"
        manager = ComponentManager(
            registry=registry,
            executor=executor,
            name=config.name,
            namespace=namespace,
            context=context,
            parameter_overrides=node_parameters(
                config.parameters, full_name=full_name, base_dir=config.base_dir
            ),
            unload_timeout=config.unload_timeout,
        )
        services = ContainerServices(manager)
        executor.add_node(manager)
        for failure in registry.failures:
            manager.get_logger().error(f"Plugin skipped: {failure}")
        return cls(config, context, registry, executor, manager, services)

    async def serve(self, *, extensions: tuple[Extension, ...] = ()) -> None:
        """Load the configured nodes, run until :meth:`stop`, then unload all."""
        loop = asyncio.get_running_loop()
        for signum in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(signum, self.stop)
        log = self.manager.get_logger()
        try:
            for request in requests_from_specs(self.config.nodes):
                try:
                    await self.manager.load_and_start(request, timeout=self.config.unload_timeout)
                except ContainerError as exc:
                    # A bad entry costs that node only; the container serves on.
                    log.error(f"Could not start {request.package}::{request.plugin}: {exc}")
            running = [asyncio.ensure_future(extension(self)) for extension in extensions]
            log.info(
                f"Container '{self.manager.get_fully_qualified_name()}' ready with "
                f"{len(self.manager.loaded())} node(s)"
            )
            await self.stopping.wait()
            log.info("Shutting down")
            for task in running:
                task.cancel()
            await asyncio.gather(*running, return_exceptions=True)
            await self.manager.unload_all()
        finally:
            for signum in (signal.SIGINT, signal.SIGTERM):
                loop.remove_signal_handler(signum)

    def stop(self) -> None:
        self.stopping.set()

    def close(self) -> bool:
        """Destroy the container node and release the executor.

        :return: ``False`` if a callback thread was still running.
        """
        self.services.destroy()
        self.executor.remove_node(self.manager)
        self.manager.destroy_node()
        return self.executor.shutdown()


def run_container(config: ContainerConfig, *, extensions: tuple[Extension, ...] = ()) -> int:
    """Run a container process until SIGINT or SIGTERM; return the exit code."""
    use_fast_discovery()
    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    try:
        app = ContainerApp.create(config, context=context)
        try:
            app.executor.spin_until_future_complete(app.serve(extensions=extensions))
        finally:
            clean = app.close()
        leftover = [t.name for t in threading.enumerate() if t is not threading.main_thread()]
        if leftover:
            # Daemon threads would die silently with the process; say so instead.
            logging.getLogger(__name__).error(f"threads left behind: {', '.join(leftover)}")
            return 1
        return 0 if clean else 1
    finally:
        rclpy.try_shutdown(context=context)
