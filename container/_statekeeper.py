"""Keeping a container's state file in step with what it hosts, and handing it over at start.

The container parameter ``state_file`` (a path; empty, the default: off)
names the file (:mod:`container._statefile` has its format). A container
given one:

* at start, takes the file over (:meth:`StateKeeper.take_over`): locks it
  against any other container process, and reads it; a file it cannot use
  (not JSON, another format or version, another container's) is renamed
  aside, kept as evidence, and the container starts without it;
* records from then on, once its start-up is done, every change: a load,
  an unload, a lifecycle transition (each node's ``transition_event``, so
  that a transition asked for by anyone is seen) and a parameter set on a
  node (``/parameter_events``: ``changed_parameters``, not the declarations
  a node makes); each change rewrites the file atomically, on a thread of
  its own, so that the event loop never waits for the disk; changes that
  come while a write is under way make one more write after it;
* on a clean shutdown (SIGINT, SIGTERM: every node taken down its
  lifecycle) removes the file: the next start is a fresh one. A container
  that dies (``kill -9``, a crash, the out-of-memory killer, a loop stuck
  past the shutdown timeout) leaves it for the next start to restore.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import functools
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from lifecycle_msgs.msg import TransitionEvent
from rcl_interfaces.msg import ParameterDescriptor, ParameterEvent
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, qos_profile_parameter_events

from ._container import LoadedNode, LoadRequest, Restore
from ._errors import StateFileError
from ._statefile import (
    LIFECYCLE_STATES,
    ContainerState,
    NodeRecord,
    encode,
    read_state,
    set_aside,
    temporary_files,
    write_atomically,
)
from ._text import clip
from ._throttle import Throttle
from .executor import in_thread
from .lifecycle import is_lifecycle, state_of

if TYPE_CHECKING:
    from rclpy.subscription import Subscription

    from ._container import ComponentManager

__all__ = ["STATE_FILE_PARAMETER", "StateKeeper", "restore_of", "restore_request"]

#: The container node's parameter that turns the state file on.
STATE_FILE_PARAMETER = "state_file"

_DESCRIPTION = (
    "A file in which the container keeps the nodes it hosts (how each was loaded, parameters set since, "
    "lifecycle state), so that a respawned container restores them; empty: none. A clean shutdown removes it."
)

#: Where rcl_lifecycle publishes a node's transitions, relative to the node.
_TRANSITION_EVENT = "~/transition_event"

#: How often a write that keeps failing is logged.
_WRITE_ERROR_PERIOD_S = 30.0

#: Where a keeper stands (see :class:`StateKeeper`).
Mode = Literal["created", "held", "recording", "stopped", "closed", "off"]


def restore_request(record: NodeRecord) -> LoadRequest:
    """The load that brings ``record``'s node back as it was loaded (its parameters as resolved then)."""
    return LoadRequest(
        package=record.package,
        plugin=record.plugin,
        name=record.name,
        namespace=record.namespace,
        remap_rules=record.remap_rules,
        parameters=record.parameters,
        extra_arguments={parameter.name: parameter.value for parameter in record.extra_arguments},
        log_level=record.log_level,
    )


def restore_of(record: NodeRecord) -> Restore:
    """What ``record``'s node keeps of its previous life: its unique id, its parameters set since."""
    return Restore(record.unique_id, record.changed_parameters)


