"""Reloading nodes in a live container: new code in, under the same names, in the same states.

A reload works on a whole plugin distribution, because that is what can be
imported afresh: its modules are imported again (off the event loop), its
node types registered from the new code, and only then are its loaded nodes
taken down their lifecycle, in reverse load order, unloaded, loaded again
from the new classes under the same requests (name, namespace, remap rules,
parameters), with the parameters set on them since they were loaded at
their current values and each one's ``reload_state`` dict, and driven back
to the states they were in (all configured, in load order, then all
activated, as a container file's start-up). Every other node runs on
throughout.

If the new code fails to import or register, nothing was touched. If a new
node fails to construct or to come back to its state, the new nodes are
unloaded, the old code is put back, and the old code's nodes are loaded
again the same way; the error says what failed, where, and what runs now.
"""

from __future__ import annotations

import asyncio
import functools
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ._container import RELOAD_STATE, Carry, LoadedNode, LoadRequest
from ._errors import ContainerError, LoadError, ReloadError
from ._reimport import failure_location
from ._text import MESSAGE_LIMIT, clip
from .executor import Escaped, in_thread
from .lifecycle import LifecycleNode, is_lifecycle, state_of

if TYPE_CHECKING:
    from rclpy.parameter import Parameter

    from ._container import ComponentManager
    from ._reimport import Reimported

__all__ = ["Reloaded", "Reloader"]

#: The primary state a node in a transition is headed for (rcl's transition states).
_HEADED_FOR = {
    "configuring": "inactive",
    "activating": "active",
    "deactivating": "inactive",
    "cleaningup": "unconfigured",
    "shuttingdown": "finalized",
    "errorprocessing": "unconfigured",
}


@dataclass(frozen=True, slots=True)
class Reloaded:
    """What a reload did."""

    distribution: str
    #: The nodes now loaded in place of the old ones, in load order.
    nodes: tuple[LoadedNode, ...]
    #: The unique ids they replaced, in the same order.
    replaced: tuple[int, ...]
    seconds: float
    #: What had to be cut short while unloading the old nodes.
    notes: tuple[str, ...] = ()

    def describe(self) -> str:
        """One line for the log: which nodes, old and new ids, states, how long."""
        if not self.nodes:
            return f"Reloaded the code of {self.distribution!r} (no node of it loaded) in {self.seconds:.2f} s"
        nodes = ", ".join(
            f"'{loaded.full_name}' (unique_id {old} -> {loaded.unique_id}{_state_suffix(loaded)})"
            for old, loaded in zip(self.replaced, self.nodes, strict=True)
        )
        return f"Reloaded {self.distribution!r} in {self.seconds:.2f} s: {nodes}"


def _state_suffix(loaded: LoadedNode) -> str:
    return f", {state_of(loaded.node)}" if is_lifecycle(loaded.node) else ""


@dataclass(frozen=True, slots=True)
class _Kept:
    """One old node, as the reload needs it to load its successor."""

    request: LoadRequest
    full_name: str
    unique_id: int
    #: The state to drive the new node to (``None``: as constructed).
    goal: str | None
    carry: Carry


