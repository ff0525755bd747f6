"""A lifecycle manager, wire-compatible with Nav2's, that also undoes what it did.

Nav2's ``lifecycle_manager`` walks ``node_names`` forward to configure and
activate and in reverse for the rest, counts a transition only when
``change_state`` succeeds *and* ``get_state`` confirms, and resets every node
when one's bond breaks. It stops at the first failure of a bring-up and leaves
the nodes it already brought up running (navigation2#4678, #855). This one:

* rolls a failed bring-up back (reverse order) and says which node failed at
  which transition and why: in the log and in ``is_active``'s message;
* retries a failed transition with exponential backoff when asked
  (``transition_retries``, ``retry_delay``, ``retry_backoff``);
* carries on past failures when taking nodes down: the goal is a safe state;
* watches heartbeats (:mod:`container.lifecycle._heartbeat`) instead of bondcpp
  handshakes, and re-runs start-up when a lost node comes back within
  ``bond_respawn_max_duration``.

It runs inside a container (``manager:`` in the container file) or as its own
process (``container manager``); both are set up in :mod:`container._app`.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, cast

from lifecycle_msgs.msg import Transition
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from .. import checks
from .._errors import ConfigError, TransitionError
from .._text import clip
from ._client import LifecycleClient, transition_id
from ._heartbeat import MIN_HEARTBEAT_PERIOD, HeartbeatWatch

__all__ = ["LifecycleManager", "ManagerSettings"]

#: Nav2's parameters with Nav2's defaults, then ours.
PARAMETERS: dict[str, Any] = {
    "node_names": [""],
    "autostart": False,
    "bond_timeout": 4.0,
    "bond_heartbeat_period": 0.25,
    "attempt_respawn_reconnection": True,
    "bond_respawn_max_duration": 10.0,
    "service_timeout": 5.0,
    # Beyond Nav2.
    "transition_timeout": 15.0,
    "transition_retries": 0,
    "retry_delay": 0.5,
    "retry_backoff": 2.0,
    "rollback_on_failure": True,
}


@dataclass(frozen=True, slots=True)
class _Step:
    """One transition as the manager applies it to every node."""

    label: str
    #: States the transition starts from.
    start: frozenset[str]
    goal: str
    #: States in which the node needs no such step.
    done: frozenset[str]
    #: The step that undoes this one, for a rollback.
    undo: str | None = None


_STEPS = {
    "configure": _Step(
        "configure", frozenset({"unconfigured"}), "inactive", frozenset({"inactive", "active"}), "cleanup"
    ),
    "activate": _Step("activate", frozenset({"inactive"}), "active", frozenset({"active"}), "deactivate"),
    "deactivate": _Step(
        "deactivate", frozenset({"active"}), "inactive", frozenset({"inactive", "unconfigured", "finalized"})
    ),
    "cleanup": _Step("cleanup", frozenset({"inactive"}), "unconfigured", frozenset({"unconfigured", "finalized"})),
    "shutdown": _Step(
        "shutdown", frozenset({"unconfigured", "inactive", "active"}), "finalized", frozenset({"finalized"})
    ),
}

#: ManageLifecycleNodes commands: name, steps, and whether it brings nodes up
#: (walks forward, rolls back on failure) or down (walks in reverse).
_COMMANDS: dict[int, tuple[str, tuple[str, ...], bool]] = {
    0: ("STARTUP", ("configure", "activate"), True),
    1: ("PAUSE", ("deactivate",), False),
    2: ("RESUME", ("activate",), True),
    3: ("RESET", ("deactivate", "cleanup"), False),
    4: ("SHUTDOWN", ("deactivate", "cleanup", "shutdown"), False),
    5: ("CONFIGURE", ("configure",), True),
    6: ("CLEANUP", ("cleanup",), False),
}
STARTUP, PAUSE, RESUME, RESET, SHUTDOWN, CONFIGURE, CLEANUP = range(7)


@dataclass(frozen=True, slots=True)
class ManagerSettings:
    """The manager node's name and parameters, from a ``manager:`` mapping."""

    name: str = "lifecycle_manager"
    namespace: str = "/"
    parameters: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any], *, source: str = "manager") -> ManagerSettings:
        """Check a ``manager:`` mapping: ``name``, ``namespace`` and the parameters.

        :raises ConfigError: an unknown key or a value of the wrong type.
        """
        values = dict(mapping)
        name = values.pop("name", "lifecycle_manager")
        namespace = values.pop("namespace", "/")
        for key, value in (("name", name), ("namespace", namespace)):
            if not isinstance(value, str) or not value:
                raise ConfigError(f"expected a non-empty string, not {value!r}", source=f"{source}.{key}")
        parameters: dict[str, Any] = {}
        for key, value in values.items():
            if key not in PARAMETERS:
                known = ", ".join(sorted({"name", "namespace", *PARAMETERS}))
                raise ConfigError(f"unknown key {key!r}; expected {known}", source=source)
            parameters[key] = _check_value(key, value, f"{source}.{key}")
        return cls(name=name, namespace=namespace, parameters=parameters)


