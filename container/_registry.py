"""Plugin discovery and the table of node types the container can load.

Plugins are loaded one entry point at a time, each inside its own
``try``/``except``: a plugin that fails to import, implements a hook wrongly,
raises while registering or registers something invalid is recorded as a
:class:`PluginError`, logged, and skipped as a whole, so one broken
distribution never takes the container down with it.

A request names a node type by ``package_name`` and ``plugin_name`` strings;
they are only ever looked up in this table. Nothing imports a module path that
came from a request.

The table follows what is installed while the container runs, as far as that
can be done without restarting Python: a request for a type the table does
not know makes the registry look at the installed entry points again (a
distribution installed after start loads), and a type whose distribution was
uninstalled or replaced since it was imported is refused (its code may be
gone or changed; only a restart imports the new code). A distribution's
code can be imported afresh in place (:meth:`PluginRegistry.reimport`, for
``container reload``): its modules are imported again and its types
registered from the new code, or, if that fails, left as they were.
"""

from __future__ import annotations

import importlib.metadata
import logging
import os
import types
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Final

import pluggy
from rclpy.node import Node

from . import _hookspecs
from ._errors import LoadError, PluginError, ReloadError
from ._hookspecs import ros_package_name
from ._text import clip

if TYPE_CHECKING:
    # The reload's machinery is imported when a reload asks for it: a
    # container that never reloads does not pay for it at start-up.
    from ._reimport import DistributionModules, Reimport, Reimported

__all__ = ["ENTRY_POINT_GROUP", "NodeType", "PluginRegistry", "ros_package_name"]

#: The entry point group plugin distributions declare their plugins under.
ENTRY_POINT_GROUP: Final = "container.plugins"

_BLOCK_ENV: Final = "CONTAINER_PLUGINS_BLOCK"
_ALLOW_ENV: Final = "CONTAINER_PLUGINS_ALLOW"
_TRACE_ENV: Final = "CONTAINER_TRACE_HOOKS"

# rclcpp's ComponentManager wording, which `ros2 component load` users know.
_NO_PACKAGE: Final = "Could not find requested resource in ament index"
_NO_CLASS: Final = "Failed to find class with the requested plugin name."

logger = logging.getLogger("container.plugins")
#: Receives pluggy's hook-call trace when tracing is on.
trace_logger = logging.getLogger("container.hooks")


@dataclass(frozen=True)
class NodeType:
    """A node class a plugin registered, under its ``package::Type`` name.

    :param distribution: the distribution's name as its metadata spells it.
    """

    package: str
    name: str
    node_class: type[Node]
    distribution: str
    full_name: str = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "full_name", f"{self.package}::{self.name}")


class _Registrar:
    """The ``register`` callback handed to one plugin's hook call.

    It stages what the plugin registers, so that a plugin failing half-way
    leaves nothing behind, and it remembers the first invalid registration
    even if the plugin catches the error it raised.
    """

    def __init__(
        self,
        *,
        distribution: str,
        entry_point: str | None,
        taken: Mapping[str, NodeType],
    ) -> None:
        self._distribution = distribution
        self._entry_point = entry_point
        self._package = ros_package_name(distribution)
        self._taken = taken
        self.staged: dict[str, NodeType] = {}
        self.error: PluginError | None = None
        self.open = True

    def __repr__(self) -> str:
        # Shows in hook traces: says whose hook call this one is.
        where = f" entry point {self._entry_point!r}" if self._entry_point else ""
        return f"<register for distribution {self._distribution!r}{where}>"

    def __call__(self, node_class: type[Node], /, *, name: str | None = None) -> None:
        if not self.open:
            raise self.failure("register() called after register_node_types returned")
        try:
            node_type = self._validate(node_class, name)
        except PluginError as exc:
            if self.error is None:
                self.error = exc
            raise
        self.staged[node_type.full_name] = node_type

    def _validate(self, node_class: object, name: str | None) -> NodeType:
        if not isinstance(node_class, type):
            raise self.failure(f"cannot register {node_class!r}: not a class")
        if not issubclass(node_class, Node):
            raise self.failure(
                f"cannot register {node_class.__qualname__}: "
                "not a subclass of rclpy.node.Node"
            )
        type_name = node_class.__name__ if name is None else name
        if not isinstance(type_name, str) or not type_name.isidentifier():
            raise self.failure(
                f"cannot register {node_class.__qualname__} as {type_name!r}: "
                "the type name must be a Python identifier"
            )
        node_type = NodeType(
            package=self._package,
            name=type_name,
            node_class=node_class,
            distribution=self._distribution,
        )
        full_name = node_type.full_name
        if full_name in self.staged:
            raise self.failure(f"node type {full_name!r} is registered twice")
        if full_name in self._taken:
            owner = self._taken[full_name].distribution
            raise self.failure(
                f"node type {full_name!r} is already registered by "
                f"distribution {owner!r}"
            )
        return node_type

    def failure(self, reason: str) -> PluginError:
        return PluginError(
            reason, distribution=self._distribution, entry_point=self._entry_point
        )