class StateKeeper:
    """The state file of one container: taken over at start, then kept in step with the container.

    It goes ``created`` -> ``held`` (:meth:`take_over`: locked and read; the
    start-up loads without writing, so that a crash mid-restore leaves the
    file whole) -> ``recording`` (:meth:`record`) -> ``stopped`` (:meth:`stop`:
    the shutdown's unloads are not recorded) -> ``closed``; ``off`` when the
    file cannot be had (locked by another process, or a bad file that could
    not be moved aside): nothing is read or written then.

    :param manager: the container; the keeper declares ``state_file`` on it
        and watches its loads (:attr:`ComponentManager.watcher`).
    :param path: the file (made absolute against the working directory).
    """

    def __init__(self, manager: ComponentManager, path: Path) -> None:
        self.manager = manager
        self.path = Path(os.path.abspath(path))
        self.mode: Mode = "created"
        self._log = manager.get_logger()
        self._lock: int | None = None
        self._group = MutuallyExclusiveCallbackGroup()
        self._transitions: dict[int, Subscription[Any]] = {}
        self._parameter_events: Subscription[Any] | None = None
        #: Per unique id: parameters set since the load, by name.
        self._changed: dict[int, dict[str, Parameter[Any]]] = {}
        #: Per unique id: the last primary state seen (a snapshot taken mid-transition uses it).
        self._primary: dict[int, str] = {}
        self._dirty = False
        self._writer: asyncio.Future[None] | None = None
        self._write_errors = Throttle(self._log.error, period=_WRITE_ERROR_PERIOD_S)
        #: Writes done, for tests and logs.
        self.writes = 0

    @classmethod
    def from_parameter(cls, manager: ComponentManager) -> StateKeeper | None:
        """Declare ``state_file`` on the container node; a keeper if it names a file.

        ``~`` is expanded; a relative path is taken from the working directory.
        """
        value: object = manager.declare_parameter(
            STATE_FILE_PARAMETER, "", ParameterDescriptor(description=_DESCRIPTION, read_only=True)
        ).value
        if not value:
            return None
        return cls(manager, Path(os.path.expanduser(str(value))))

    # -- start -----------------------------------------------------------------------------
    def take_over(self) -> ContainerState | None:
        """Lock the file for this process and read it: the state to restore, or ``None``.

        Every outcome is logged: nothing to restore yet, a file set aside and
        why, a file another container process holds. From here on the
        keeper watches the container's loads, and writes nothing until
        :meth:`record`.
        """
        self._expect("created")
        if self.path.is_dir():
            # Never moved aside: it is a directory of the user's, not a state file.
            self._log.error(
                f"state file '{self.path}' is a directory: name a file in it; "
                "this container neither restores nor records its nodes"
            )
            self.mode = "off"
            return None
        try:
            self._lock = _lock(self.path)
        except StateFileError as exc:
            self._log.error(f"{exc}; this container neither restores nor records its nodes")
            self.mode = "off"
            return None
        for leftover in temporary_files(self.path):
            # A write cut short by the end of a previous process: never renamed, never read.
            with contextlib.suppress(OSError):
                leftover.unlink()
        try:
            state = read_state(self.path)
            if state is not None and state.container != self.manager.get_fully_qualified_name():
                raise StateFileError(
                    f"it holds the nodes of container {clip(state.container, quote=True)}, "
                    f"not of '{self.manager.get_fully_qualified_name()}'",
                    path=str(self.path),
                )
        except StateFileError as exc:
            state = None
            try:
                kept = set_aside(self.path)
            except OSError as error:
                self._log.error(
                    f"{exc}; it could not be moved aside ({error.strerror or error}): it is left as it is, and "
                    "this container neither restores nor records its nodes"
                )
                self._release()
                self.mode = "off"
                return None
            self._log.error(f"{exc}; moved aside to '{kept}', and the container starts without its nodes")
        if state is None:
            self._log.info(f"State file '{self.path}': nothing to restore; the nodes loaded from now on are recorded")
        self.mode = "held"
        self.manager.watcher = self
        # rclpy's annotation knows no async callbacks; AsyncioExecutor runs
        # them on the loop, where the container's bookkeeping lives.
        self._parameter_events = self.manager.create_subscription(
            ParameterEvent,
            "/parameter_events",
            self._on_parameter_event,  # type: ignore[arg-type]
            qos_profile_parameter_events,
            callback_group=self._group,
        )
        if state is not None:
            self.manager.reserve_unique_ids(state.next_unique_id)
        return state

    def carry_over(self, loaded: LoadedNode, record: NodeRecord) -> None:
        """Take ``record``'s parameters set since its load as ``loaded``'s (the node restored from it)."""
        self._changed[loaded.unique_id] = {p.name: p for p in record.changed_parameters}

    def record(self) -> None:
        """Start writing: now, and on every change from here on."""
        if self.mode == "off":
            return
        self._expect("held")
        self.mode = "recording"
        self._schedule()

    # -- what changes ----------------------------------------------------------------------
    def loaded(self, loaded: LoadedNode) -> None:
        """Watch a node just loaded: its transitions; then record it."""
        if is_lifecycle(loaded.node):
            self._primary[loaded.unique_id] = "unconfigured"
            topic = loaded.node.resolve_topic_name(_TRANSITION_EVENT)
            self._transitions[loaded.unique_id] = self.manager.create_subscription(
                TransitionEvent,
                topic,
                self._on_transition,  # type: ignore[arg-type]
                QoSProfile(depth=10),  # rcl_lifecycle's publisher: reliable, keep last 10
                callback_group=self._group,
            )
        self._schedule()

    def unloaded(self, loaded: LoadedNode) -> None:
        """Stop watching a node taken off the container; record that it is gone."""
        subscription = self._transitions.pop(loaded.unique_id, None)
        if subscription is not None:
            self.manager.destroy_subscription(subscription)
        self._changed.pop(loaded.unique_id, None)
        self._primary.pop(loaded.unique_id, None)
        self._schedule()

    async def _on_transition(self, event: TransitionEvent) -> None:
        # Which node does not matter: the snapshot reads every node's state.
        self._schedule()

    async def _on_parameter_event(self, event: ParameterEvent) -> None:
        """Note which parameters of a hosted node were set (or undeclared) since its load.

        The values are read from the node itself, not from the event: any
        participant may publish on ``/parameter_events``, and a forged event
        can at most make the file pin a value the node really has.
        """
        if not (event.changed_parameters or event.deleted_parameters):
            return  # declarations (new_parameters) are the node's own business
        for loaded in self.manager.loaded():
            if loaded.full_name == event.node:
                node = loaded.node
                changed = self._changed.setdefault(loaded.unique_id, {})
                for name in dict.fromkeys(message.name for message in event.changed_parameters):
                    if node.has_parameter(name):
                        changed[name] = node.get_parameter(name)
                for message in event.deleted_parameters:
                    if not node.has_parameter(message.name):
                        changed.pop(message.name, None)
                self._schedule()
                return

    # -- writing ---------------------------------------------------------------------------
    def _schedule(self) -> None:
        """Note a change (on the loop's thread); write it unless a write runs, which then writes again."""
        self._dirty = True
        if self.mode == "recording" and (self._writer is None or self._writer.done()):
            self._writer = asyncio.ensure_future(self._write())

    async def _write(self) -> None:
        while self._dirty and self.mode == "recording":
            self._dirty = False
            # The snapshot on the loop, where the container's bookkeeping lives;
            # its encoding and the disk on a thread.
            state = self.snapshot()
            try:
                await in_thread(functools.partial(_encode_and_write, self.path, state), name="state-file")
            except OSError as exc:
                self._write_errors(
                    "write",
                    f"Cannot write the state file '{self.path}': {exc.strerror or exc}; "
                    "a respawned container would restore what it last held",
                )
            else:
                self.writes += 1

    async def flush(self) -> None:
        """Wait until every change so far is written (or failed to be)."""
        while self._writer is not None and not self._writer.done():
            await asyncio.shield(self._writer)

    def snapshot(self) -> ContainerState:
        """What the container hosts now, as the file records it."""
        nodes = []
        for loaded in self.manager.loaded():
            changed = self._changed.get(loaded.unique_id, {})
            request = loaded.request
            nodes.append(
                NodeRecord(
                    unique_id=loaded.unique_id,
                    package=loaded.node_type.package,
                    plugin=loaded.node_type.full_name,
                    name=request.name,
                    namespace=request.namespace,
                    full_name=loaded.full_name,
                    remap_rules=tuple(request.remap_rules),
                    parameters=loaded.parameters,
                    changed_parameters=tuple(changed.values()),
                    extra_arguments=tuple(
                        Parameter(name, value=value) for name, value in request.extra_arguments.items()
                    ),
                    log_level=request.log_level,
                    state=self._state_of(loaded),
                )
            )
        return ContainerState(self.manager.get_fully_qualified_name(), self.manager.next_unique_id, tuple(nodes))

    def _state_of(self, loaded: LoadedNode) -> str | None:
        if not is_lifecycle(loaded.node):
            return None
        state = state_of(loaded.node)
        if state in LIFECYCLE_STATES:
            self._primary[loaded.unique_id] = state
            return state
        # Mid-transition: where it stood before; its transition_event brings the next write.
        return self._primary.get(loaded.unique_id, "unconfigured")

    # -- end -------------------------------------------------------------------------------
    def stop(self) -> None:
        """Write no more: the shutdown's unloads leave the file as it was, should the process die meanwhile."""
        if self.mode in ("held", "recording"):
            self.mode = "stopped"

    async def clear(self) -> None:
        """After a clean shutdown (every node taken down): remove the file, so the next start is a fresh one."""
        if self.mode != "stopped":
            return
        await self.flush()
        try:
            self.path.unlink(missing_ok=True)
        except OSError as exc:
            self._log.error(f"Cannot remove the state file '{self.path}': {exc.strerror or exc}")
            return
        self._log.info(f"State file '{self.path}' removed: a clean shutdown, so the next start is a fresh one")

    def close(self) -> None:
        """Stop watching and release the file's lock (idempotent); the file stays as it is."""
        if self.manager.watcher is self:
            self.manager.watcher = None
        for subscription in self._transitions.values():
            self.manager.destroy_subscription(subscription)
        self._transitions.clear()
        if self._parameter_events is not None:
            self.manager.destroy_subscription(self._parameter_events)
            self._parameter_events = None
        if self._writer is not None:
            self._writer.cancel()
        self._release()
        self.mode = "closed"

    def _release(self) -> None:
        if self._lock is not None:
            os.close(self._lock)  # the lock goes with the descriptor
            self._lock = None

    def _expect(self, mode: Mode) -> None:
        if self.mode != mode:
            raise StateFileError(f"the keeper is {self.mode}, not {mode}", path=str(self.path))


def _encode_and_write(path: Path, state: ContainerState) -> None:
    write_atomically(path, encode(state))


def _lock(path: Path) -> int:
    """Lock ``PATH.lock`` for this process (the kernel releases it when the process ends, however it ends).

    :return: the lock file's descriptor, to hold while the container runs.
    :raises StateFileError: the directory cannot be made, or another process holds the lock.
    """
    lock_path = path.with_name(f"{path.name}.lock")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        descriptor = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        raise StateFileError(f"cannot be used: {exc.strerror or exc}", path=str(path)) from exc
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(descriptor)
        raise StateFileError(
            f"is in use by another container process (it holds '{lock_path}')", path=str(path)
        ) from exc
    return descriptor