def _check_value(key: str, value: Any, where: str) -> Any:
    default = PARAMETERS[key]
    if isinstance(default, bool):
        return checks.boolean(value, where=where)
    if isinstance(default, int):
        return checks.integer(value, where=where, minimum=0)
    if key == "bond_heartbeat_period":
        return checks.number(value, where=where, minimum=MIN_HEARTBEAT_PERIOD)
    if isinstance(default, float):
        return checks.number(value, where=where)
    names = checks.strings(value, where=where)
    if not names or not all(names):
        raise ConfigError("must be a non-empty list of node names", source=where)
    return list(names)


@dataclass
class _Outcome:
    """What one command did: which steps succeeded, and the first failure."""

    done: list[tuple[str, str]] = field(default_factory=list)
    failure: TransitionError | None = None
    errors: list[TransitionError] = field(default_factory=list)


class LifecycleManager(Node):
    """Bring ``node_names`` up and down in order; keep them safe when one is lost.

    Services: ``~/manage_nodes`` (ManageLifecycleNodes) and ``~/is_active``
    (Trigger; the message says why the system is not active).
    """

    def __init__(
        self,
        settings: ManagerSettings | None = None,
        *,
        context: Context | None = None,
        namespace: str | None = None,
        use_global_arguments: bool = False,
    ) -> None:
        from nav2_msgs.srv import ManageLifecycleNodes

        settings = settings or ManagerSettings()
        super().__init__(
            settings.name,
            namespace=namespace or settings.namespace,
            context=context,
            parameter_overrides=[Parameter(k, value=v) for k, v in settings.parameters.items()],
            # A manager process of its own takes the command line's ROS
            # arguments (name, namespace, --params-file); one inside a
            # container leaves them to the container node.
            use_global_arguments=use_global_arguments,
        )
        for key, default in PARAMETERS.items():
            self.declare_parameter(key, default)
        self.node_names = [self._full_name(n) for n in self._param("node_names") if n]
        self.autostart = bool(self._param("autostart"))
        self.bond_timeout = float(self._param("bond_timeout"))
        self.heartbeat_period = float(self._param("bond_heartbeat_period"))
        self.respawn = bool(self._param("attempt_respawn_reconnection"))
        self.respawn_max_duration = float(self._param("bond_respawn_max_duration"))
        self.service_timeout = float(self._param("service_timeout"))
        self.transition_timeout = float(self._param("transition_timeout"))
        self.retries = int(self._param("transition_retries"))
        self.retry_delay = float(self._param("retry_delay"))
        self.retry_backoff = float(self._param("retry_backoff"))
        self.rollback = bool(self._param("rollback_on_failure"))

        self.system_active = False
        #: Why the system is not active, for ``is_active`` and the log.
        self.status = "not started"
        self._busy = asyncio.Lock()
        #: Bumped by every command, so a pending respawn knows it was overtaken.
        self._generation = 0
        self._tasks: set[asyncio.Task[Any]] = set()
        #: The instance of each node whose heartbeats count (seen at activation).
        self._instances: dict[str, str] = {}
        #: Nodes lost and not back within the respawn window.
        self._stragglers: set[str] = set()

        calls = ReentrantCallbackGroup()
        self._lifecycle = {
            name: LifecycleClient(self, name, callback_group=calls, service_timeout=self.service_timeout)
            for name in self.node_names
        }
        self._watch = (
            HeartbeatWatch(self, callback_group=MutuallyExclusiveCallbackGroup())
            if self.bond_timeout > 0
            else None
        )
        commands = MutuallyExclusiveCallbackGroup()
        self.create_service(ManageLifecycleNodes, "~/manage_nodes", self._serve_manage, callback_group=commands)
        self.create_service(Trigger, "~/is_active", self._serve_is_active, callback_group=ReentrantCallbackGroup())
        if self._watch is not None:
            # rclpy 9 annotates timer callbacks as plain; its executors and ours run an async one.
            check = cast("Callable[[], None]", self._check_heartbeats)
            self.create_timer(self.heartbeat_period, check, callback_group=MutuallyExclusiveCallbackGroup())

    def _param(self, name: str) -> Any:
        return self.get_parameter(name).value

    def _full_name(self, name: str) -> str:
        if name.startswith("/"):
            return name
        return f"{self.get_namespace().rstrip('/')}/{name}"

    # -- services -----------------------------------------------------------------
    async def _serve_manage(self, request: Any, response: Any) -> Any:
        response.success = await self.command(int(request.command))
        return response

    async def _serve_is_active(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success = self.system_active
        response.message = "active" if self.system_active else self.status
        return response

    # -- commands -----------------------------------------------------------------
    async def command(self, command: int) -> bool:
        """Carry out a ManageLifecycleNodes command; ``True`` if every step succeeded."""
        if command not in _COMMANDS:
            self.get_logger().error(f"Unknown manage_nodes command {command}")
            return False
        self._generation += 1
        async with self._busy:
            return await self._command(command)

    async def _command(self, command: int) -> bool:
        name, labels, brings_up = _COMMANDS[command]
        self.system_active = False
        self.get_logger().info(f"{name}: {', '.join(labels)} {', '.join(self.node_names)}")
        if brings_up:
            outcome = await self._bring_up(labels)
            if outcome.failure is not None:
                self.status = f"{name} failed: {outcome.failure}"
                undone = await self._roll_back(outcome) if self.rollback else []
                rolled = f"; rolled back {', '.join(undone)}" if undone else ""
                self.status += rolled
                self.get_logger().error(self.status)
                return False
            self.system_active = command in (STARTUP, RESUME)
            self.status = "active" if self.system_active else f"{name} done"
        else:
            outcome = await self._take_down(labels, self.node_names)
            if outcome.errors:
                self.status = f"{name} incomplete: " + "; ".join(str(e) for e in outcome.errors)
                self.get_logger().error(self.status)
                return False
            self.status = f"{name} done"
        self.get_logger().info(f"{name} done" if not self.system_active else "Managed nodes are active")
        return True

    async def _bring_up(self, labels: Iterable[str]) -> _Outcome:
        outcome = _Outcome()
        since = time.monotonic() - self.bond_timeout
        for label in labels:
            for node in self.node_names:
                try:
                    if await self._step(node, label):
                        outcome.done.append((node, label))
                    if label == "activate":
                        await self._expect_heartbeat(node, since=since)
                except TransitionError as exc:
                    outcome.failure = exc
                    return outcome
        return outcome

    async def _roll_back(self, outcome: _Outcome) -> list[str]:
        """Undo a failed bring-up's steps, the last one first; return the nodes touched.

        A node that failed to activate was configured by this bring-up, so
        its configure is undone with the rest.
        """
        undo: list[tuple[str, str]] = []
        for node, label in reversed(outcome.done):
            step = _STEPS[label].undo
            if step is not None:
                undo.append((node, step))
        touched: list[str] = []
        for node, label in undo:
            try:
                await self._step(node, label, retry=False)
            except TransitionError as exc:
                self.get_logger().error(f"Rollback: {exc}")
            if node not in touched:
                touched.append(node)
        return touched

    async def _take_down(self, labels: Iterable[str], nodes: list[str]) -> _Outcome:
        outcome = _Outcome()
        for label in labels:
            for node in reversed(nodes):
                try:
                    if await self._step(node, label, retry=False):
                        outcome.done.append((node, label))
                except TransitionError as exc:
                    self.get_logger().error(str(exc))
                    outcome.errors.append(exc)
        return outcome

    async def _expect_heartbeat(self, node: str, *, since: float) -> None:
        if self._watch is None:
            return
        beat = await self._watch.wait(node, after=since, timeout=self.bond_timeout)
        if beat is None:
            raise TransitionError(
                f"no heartbeat on /bond within {self.bond_timeout:g} s (heartbeats off on the "
                "node? set the manager's bond_timeout to 0 to manage nodes without them)",
                node=node,
                transition="activate",
            )
        # From now on only this instance's heartbeats count for the node: a
        # peer (or a stale process) beating under its name hides nothing.
        self._instances[node] = beat.instance_id

    # -- one node, one step ---------------------------------------------------------
    async def _step(self, node: str, label: str, *, retry: bool = True) -> bool:
        """Move ``node`` through ``label`` unless it is already past it.

        :return: ``True`` if a transition was made, ``False`` if none was needed.
        :raises TransitionError: with the reason; after retries, if configured.
        """
        step = _STEPS[label]
        client = self._lifecycle[node]
        attempts = 1 + (self.retries if retry else 0)
        delay = self.retry_delay
        for attempt in range(1, attempts + 1):
            try:
                _, state = await client.get_state()
                if state in step.done:
                    return False
                if state not in step.start:
                    raise TransitionError(
                        f"not possible from state {clip(state, quote=True)}", node=node, transition=label
                    )
                await self._transition(client, step, state)
                self.get_logger().info(f"{node}: {label} -> {step.goal}")
                return True
            except TransitionError as exc:
                if attempt == attempts:
                    raise
                self.get_logger().warning(
                    f"{exc}; attempt {attempt} of {attempts}, retrying in {delay:g} s"
                )
                await asyncio.sleep(delay)
                delay *= self.retry_backoff
        raise AssertionError("unreachable")  # pragma: no cover

    async def _transition(self, client: LifecycleClient, step: _Step, state: str) -> None:
        request = Transition(id=transition_id(step.label, state), label=step.label)
        ok = await client.change_state(request, timeout=self.transition_timeout)
        _, now = await client.get_state()
        if not ok:
            raise TransitionError(
                f"change_state answered success=false; the node is {clip(now)}",
                node=client.target,
                transition=step.label,
            )
        if now != step.goal:
            raise TransitionError(
                f"change_state succeeded but get_state reports {clip(now, quote=True)}, not '{step.goal}'",
                node=client.target,
                transition=step.label,
            )

    # -- heartbeats -------------------------------------------------------------------
    async def _check_heartbeats(self) -> None:
        if self._watch is None or self._busy.locked():
            return
        self._catch_stragglers()
        if not self.system_active:
            return
        now = time.monotonic()
        lost = []
        for node in self.node_names:
            seen = self._watch.last(node, instance=self._instances.get(node))
            if seen is None or not seen.active or now - seen.received > self.bond_timeout:
                lost.append(node)
        if lost:
            self.system_active = False
            self._spawn(self._on_lost(lost, now))

    def _spawn(self, coro: Awaitable[None]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _on_lost(self, lost: list[str], since: float) -> None:
        assert self._watch is not None
        self._generation += 1
        generation = self._generation
        for node in lost:
            seen = self._watch.last(node)
            why = (
                "said goodbye"
                if seen is not None and not seen.active
                else f"no heartbeat for more than {self.bond_timeout:g} s"
            )
            self.get_logger().error(f"Heartbeat of {node} lost ({why}); bringing all managed nodes to a safe state")
        others = [n for n in self.node_names if n not in lost]
        self.status = f"heartbeat lost: {', '.join(lost)}"
        async with self._busy:
            outcome = await self._take_down(("deactivate", "cleanup"), others)
        if outcome.errors:
            self.status += "; reset incomplete: " + "; ".join(str(e) for e in outcome.errors)
        if not self.respawn:
            self.get_logger().error(self.status)
            return
        self.get_logger().info(
            f"Waiting up to {self.respawn_max_duration:g} s for {', '.join(lost)} to come back"
        )
        deadline = time.monotonic() + self.respawn_max_duration
        for node in lost:
            back = await self._watch.wait(node, after=since, timeout=max(0.0, deadline - time.monotonic()))
            if back is None:
                self.status += f"; {node} did not come back within {self.respawn_max_duration:g} s"
                self.get_logger().error(self.status)
                # Should it come back later, it is brought where its peers are.
                self._stragglers.update(lost)
                return
        if generation != self._generation:
            return  # a command came in meanwhile: it decides
        self.get_logger().info(f"{', '.join(lost)} back; starting up again")
        async with self._busy:
            await self._take_down(("deactivate", "cleanup"), self.node_names)
            await self._command(STARTUP)

    def _catch_stragglers(self) -> None:
        """A node back after the respawn window must not stay active alone."""
        assert self._watch is not None
        now = time.monotonic()
        for node in list(self._stragglers):
            seen = self._watch.last(node)
            if seen is None or not seen.active or now - seen.received > self.bond_timeout:
                continue
            self._stragglers.discard(node)
            self.get_logger().warning(
                f"{node} came back after the respawn window; bringing it to unconfigured like its peers"
            )
            self._spawn(self._reset_straggler(node))

    async def _reset_straggler(self, node: str) -> None:
        async with self._busy:
            outcome = await self._take_down(("deactivate", "cleanup"), [node])
        if outcome.errors:
            self.status += f"; {node} came back and could not be reset: " + "; ".join(map(str, outcome.errors))
            self.get_logger().error(self.status)

    # -- running ----------------------------------------------------------------------
    async def run(self) -> None:
        """Start up if ``autostart``, then serve until cancelled."""
        if self.autostart:
            await self.command(STARTUP)
        await asyncio.Event().wait()

    async def settle(self, *, timeout: float) -> None:
        """Reset the reachable nodes (reverse order) before the process goes away."""
        for task in list(self._tasks):
            task.cancel()
        reachable = [n for n in self.node_names if self._lifecycle[n].ready_now()]
        self.system_active = False
        with contextlib.suppress(asyncio.TimeoutError):
            async with self._busy:
                await asyncio.wait_for(self._take_down(("deactivate", "cleanup"), reachable), timeout)

    def destroy_node(self) -> None:
        for task in list(self._tasks):
            task.cancel()
        if self._watch is not None:
            self._watch.close()
        for client in self._lifecycle.values():
            client.close()
        super().destroy_node()  # type: ignore[no-untyped-call, unused-ignore]  # rclpy 7's is untyped
