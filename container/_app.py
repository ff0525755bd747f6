"""The processes: a container (registry, executor, container node, nodes), a manager.

``run_container`` is what ``container run`` does, as a server session
(:mod:`container._session`): on SIGINT or SIGTERM it unloads every node
through its lifecycle and destroys the container node; the session then
releases the executor and reports any thread left behind. The plugins are
discovered (imported) before the session starts ROS: a signal meanwhile
finds nothing to take down, and ends the process at once
(:mod:`container._entry`).

A container given a state file (the ``state_file`` parameter,
:mod:`container._statekeeper`) starts with the nodes it records, each
driven back to its recorded state, in place of its file's nodes, and keeps
the file in step from its start-up on.
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from rclpy.context import Context
from rclpy.exceptions import ParameterException

from ._config import ContainerConfig
from ._container import ComponentManager, LoadedNode, LoadRequest, entry_label, requests_from_specs
from ._diagnostics import LoopDiagnostics
from ._errors import ConfigError, ContainerError
from ._load import LoadReporter
from ._params import node_parameters
from ._registry import PluginRegistry
from ._roslog import route_to
from ._services import ContainerServices
from ._session import EXIT_FAILURE, EXIT_OK, EXIT_USAGE, Session, run_session
from ._statefile import ContainerState, NodeRecord
from ._statekeeper import StateKeeper, restore_of, restore_request
from ._text import clip
from .devices import set_device_policy
from .executor import AsyncioExecutor
from .lifecycle import LifecycleManager, ManagerSettings, contain_fault, is_lifecycle, state_of, transition

if TYPE_CHECKING:
    from rclpy.impl.rcutils_logger import RcutilsLogger

__all__ = ["ContainerApp", "manager_extension", "reload_extension", "run_container", "run_manager"]

#: Extensions started after the configured nodes load (the lifecycle manager);
#: each returns a coroutine to await on shutdown.
Extension = Callable[["ContainerApp"], Awaitable[None]]


@dataclass(frozen=True, slots=True)
class _Entry:
    """One node the start-up loads: an entry of the file, or a record of the state file."""

    index: int
    #: How the log names it: ``nodes[3] (name: front_lidar)``, ``'/demo/talker' (unique_id 4)``.
    label: str
    request: LoadRequest
    #: The state to bring it to: ``inactive``, ``active``, ``finalized``; ``None``: as constructed.
    goal: str | None
    record: NodeRecord | None = None


def _entries(config: ContainerConfig, restoring: ContainerState | None) -> list[_Entry]:
    """What the start-up loads: the state file's nodes when there is one to restore, else the file's."""
    if restoring is None:
        return [
            _Entry(index, entry_label(index, request), request, "active" if request.wants_autostart else None)
            for index, request in enumerate(requests_from_specs(config.nodes))
        ]
    return [
        _Entry(
            index,
            # The file may have been edited by hand: its text is echoed clipped.
            f"{clip(record.full_name, quote=True)} (unique_id {record.unique_id}, {clip(record.type_label)})",
            restore_request(record),
            None if record.state == "unconfigured" else record.state,
            record,
        )
        for index, record in enumerate(restoring.nodes)
    ]


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
    diagnostics: LoopDiagnostics
    #: The per-node load on ``~/load`` (``None``: the executor keeps no accounts).
    load: LoadReporter | None
    #: The state file's keeper (``None``: no ``state_file``).
    state: StateKeeper | None = None
    stopping: asyncio.Event = field(default_factory=asyncio.Event)

    @classmethod
    def create(
        cls,
        config: ContainerConfig,
        *,
        context: Context,
        executor: AsyncioExecutor | None = None,
        registry: PluginRegistry | None = None,
    ) -> ContainerApp:
        """Build the container on ``executor`` (by default a new one made for ``config``).

        Installs the file's device policy for the process (what port
        parameters of the plugins it loads may name).

        :param registry: the plugins, discovered already (by default
            discovered now, as ``config`` narrows them: :func:`discover`).
        """
        set_device_policy(config.devices)
        if registry is None:
            registry = discover(config)
        if executor is None:
            executor = AsyncioExecutor(
                context=context,
                reentrant_limit=config.reentrant_limit,
                on_callback_error=contain_fault,
                stall_after=config.watchdog_threshold,
            )
        namespace = config.namespace if config.namespace.startswith("/") else f"/{config.namespace}"
        manager = ComponentManager(
            registry=registry,
            executor=executor,
            name=config.name,
            namespace=namespace,
            context=context,
            parameter_overrides=node_parameters(
                config.parameters, full_name=config.full_name, base_dir=config.base_dir
            ),
            unload_timeout=config.unload_timeout,
            load_timeout=config.load_timeout,
            use_intra_process_comms=config.use_intra_process_comms,
        )
        services = ContainerServices(manager)
        accounting = executor.accounting
        try:
            load = LoadReporter(manager, accounting) if accounting is not None else None
            state = StateKeeper.from_parameter(manager)
        except (ConfigError, ParameterException):
            services.destroy()
            manager.destroy_node()
            raise
        diagnostics = LoopDiagnostics(manager, executor, load=load)
        # The registry has logged each plugin it skipped, once.
        executor.add_node(manager)
        # From here on the process's own lines (signals, the watchdog) are
        # the container node's: on /rosout with its name.
        route_to(manager)
        return cls(config, context, registry, executor, manager, services, diagnostics, load, state)

    async def serve(
        self,
        *,
        extensions: tuple[Extension, ...] = (),
        stopping: asyncio.Event | None = None,
        stop_asked: Callable[[], bool] | None = None,
        on_ready: Callable[[], None] | None = None,
        exit_on_failure: bool | None = None,
    ) -> list[str]:
        """Load the configured nodes, run until :meth:`stop` (or ``stopping``), then unload all.

        A stop requested while the nodes load ends the loading: what loaded
        is unloaded, and ``on_ready`` is never called. With a state file to
        restore, its nodes load in place of the file's, each brought back to
        its recorded state; one that cannot load is skipped (it never counts
        as a failure of the file's).

        :param stop_asked: whether a stop was asked for that ``stopping`` does
            not show yet (a signal the loop has not handled: the loop was busy
            constructing a node); looked at before each node's load and start.
        :param on_ready: called once every listed node was tried.
        :param exit_on_failure: stop at once, right after ready, when a listed
            node failed (default: the file's ``on_failure``).
        :return: the listed nodes that failed, one line each
            (``nodes[3] (name: front_lidar): reason``).
        """
        if stopping is not None:
            self.stopping = stopping

        def stop_now() -> bool:
            return self.stopping.is_set() or (stop_asked is not None and stop_asked())

        if exit_on_failure is None:
            exit_on_failure = self.config.on_failure == "exit"
        log = self.manager.get_logger()
        restoring = self.state.take_over() if self.state is not None else None
        if restoring is not None and self.state is not None:
            instead = f", in place of the {len(self.config.nodes)} node(s) the file lists" if self.config.nodes else ""
            log.info(
                f"Restoring {len(restoring.nodes)} node(s) from the state file '{self.state.path}' "
                f"(written {restoring.written or 'at an unknown time'} by process {restoring.pid or '?'}){instead}"
            )
        began = asyncio.get_running_loop().time()
        entries = _entries(self.config, restoring)
        failed, constructed = await self._bring_up(entries, stop_now=stop_now)
        if restoring is not None:
            self._report_restore(restoring, constructed, asyncio.get_running_loop().time() - began)
        if self.state is not None and not stop_now():
            self.state.record()
        failed.sort(key=lambda failure: failure[0])
        running: list[asyncio.Future[None]] = []
        if not stop_now():
            running = [asyncio.ensure_future(extension(self)) for extension in extensions]
            loaded = len(self.manager.loaded())
            log.info(f"Container '{self.manager.get_fully_qualified_name()}' ready with {loaded} node(s)")
            _summarise_warnings(log, [(entry.label, node) for entry, node in constructed if entry.record is None])
            if failed:
                log.error(
                    f"{len(failed)} of the {len(entries)} node(s) the file lists failed: "
                    + ", ".join(entry for _, entry, _ in failed)
                    + (" (on_failure: exit, so the container stops)" if exit_on_failure else "")
                )
            if on_ready is not None:
                on_ready()
            if not (failed and exit_on_failure):
                await self.stopping.wait()
        log.info("Shutting down")
        if self.state is not None:
            # The shutdown's unloads are not recorded: should the process die
            # meanwhile, the file still holds every node.
            self.state.stop()
        for task in running:
            task.cancel()
        await asyncio.gather(*running, return_exceptions=True)
        await self.manager.unload_all()
        if self.state is not None:
            await self.state.clear()
        return [f"{entry}: {exc}" for _, entry, exc in failed]

    async def _bring_up(
        self, entries: Sequence[_Entry], *, stop_now: Callable[[], bool]
    ) -> tuple[list[tuple[int, str, ContainerError]], list[tuple[_Entry, LoadedNode]]]:
        """Load ``entries``: every one constructed first, in order, then served, then brought up.

        Nav2's bring-up: every node to be started configured, in order, then
        every node to be activated activated. A node's activation finds the
        others configured, and nothing publishes while the rest are still
        being configured (see ComponentManager.load's ``serve``).

        :param stop_now: whether a stop was asked for (looked at before
            each node's load and each transition).
        :return: the file's entries that failed (index, label, error), and
            every node constructed with its entry.
        """
        log = self.manager.get_logger()
        failed: list[tuple[int, str, ContainerError]] = []

        def fail(entry: _Entry, exc: ContainerError, *, constructed: bool) -> None:
            if entry.record is None:
                # A bad entry costs that node only; the container serves on.
                log.error(f"Could not start {entry.label}: {exc}")
                failed.append((entry.index, entry.label, exc))
            elif constructed:
                log.error(f"Could not bring {entry.label} back to {entry.goal}: {exc}")
            else:
                log.error(f"Could not restore {entry.label}: {exc}; skipped, and dropped from the state file")

        constructed: list[tuple[_Entry, LoadedNode]] = []
        try:
            for entry in entries:
                if stop_now():
                    break
                restore = restore_of(entry.record) if entry.record is not None else None
                try:
                    loaded = await self.manager.load(entry.request, serve=False, restore=restore)
                except ContainerError as exc:
                    fail(entry, exc, constructed=False)
                    continue
                if entry.record is not None and self.state is not None:
                    self.state.carry_over(loaded, entry.record)
                constructed.append((entry, loaded))
        finally:
            self.manager.serve_loaded(node for _, node in constructed)
        timeout = self.config.unload_timeout
        starting = [item for item in constructed if item[0].goal in ("inactive", "active")]
        for until in ("inactive", "active"):
            for item in list(starting):
                entry, node = item
                if stop_now():
                    break
                if not self.manager.holds(node) or (until == "active" and entry.goal != "active"):
                    continue
                try:
                    await self.manager.start(node, timeout=timeout, until=until)
                except ContainerError as exc:
                    fail(entry, exc, constructed=True)
                    starting.remove(item)
        for entry, node in constructed:
            # Only a state file's record asks for it: a node shut down for good.
            if entry.goal == "finalized" and self.manager.holds(node) and not stop_now():
                try:
                    await transition(self.executor, node.node, "shutdown", timeout=timeout)
                except ContainerError as exc:
                    fail(entry, exc, constructed=True)
        return failed, constructed

    def _report_restore(
        self, restoring: ContainerState, constructed: Sequence[tuple[_Entry, LoadedNode]], seconds: float
    ) -> None:
        """One line per node restored (its state, and whether it is the recorded one), then a summary."""
        log = self.manager.get_logger()
        restored = [(entry, node) for entry, node in constructed if self.manager.holds(node)]
        for entry, node in restored:
            state = state_of(node.node) if is_lifecycle(node.node) else None
            what = f"Restored '{node.full_name}' (unique_id {node.unique_id})"
            if entry.goal is not None and state != entry.goal:
                log.warning(f"{what}: {state}, not {entry.goal} as recorded")
            else:
                log.info(f"{what}{f': {state}' if state is not None else ''}")
        log.info(
            f"Restored {len(restored)} of the {len(restoring.nodes)} node(s) of the state file in {seconds:.2f} s"
            + (f"; next unique_id {self.manager.next_unique_id}" if restoring.nodes else "")
        )

    def stop(self) -> None:
        self.stopping.set()

    def close(self) -> None:
        """Destroy the container node; the executor is its owner's to shut down."""
        if self.state is not None:
            self.state.close()
        self.services.destroy()
        self.diagnostics.close()
        if self.load is not None:
            self.load.close()
        self.executor.remove_node(self.manager)
        route_to(None)  # before the node's /rosout publisher goes
        self.manager.destroy_node()


def discover(config: ContainerConfig) -> PluginRegistry:
    """The installed plugins, as the container file narrows them (``container.plugins``)."""
    return PluginRegistry(allow=config.plugins_allow, block=config.plugins_block, trace=config.trace_hooks)


def _summarise_warnings(log: RcutilsLogger, constructed: Sequence[tuple[str, LoadedNode]]) -> None:
    """Repeat, at ready, the warnings the file's loads caused: one line each, after a count.

    They were logged as they happened, among the start-up's other lines;
    whoever reads the start-up's end (a terminal, ``ros2 launch``'s output)
    sees them here without scrolling back.
    """
    warned = [(entry, warning) for entry, loaded in constructed for warning in loaded.warnings]
    if not warned:
        return
    log.warning(f"{len(warned)} warning(s) while loading the file's nodes:")
    for entry, warning in warned:
        log.warning(f"  {entry} [{warning.logger}]: {warning.message}")


def run_container(
    config: ContainerConfig,
    *,
    extensions: tuple[Extension, ...] = (),
    ros_args: Sequence[str] = (),
    exit_on_failure: bool | None = None,
) -> int:
    """Run a container process until SIGINT or SIGTERM; return the exit code.

    :param ros_args: the command line's ROS arguments; rcl applies them to
        the container node (its name, namespace, parameters, remaps) and to
        logging, not to the nodes it loads unless a load forwards them.
    :param exit_on_failure: exit 1 right after start-up when a listed node
        failed to load or start (default: the file's ``on_failure``, whose
        default ``continue`` serves on and exits 0, as rclcpp's container).
    """

    # Plugins import before ROS starts: nothing to take down if a signal
    # comes meanwhile (the entry point's handler ends the process).
    registry = discover(config)

    async def main(session: Session) -> int:
        try:
            app = ContainerApp.create(config, context=session.context, executor=session.executor, registry=registry)
        except (ParameterException, ConfigError) as exc:
            # A container parameter of the wrong type or value (--params-file, -p, the file).
            print(f"container run: {' '.join(str(exc).split())}", file=sys.stderr)
            return EXIT_USAGE
        exits = config.on_failure == "exit" if exit_on_failure is None else exit_on_failure
        try:
            failures = await app.serve(
                extensions=extensions,
                stopping=session.stopping,
                stop_asked=session.stop_asked,
                on_ready=session.mark_ready,
                exit_on_failure=exits,
            )
        finally:
            app.close()
        return EXIT_FAILURE if failures and exits else EXIT_OK

    return run_session(
        main,
        server=True,
        executor_options={
            "reentrant_limit": config.reentrant_limit,
            "on_callback_error": contain_fault,
            "shutdown_timeout": config.shutdown_timeout,
            "stall_after": config.watchdog_threshold,
        },
        ros_args=ros_args,
    )


def manager_extension(settings: ManagerSettings) -> Callable[[ContainerApp], Awaitable[None]]:
    """A container extension running a manager next to the container's nodes.

    On container shutdown it resets the nodes it manages in reverse order
    (bounded by the container's ``unload_timeout`` per node) before the
    container unloads them.
    """

    async def run(app: ContainerApp) -> None:
        manager = LifecycleManager(settings, context=app.context, namespace=settings.namespace)
        app.executor.add_node(manager)
        try:
            await manager.run()
        finally:
            try:
                await manager.settle(timeout=app.config.unload_timeout * max(1, len(manager.node_names)))
            finally:
                app.executor.remove_node(manager)
                manager.destroy_node()

    return run


def reload_extension() -> Callable[[ContainerApp], Awaitable[None]]:
    """A container extension reloading a plugin's nodes when its code changes (``container run --reload``)."""

    async def run(app: ContainerApp) -> None:
        from ._watch import SourceWatcher

        await SourceWatcher(app.services.reloader, app.registry, app.manager.get_logger()).run()

    return run


def run_manager(settings: ManagerSettings, *, ros_args: Sequence[str] = ()) -> int:
    """Run a manager as its own process until SIGINT or SIGTERM; the exit code.

    Like Nav2's, a manager process that stops leaves the nodes as they are.

    :param ros_args: the command line's ROS arguments, for the manager node
        (``-r __node:=``, ``--params-file`` with Nav2's parameters, ...);
        ``settings`` win over them, as constructor overrides do in rclpy.
    """
    async def main(session: Session) -> int:
        try:
            manager = LifecycleManager(settings, context=session.context, use_global_arguments=True)
        except ParameterException as exc:
            # A parameter of the wrong type in --params-file or -p.
            print(f"container manager: {' '.join(str(exc).split())}", file=sys.stderr)
            return EXIT_USAGE
        session.executor.add_node(manager)
        route_to(manager)
        session.mark_ready()
        running = asyncio.ensure_future(manager.run())
        try:
            await session.stopping.wait()
        finally:
            running.cancel()
            await asyncio.gather(running, return_exceptions=True)
            session.executor.remove_node(manager)
            route_to(None)
            manager.destroy_node()
        return EXIT_OK

    return run_session(main, server=True, ros_args=ros_args)