class Reloader:
    """Reload the nodes of a plugin distribution on a :class:`ComponentManager`.

    :param timeout: seconds each lifecycle step may take (default: the
        manager's ``unload_timeout``).
    """

    def __init__(self, manager: ComponentManager, *, timeout: float | None = None) -> None:
        self._manager = manager
        self._timeout = manager.unload_timeout if timeout is None else timeout

    async def reload_node(self, node: int | str) -> Reloaded:
        """Reload the node with unique id or full name ``node``, with every other node of its distribution.

        :raises LoadError: no such node.
        :raises ReloadError: the reload failed; its message says what runs now.
        """
        if isinstance(node, int):
            loaded = self._manager.find(node)
        else:
            loaded = self._manager.find_named(node if node.startswith("/") else f"/{node}")
        return await self.reload_distribution(loaded.node_type.distribution)

    async def reload_distribution(self, distribution: str) -> Reloaded:
        """Import ``distribution`` afresh and reload its loaded nodes (see the module's docs)."""
        async with self._manager.changing:
            if self._manager.closed:
                raise LoadError("the container is shutting down: nothing is reloaded")
            return await self._reload(distribution)

    async def _reload(self, distribution: str) -> Reloaded:
        manager = self._manager
        log = manager.get_logger()
        began = time.monotonic()
        group = [loaded for loaded in manager.loaded() if loaded.node_type.distribution == distribution]
        untouched = "nothing was changed: the old code's nodes run on" if group else "nothing was changed"
        importing = asyncio.ensure_future(
            in_thread(functools.partial(manager.registry.reimport, distribution), name=f"reimport:{clip(distribution)}")
        )
        try:
            swap: Reimported = await asyncio.wait_for(asyncio.shield(importing), manager.load_timeout)
        except TimeoutError:
            # It runs on (a thread cannot be stopped); should it succeed, the old code goes back.
            importing.add_done_callback(_undo_when_done)
            raise ReloadError(
                f"Could not reload {distribution!r}: importing its new code did not end within "
                f"{manager.load_timeout:g} s (load_timeout); {untouched}",
                distribution=distribution, old_code_running=bool(group),
            ) from None
        except LoadError as exc:
            # The registry's ReloadError (the new code failed) knows where.
            location = exc.location if isinstance(exc, ReloadError) else ""
            raise ReloadError(
                f"Could not reload {distribution!r}: {exc}; {untouched}",
                distribution=distribution, location=location, old_code_running=bool(group),
            ) from exc
        missing = sorted({loaded.node_type.full_name for loaded in group} - set(swap.types))
        if missing:
            swap.undo()
            raise ReloadError(
                f"Could not reload {distribution!r}: its new code registers no {', '.join(missing)}; {untouched}",
                distribution=distribution, old_code_running=True,
            )
        before = [await self._before(loaded) for loaded in group]
        notes: list[str] = []
        for loaded in reversed(group):
            _, cut = await manager.unload(loaded.unique_id)
            notes.extend(f"'{loaded.full_name}': {note}" for note in cut)
        kept = [
            _Kept(loaded.request, loaded.full_name, loaded.unique_id, goal, Carry(changed, _reload_state_of(loaded)))
            for loaded, (goal, changed) in zip(group, before, strict=True)
        ]
        try:
            nodes = await self._bring_back(kept)
        except ContainerError as exc:
            swap.undo()
            location = failure_location(_root_cause(exc), manager.registry.modules_of(distribution))
            failure = clip(" ".join(str(exc).split()), limit=MESSAGE_LIMIT)
            if location:
                failure = f"{location}: {failure}"
            log.warning(f"Reloading {distribution!r}: the new code failed; loading the old code's nodes again")
            problems = await self._salvage(kept)
            now = (
                "the old code's nodes were loaded again"
                if not problems
                else "the old code's nodes could not all be loaded again: " + "; ".join(problems)
            )
            raise ReloadError(
                f"Could not reload {distribution!r}: {failure}; {now}",
                distribution=distribution, location=location, old_code_running=not problems,
            ) from exc
        reloaded = Reloaded(
            distribution, tuple(nodes), tuple(k.unique_id for k in kept), time.monotonic() - began, tuple(notes)
        )
        log.info(reloaded.describe())
        return reloaded

    async def _before(self, loaded: LoadedNode) -> tuple[str | None, list[Parameter[Any]]]:
        """What the new node takes over that must be read while the old one runs: its goal state
        (``None``: unconfigured, as constructed) and the parameters set on it."""
        node = loaded.node
        goal: str | None = None
        if is_lifecycle(node):
            if isinstance(node, LifecycleNode):
                # A transition under way (a peer's change_state) ends first.
                await node.end_transition(timeout=self._timeout)
            state = state_of(node)
            goal = _HEADED_FOR.get(state, state)
            if goal == "unconfigured":
                goal = None
        return goal, loaded.changed_parameters()

    async def _bring_back(self, kept: Sequence[_Kept]) -> list[LoadedNode]:
        """Load a node for each of ``kept`` from the registry's current code, and drive it to its goal.

        All or nothing: on a failure, what was loaded is unloaded again.
        """
        manager = self._manager
        built: list[LoadedNode] = []
        try:
            for item in kept:
                # A copy: what a new node that fails wrote in it is not what the old code gets back.
                carry = Carry(item.carry.changed_parameters, dict(item.carry.state))
                built.append(await manager.load(item.request, serve=False, carry=carry))
            manager.serve_loaded(built)
            for until in ("inactive", "active"):
                for item, loaded in zip(kept, built, strict=True):
                    if item.goal == "active" or (item.goal == "inactive" and until == "inactive"):
                        await manager.start(loaded, timeout=self._timeout, until=until)
            for item, loaded in zip(kept, built, strict=True):
                if item.goal == "finalized":
                    await manager.shut_down(loaded, timeout=self._timeout)
        except ContainerError:
            for loaded in reversed(built):
                if manager.holds(loaded):
                    await manager.unload(loaded.unique_id)
            raise
        return built

    async def _salvage(self, kept: Sequence[_Kept]) -> list[str]:
        """Load the old code's nodes again, each on its own: one that fails costs only itself.

        :return: what failed, one entry per node.
        """
        problems: list[str] = []
        for item in kept:
            try:
                await self._bring_back([item])
            except ContainerError as exc:
                problems.append(f"'{item.full_name}': {clip(' '.join(str(exc).split()))}")
        return problems


def _reload_state_of(node: LoadedNode) -> dict[str, Any]:
    """The old node's ``reload_state``, read once it is down (its shutdown may have written it)."""
    state = getattr(node.node, RELOAD_STATE, None)
    return state if isinstance(state, dict) else {}


def _undo_when_done(importing: asyncio.Future[Reimported]) -> None:
    """Put the old code back after an import the reload gave up on, if it succeeded after all."""
    if not importing.cancelled() and importing.exception() is None:
        importing.result().undo()


def _root_cause(error: BaseException) -> BaseException:
    """The error at the bottom of ``error``'s chain: what the plugin's code raised."""
    while True:
        if isinstance(error, Escaped):
            error = error.error
        elif error.__cause__ is not None:
            error = error.__cause__
        else:
            return error