def _names_from_env(variable: str) -> set[str] | None:
    value = os.environ.get(variable)
    if value is None:
        return None
    return {name.strip() for name in value.split(",") if name.strip()}


def _flag_from_env(variable: str) -> bool:
    return os.environ.get(variable, "").strip().lower() in {"1", "true", "yes", "on"}


def _one_line(text: str) -> str:
    # pluggy's validation messages span lines; a log line and a LoadNode
    # error_message read better as one.
    return "; ".join(line.strip() for line in text.splitlines() if line.strip())


class PluginRegistry:
    """Load plugin distributions and keep the node types they register.

    Restrictions from the keyword arguments (the configuration file) and from
    the environment only ever narrow what loads: a distribution named in
    either block-list is skipped, and when both allow-lists are given a
    distribution must be in both. An empty allow-list loads no plugin.
    Distribution names match whatever their spelling of case, ``-``, ``_``
    and ``.``.

    :param block: distributions never to load (also ``CONTAINER_PLUGINS_BLOCK``,
        comma-separated).
    :param allow: if given, the only distributions to load (also
        ``CONTAINER_PLUGINS_ALLOW``).
    :param trace: log every hook call to the ``container.hooks`` logger (also
        ``CONTAINER_TRACE_HOOKS=1``).
    :param group: the entry point group to discover; tests point it elsewhere
        so installed plugins stay out of the way.
    """

    def __init__(
        self,
        *,
        block: Iterable[str] = (),
        allow: Iterable[str] | None = None,
        trace: bool = False,
        group: str = ENTRY_POINT_GROUP,
    ) -> None:
        self._pm = pluggy.PluginManager(_hookspecs.PROJECT_NAME)
        self._pm.add_hookspecs(_hookspecs)
        if trace or _flag_from_env(_TRACE_ENV):
            self._pm.trace.root.setwriter(_write_trace)
            self._pm.enable_tracing()
        self._group = group
        self._types: dict[str, NodeType] = {}
        self._failures: list[PluginError] = []
        # What discovery has looked at: (distribution, entry point, version)
        # triples, so a rescan loads only entry points it has not tried.
        self._seen: set[tuple[str, str, str]] = set()
        # Distributions that registered types through entry points, with the
        # metadata they were loaded from: a type is only handed out while that
        # metadata is still installed.
        self._sources: dict[str, tuple[importlib.metadata.Distribution, str]] = {}
        # Distributions dropped because their files changed, with the reason.
        self._stale: dict[str, str] = {}
        # Those of them whose metadata was gone (uninstalled), not replaced.
        self._uninstalled: set[str] = set()
        env_block = _names_from_env(_BLOCK_ENV) or set()
        self._block = {ros_package_name(name) for name in (*block, *env_block)}
        self._allow: list[set[str]] = [
            {ros_package_name(name) for name in names}
            for names in (allow, _names_from_env(_ALLOW_ENV))
            if names is not None
        ]
        self._load_entry_points(group)

    @property
    def types(self) -> Mapping[str, NodeType]:
        """Node types by full name (``package::Type``), read-only."""
        return types.MappingProxyType(self._types)

    @property
    def failures(self) -> list[PluginError]:
        """Plugins that were skipped because they are broken, in load order."""
        return list(self._failures)

    def packages(self) -> dict[str, list[str]]:
        """Return full type names grouped by package, both sorted.

        This is what ``ros2 component types`` prints: each package, then its
        ``package::Type`` names.
        """
        grouped: dict[str, list[str]] = {}
        for node_type in self._types.values():
            grouped.setdefault(node_type.package, []).append(node_type.full_name)
        return {package: sorted(grouped[package]) for package in sorted(grouped)}

    def resolve(self, package_name: str, plugin_name: str) -> NodeType:
        """Return the registered type a LoadNode request names.

        A name the table does not know makes the registry look for plugins
        installed since (:meth:`rescan`) before it refuses.

        :param plugin_name: ``package::Type`` as ``ros2 component load`` sends
            it, or the bare ``Type``.
        :raises LoadError: with rclcpp's messages, for an unknown package or an
            unknown type in a known package; with the plugin's own failure when
            the package is that of a plugin that could not be loaded; and when
            the type's distribution was uninstalled or replaced since it was imported.
        """
        if "::" not in plugin_name:
            plugin_name = f"{package_name}::{plugin_name}"
        node_type = self._lookup(package_name, plugin_name)
        if node_type is not None:
            self._check_installed(node_type)
            return node_type
        self.rescan()
        node_type = self._lookup(package_name, plugin_name)
        if node_type is not None:
            return node_type
        for distribution, reason in self._stale.items():
            if ros_package_name(distribution) == package_name:
                raise LoadError(f"Cannot load {clip(plugin_name)}: {self._refusal(distribution, reason)}")
        for failure in reversed(self._failures):
            if failure.distribution and ros_package_name(failure.distribution) == package_name:
                raise LoadError(f"Plugin failed to load: {failure}")
        if not any(t.package == package_name for t in self._types.values()):
            raise LoadError(_NO_PACKAGE)
        raise LoadError(_NO_CLASS)

    def rescan(self) -> list[str]:
        """Load the plugins of entry points installed since the last look.

        Entry points already tried (the same distribution, name and version)
        are not imported again, whether they loaded or failed; a distribution
        installed again in another version is tried anew, unless its old
        version was imported (Python keeps the old modules: that needs a
        restart).

        :returns: the full names of the node types that were added.
        """
        importlib.invalidate_caches()
        before = set(self._types)
        self._load_entry_points(self._group)
        added = sorted(set(self._types) - before)
        if added:
            logger.info("Plugins installed since start: %s", ", ".join(added))
        return added

    def _lookup(self, package_name: str, full_name: str) -> NodeType | None:
        node_type = self._types.get(full_name)
        if node_type is None or node_type.package != package_name:
            return None
        return node_type

    def _check_installed(self, node_type: NodeType) -> None:
        """Refuse a type whose distribution's files are not what was imported."""
        reason = self._check_stale(node_type.distribution)
        if reason is not None:
            raise LoadError(f"Cannot load {node_type.full_name}: {reason}")

    def _check_stale(self, distribution: str) -> str | None:
        """Forget ``distribution`` if what was imported is no longer installed.

        :returns: why it was forgotten, or None if it is still installed.
        """
        source = self._sources.get(distribution)
        if source is None or _still_installed(source[0]):
            return None
        importlib.invalidate_caches()
        try:
            now = importlib.metadata.distribution(distribution).version
        except importlib.metadata.PackageNotFoundError:
            # Said of when the container imported it, not of when it started:
            # a plugin installed after start may be uninstalled again.
            reason = f"distribution {distribution!r} is no longer installed"
            self._uninstalled.add(distribution)
        else:
            reason = (
                f"distribution {distribution!r} was replaced after the container imported it "
                f"(version {source[1]} was imported, {now} is installed): restart the "
                "container to load the new code"
            )
        self._forget(distribution, reason)
        return reason

    def _refusal(self, distribution: str, reason: str) -> str:
        """Why a forgotten distribution's types are refused, as things stand now.

        One that was uninstalled may have been installed again since:
        Python keeps the modules it imported first, so only a restart loads it.
        """
        if distribution not in self._uninstalled:
            return reason
        importlib.invalidate_caches()
        try:
            importlib.metadata.distribution(distribution)
        except importlib.metadata.PackageNotFoundError:
            return reason
        return (
            f"distribution {distribution!r} was uninstalled after the container imported it, and installed "
            "again since: restart the container to load it"
        )

    def _forget(self, distribution: str, reason: str) -> None:
        """Drop a distribution's types and hook implementations for good."""
        self._take_out(distribution)
        del self._sources[distribution]
        self._stale[distribution] = reason
        logger.warning("Node types of %s: %s", distribution, reason)

    @property
    def distributions(self) -> tuple[str, ...]:
        """The distributions whose plugins were loaded through entry points, in load order."""
        return tuple(self._sources)

    def modules_of(self, distribution: str) -> DistributionModules:
        """The module trees of a distribution loaded through entry points.

        :raises LoadError: it was not loaded from entry points, or it is the
            container's own.
        """
        from ._reimport import distribution_modules

        if distribution not in self._sources:
            raise LoadError(f"distribution {distribution!r} was not loaded from an installed entry point")
        return distribution_modules(distribution, self._entry_points_of(distribution))

    def reloadable_sources(self) -> dict[str, list[Path]]:
        """The files and directories holding the code of every distribution that can be reimported."""
        from ._reimport import distribution_modules

        found: dict[str, list[Path]] = {}
        entry_points = importlib.metadata.entry_points(group=self._group)
        for distribution in self._sources:
            try:
                modules = distribution_modules(distribution, self._entry_points_of(distribution, entry_points))
            except LoadError:
                continue
            found[distribution] = modules.sources()
        return found

    def _entry_points_of(
        self, distribution: str, entry_points: Iterable[importlib.metadata.EntryPoint] | None = None
    ) -> list[importlib.metadata.EntryPoint]:
        if entry_points is None:
            entry_points = importlib.metadata.entry_points(group=self._group)
        return [
            entry_point
            for entry_point in entry_points
            if entry_point.dist is not None and entry_point.dist.name == distribution
        ]

    def reimport(self, distribution: str) -> Reimported:
        """Import ``distribution``'s modules afresh and register its node types from the new code.

        Blocking (it imports): call it off the event loop. Nodes already
        constructed keep their classes; loads from now on get the new ones.

        :raises LoadError: the distribution cannot be reimported (not from
            entry points, the container's own, uninstalled or replaced).
        :raises ReloadError: its new code fails to import or to register
            (the message starts with the failure's ``file:line``); the old
            code stays in place.
        """
        from ._reimport import Reimported, failure_location, import_afresh

        modules = self.modules_of(distribution)
        reason = self._check_stale(distribution)
        if reason is not None:
            raise LoadError(f"Cannot reload {distribution!r}: {reason}")
        entry_points = self._entry_points_of(distribution)
        old_plugins = [
            (name, plugin) for name, plugin in self._pm.list_name_plugin() if name.startswith(f"{distribution}:")
        ]
        old_types = {name: t for name, t in self._types.items() if t.distribution == distribution}

        def put_back(reimport: Reimport | None) -> None:
            self._take_out(distribution)
            if reimport is not None:
                reimport.undo()
            for name, plugin in old_plugins:
                self._pm.register(plugin, name=name)
            self._types.update(old_types)

        def load_all() -> None:
            # Every module first: an import that fails or never returns leaves the
            # old code's hooks and types in place.
            plugins = [(entry_point.name, self._import(entry_point, distribution)) for entry_point in entry_points]
            self._take_out(distribution)
            for name, plugin in plugins:
                self._add(plugin, distribution=distribution, entry_point=name)

        try:
            _, reimport = import_afresh(modules, load_all)
        except PluginError as exc:
            put_back(None)
            where = failure_location(exc.__cause__ or exc, modules)
            raise ReloadError(
                f"{where + ': ' if where else ''}{exc.reason}",
                distribution=distribution, location=where, old_code_running=True,
            ) from exc
        except BaseException:
            put_back(None)
            raise
        new_types = {name: t for name, t in self._types.items() if t.distribution == distribution}
        logger.info("Imported %s afresh: %s", distribution, ", ".join(sorted(new_types)) or "no node type")
        return Reimported(distribution, types.MappingProxyType(new_types), lambda: put_back(reimport))

    def _take_out(self, distribution: str) -> None:
        """Drop a distribution's types and unregister its hook implementations."""
        for full_name in [name for name, t in self._types.items() if t.distribution == distribution]:
            del self._types[full_name]
        for name, plugin in list(self._pm.list_name_plugin()):
            if name.startswith(f"{distribution}:"):
                self._pm.unregister(plugin)

    def add_plugin(self, plugin: object, *, distribution: str) -> None:
        """Load an in-process plugin object as if ``distribution`` shipped it.

        For built-in node types and for tests; the same checks apply as to an
        installed plugin, but a broken one raises instead of being skipped.

        :raises PluginError: the plugin is invalid; nothing of it was kept.
        """
        self._add(plugin, distribution=distribution, entry_point=None)

    def _load_entry_points(self, group: str) -> None:
        for entry_point in importlib.metadata.entry_points(group=group):
            dist = entry_point.dist
            distribution = dist.name if dist else None
            seen = (distribution or "", entry_point.name, dist.version if dist else "")
            if seen in self._seen:
                continue
            self._seen.add(seen)
            if distribution is None:
                self._fail(
                    PluginError(
                        "the entry point belongs to no distribution",
                        entry_point=entry_point.name,
                    )
                )
                continue
            if not self._permitted(distribution):
                logger.debug(
                    "Not loading plugin %s from distribution %r: not permitted by "
                    "the block/allow lists",
                    entry_point.name,
                    distribution,
                )
                continue
            if distribution in self._stale:
                continue
            source = self._sources.get(distribution)
            if source is not None and dist is not None and dist.version != source[1]:
                # A version other than the one imported: Python keeps the old
                # modules, so only a restart can load the new code.
                self._check_stale(distribution)
                continue
            try:
                plugin = self._import(entry_point, distribution)
                self._add(plugin, distribution=distribution, entry_point=entry_point.name)
            except PluginError as exc:
                self._fail(exc)
            else:
                assert dist is not None
                self._sources[distribution] = (dist, dist.version)

    def _permitted(self, distribution: str) -> bool:
        name = ros_package_name(distribution)
        return name not in self._block and all(name in allow for allow in self._allow)

    @staticmethod
    def _import(entry_point: importlib.metadata.EntryPoint, distribution: str) -> object:
        try:
            return entry_point.load()
        except KeyboardInterrupt:
            raise
        except BaseException as exc:  # sys.exit() at import too: reported and skipped
            raise PluginError(
                f"cannot import {entry_point.value!r}: {type(exc).__name__}: {exc}",
                distribution=distribution,
                entry_point=entry_point.name,
            ) from exc

    def _add(self, plugin: object, *, distribution: str, entry_point: str | None) -> None:
        def error(reason: str) -> PluginError:
            return PluginError(reason, distribution=distribution, entry_point=entry_point)

        pm_name = f"{distribution}:{entry_point or self._pm.get_canonical_name(plugin)}"
        try:
            registered = self._pm.register(plugin, name=pm_name)
        except pluggy.PluginValidationError as exc:
            raise error(f"invalid hook implementation: {_one_line(str(exc))}") from exc
        except Exception as exc:
            raise error(f"cannot register the plugin: {_one_line(str(exc))}") from exc
        if registered is None:
            raise error("the entry point resolved to None")
        try:
            try:
                # Every plugin before this one passed, so it is the culprit.
                self._pm.check_pending()
            except pluggy.PluginValidationError as exc:
                reason = f"invalid hook implementation: {_one_line(str(exc))}"
                raise error(reason) from exc
            registrar = _Registrar(
                distribution=distribution, entry_point=entry_point, taken=self._types
            )
            self._call_register_hook(plugin, registrar)
        except BaseException:
            self._pm.unregister(plugin)
            raise
        self._types.update(registrar.staged)

    def _call_register_hook(self, plugin: object, registrar: _Registrar) -> None:
        # pluggy calls all implementations of a hook together; calling through
        # a subset caller that holds only this plugin tells whose types these
        # are, and still goes through the manager, so tracing sees the call.
        others = [other for other in self._pm.get_plugins() if other is not plugin]
        hook = self._pm.subset_hook_caller("register_node_types", remove_plugins=others)
        raised: BaseException | None = None
        try:
            hook(register=registrar)
        except KeyboardInterrupt:
            raise
        except BaseException as exc:
            raised = exc
        finally:
            registrar.open = False
        if registrar.error is not None:
            raise registrar.error
        if raised is not None:
            raise registrar.failure(
                f"register_node_types raised {type(raised).__name__}: {raised}"
            ) from raised

    def _fail(self, error: PluginError) -> None:
        self._failures.append(error)
        logger.warning("Skipping plugin: %s", error)
        logger.debug("Plugin failure detail", exc_info=error)


def _still_installed(dist: importlib.metadata.Distribution) -> bool:
    # The metadata file goes with its distribution: pip removes it on
    # uninstall, and an upgrade installs another version's directory.
    # (METADATA in a .dist-info, PKG-INFO in an .egg-info.)
    return any(dist.read_text(name) is not None for name in ("METADATA", "PKG-INFO"))


def _write_trace(message: str) -> None:
    trace_logger.info("%s", message.rstrip())
