"""The project's lifecycle node base: rclpy's LifecycleNode, made easy to get right.

rclpy's :class:`rclpy.lifecycle.LifecycleNode` runs transition callbacks
synchronously inside its ``change_state`` service, raises on a transition
that is not available from the current state (rclpy#1209), and enables
lifecycle publishers only if ``on_activate()`` remembers to call ``super()``.
This base keeps rclpy's rcl state machine and ``transition_event``, serves
the standard services itself, keep-all (:mod:`container.lifecycle._services`:
rcl's keep only 10 requests), and replaces how a transition is *driven*:

* transition callbacks may be ``async def``; while one awaits, the event loop
  and every other node keep running. Plain callbacks run on a short-lived
  thread, so a blocking one delays only its own node;
* each callback is bounded by ``transition_timeout``: past it, the transition
  fails back to its start state (the rcl ``failure`` path);
* an unavailable transition answers ``success=false`` and is logged;
* publishers and timers created through the node follow its state: publishing
  is a no-op and timers are paused unless the node is active;
* the node publishes heartbeats (:mod:`container.lifecycle._heartbeat`) for a lifecycle
  manager, in every state, every ``bond_heartbeat_period`` seconds.

Transitions of one node never overlap, whoever asks for them (``change_state``,
the container, :meth:`LifecycleNode.transition`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import inspect
import threading
import traceback
from collections.abc import AsyncIterator, Callable
from typing import Any, cast

import lifecycle_msgs.msg
import lifecycle_msgs.srv
from lifecycle_msgs.msg import State
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.callback_groups import CallbackGroup
from rclpy.clock import Clock
from rclpy.lifecycle import LifecyclePublisher, LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile
from rclpy.timer import Timer

from .. import checks
from .._compat import managed_entities, state_machine
from .._errors import TransitionError
from .._logger import FastLogging
from .._text import MESSAGE_LIMIT, clip
from ..executor import Escaped, contained, in_thread, run_coroutine, working_for
from ..intra import IntraProcessNode
from ._base import LifecycleNodeBase
from ._heartbeat import DEFAULT_HEARTBEAT_PERIOD, MIN_HEARTBEAT_PERIOD, HeartbeatPublisher, status_type
from ._services import LifecycleServices

__all__ = ["LifecycleNode"]

#: Which callback runs in which transition state.
_CALLBACKS = {
    State.TRANSITION_STATE_CONFIGURING: "on_configure",
    State.TRANSITION_STATE_CLEANINGUP: "on_cleanup",
    State.TRANSITION_STATE_SHUTTINGDOWN: "on_shutdown",
    State.TRANSITION_STATE_ACTIVATING: "on_activate",
    State.TRANSITION_STATE_DEACTIVATING: "on_deactivate",
    State.TRANSITION_STATE_ERRORPROCESSING: "on_error",
}

SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE
ERROR = TransitionCallbackReturn.ERROR

#: How long past ``transition_timeout`` a ``change_state`` caller waits for
#: the node's own timeout to answer, before the answer is a timeout.
_ANSWER_MARGIN_S = 1.0

#: How long a cancelled transition may take to fail back to its start state.
_FAIL_BACK_S = 1.0

#: States in which managed publishers publish.
_PUBLISHING = {"activating", "active"}


class LifecycleNode(FastLogging, IntraProcessNode, LifecycleNodeBase):
    """A lifecycle node whose transition callbacks may be coroutines.

    Override ``on_configure``, ``on_activate``, ... as in rclpy, with
    ``def`` or ``async def``; return a :class:`TransitionCallbackReturn`.
    An exception counts as ``ERROR`` (logged with its traceback; ``on_error``
    runs). Calling ``super()`` is not needed for publishers and timers to
    follow the node's state.

    Parameters declared on every node: ``transition_timeout`` (seconds one
    transition callback may take; ``<= 0`` waits forever) and
    ``bond_heartbeat_period`` (seconds between heartbeats; ``<= 0`` turns
    heartbeats off).

    Transitions need the node to run on an :class:`~container.AsyncioExecutor`
    (or any running asyncio loop) unless every callback is synchronous.

    :param transition_timeout: default of the ``transition_timeout`` parameter.
    :param heartbeat_period: default of the ``bond_heartbeat_period`` parameter.
    :param use_intra_process_comms: exchange messages in process with the
        other such nodes of the context (:mod:`container.intra`); every
        publisher and subscription of the node takes part.

    ``reload_state`` is a dict handed from the node to the one that replaces
    it when its plugin is reloaded (``container reload``): whatever it holds
    once this node is down, the new node finds in its own ``reload_state``
    from its constructor on. It starts empty on a first load.

    rclpy's ``enable_communication_interface`` keyword is taken as in rclpy:
    ``False`` serves none of the standard lifecycle services (the node
    still publishes ``transition_event``); otherwise the node serves them
    itself (:class:`~container.lifecycle._services.LifecycleServices`).
    """

    reload_state: dict[str, Any]

    def __init__(
        self,
        node_name: str,
        *,
        transition_timeout: float = 10.0,
        heartbeat_period: float = DEFAULT_HEARTBEAT_PERIOD,
        use_intra_process_comms: bool = False,
        **kwargs: Any,
    ) -> None:
        # Set before the constructor when the node replaces one a reload took down.
        if not isinstance(getattr(self, "reload_state", None), dict):
            self.reload_state = {}
        # Node.__init__ creates /parameter_events through create_publisher;
        # that one, and anything rclpy creates for itself, stays always-on.
        self._entities_follow_state = False
        # What it was given to read, checked once its first configure has
        # declared everything (checks.unread_parameters).
        self._unread_check: tuple[str, ...] | None = tuple(
            getattr(p, "name", "") for p in kwargs.get("parameter_overrides") or ()
        )
        # What it was warned of about them, for whoever loaded it.
        self._parameter_warnings: list[str] = []
        # rcl's own lifecycle services keep 10 requests and cannot be told
        # otherwise; the node serves its own (_services), while rcl keeps
        # publishing transition_event.
        serve_services = bool(kwargs.pop("enable_communication_interface", True))
        super().__init__(
            node_name,
            use_intra_process_comms=use_intra_process_comms,
            enable_communication_interface=False,
            **kwargs,
        )
        self._managed_timers: set[Timer] = set()
        self._paused_timers: set[Timer] = set()
        self._transition_lock = asyncio.Lock()
        self._transition_task: asyncio.Task[Any] | None = None
        self._failure: str | None = None
        self._declare_seconds(
            "transition_timeout",
            transition_timeout,
            "Seconds a transition callback may take before the transition fails "
            "back to its start state; <= 0 waits forever.",
        )
        period = self._declare_seconds(
            "bond_heartbeat_period",
            heartbeat_period,
            "Seconds between heartbeats on /bond for a lifecycle manager; <= 0 disables them.",
        )
        if 0 < period < MIN_HEARTBEAT_PERIOD:
            # 1e-9 would publish as fast as the loop can: a core spent on heartbeats.
            raise TransitionError(
                f"parameter 'bond_heartbeat_period' must be 0 (off) or at least "
                f"{MIN_HEARTBEAT_PERIOD:g} s, not {period:g}",
                node=self.get_fully_qualified_name(),
                transition="create",
            )
        self._lifecycle_services: LifecycleServices | None = None
        if serve_services:
            self._lifecycle_services = LifecycleServices(
                self, read=self._machine, change_state=self._serve_change_state
            )
        self._heartbeat: HeartbeatPublisher | None = None
        if period > 0:
            if status_type() is None:
                self.get_logger().warning(
                    "Heartbeats disabled: the 'bond' interface package is not installed"
                )
            else:
                self._heartbeat = HeartbeatPublisher(self, period=period)
        self._entities_follow_state = True

    def _declare_seconds(self, name: str, default: float, description: str) -> float:
        # dynamic_typing: a YAML ``5`` (an integer) must be accepted for seconds.
        descriptor = ParameterDescriptor(description=description, dynamic_typing=True)
        value: Any = self.declare_parameter(name, float(default), descriptor).value
        try:
            return float(value)
        except (TypeError, ValueError):
            raise TransitionError(
                f"parameter {name!r} must be a number of seconds, not {value!r}",
                node=self.get_fully_qualified_name(),
                transition="create",
            ) from None

    # -- state ---------------------------------------------------------------
    @property
    def lifecycle_state(self) -> LifecycleState:
        """The node's current state (primary or transition)."""
        state_id, label = self._machine("current_state")
        return LifecycleState(label=label, state_id=state_id)

    @property
    def last_failure(self) -> str | None:
        """Why the latest transition failed, when it did and the reason is known.

        A callback that timed out or raised, or one that returned
        :meth:`fail_transition`'s answer. The container puts it in its
        answers (a load with autostart), which carry nothing but text.
        """
        return self._failure

    def fail_transition(self, reason: str) -> TransitionCallbackReturn:
        """Log ``reason`` and fail the transition with it: ``return self.fail_transition("port busy")``.

        A reason over 800 characters is clipped (:func:`~container.clip`), in
        the log and in the answer: it may echo a peer's value.
        """
        reason = clip(reason, limit=MESSAGE_LIMIT)
        self.get_logger().error(reason)
        self._failure = reason
        return FAILURE

    @property
    def heartbeat(self) -> HeartbeatPublisher | None:
        """The node's heartbeat publisher, if heartbeats are on."""
        return self._heartbeat

    def _machine(self, name: str, *args: Any) -> Any:
        """Use rcl's state machine while holding it, so it cannot be freed meanwhile.

        Once it is destroyed (the node was unloaded under a callback that
        still runs) this raises ``InvalidHandle`` instead of touching freed
        memory.
        """
        machine = state_machine(self)
        with machine:
            attribute = getattr(machine, name)
            return attribute(*args) if callable(attribute) else attribute

    # -- transitions -----------------------------------------------------------
    async def end_transition(self, *, timeout: float) -> str | None:
        """Wait for a transition in progress to end; past ``timeout``, cancel it.

        Called before the node is taken down and destroyed (unload, container
        shutdown): a transition callback still running then would find its
        state machine gone. A cancelled transition fails back to its start
        state, and a ``change_state`` caller waiting for it gets ``success=false``.

        :return: ``None`` when no transition was running or it ended in
            time; else what was cancelled, for a log line.
        """
        if not self._transition_lock.locked() or await self._transitions_idle(timeout):
            return None
        state = self.lifecycle_state.label
        task = self._transition_task
        if task is not None and task is not asyncio.current_task():
            task.cancel()
        await self._transitions_idle(_FAIL_BACK_S)
        return f"transition in progress ({state}) cancelled after {timeout:g} s"

    async def _transitions_idle(self, timeout: float) -> bool:
        """Wait until no transition runs; ``False`` if one still does after ``timeout``."""
        try:
            async with asyncio.timeout(timeout), self._transition_lock:
                return True
        except TimeoutError:
            return False

    @contextlib.asynccontextmanager
    async def _transitioning(self) -> AsyncIterator[None]:
        """Hold the transition lock, remembering which task does (see :meth:`end_transition`)."""
        async with self._transition_lock:
            self._transition_task = asyncio.current_task()
            try:
                yield
            finally:
                self._transition_task = None

    async def transition(self, label: str, *, timeout: float | None = None) -> bool:
        """Carry out one transition (``configure``, ``activate``, ``shutdown``, ...).

        :param timeout: seconds each callback may take; the
            ``transition_timeout`` parameter when ``None``.
        :return: ``True`` when the callback succeeded and the node reached the
            transition's goal; ``False`` on failure, error, timeout, or when
            the transition is not available from the current state.
        """
        return await self._request(label, timeout=timeout) is SUCCESS

    async def fail(self, error: BaseException | None = None) -> str:
        """Send an active node through error processing; return the state it ends in.

        The route is the one rcl offers out of ``active``: ``deactivate``
        (without running ``on_deactivate``: the node is faulty), then the
        error transition to ``errorprocessing``, where ``on_error`` decides
        between ``unconfigured`` and ``finalized``. Each step appears on
        ``transition_event``. A node that is not active is left alone.
        """
        async with self._transitioning():
            if self.lifecycle_state.label != "active":
                return self.lifecycle_state.label
            detail = f" after {type(error).__name__}: {error}" if error is not None else ""
            self.get_logger().error(f"Entering error processing{detail}")
            await self._carry_out(
                lifecycle_msgs.msg.Transition.TRANSITION_DEACTIVATE,
                timeout=self._timeout(None),
                inline=False,
                forced=ERROR,
            )
            final = self.lifecycle_state.label
            self.get_logger().info(f"Error processing done: the node is {final}")
            return final

    async def _request(
        self, request: str | int, *, timeout: float | None, abandoned: threading.Event | None = None
    ) -> TransitionCallbackReturn | None:
        async with self._transitioning():
            transition_id = self._resolve(request)
            if transition_id is None:
                self._refuse(request)
                return None
            return await self._carry_out(
                transition_id, timeout=self._timeout(timeout), inline=False, abandoned=abandoned
            )

    def _timeout(self, timeout: float | None) -> float | None:
        if timeout is None:
            value = self.get_parameter("transition_timeout").value
            timeout = float(value) if value is not None else 0.0
        return timeout if timeout > 0 else None

    def _resolve(self, request: str | int) -> int | None:
        """The id of the requested transition if available from the current state."""
        for transition_id, label, *_ in self._machine("available_transitions"):
            if request in (transition_id, label):
                return int(transition_id)
        return None

    def _refuse(self, request: str | int) -> None:
        available = ", ".join(
            f"{label} [{tid}]" for tid, label, *_ in self._machine("available_transitions")
        )
        self.get_logger().warning(
            f"Transition {clip(request, quote=True)} is not available from state "
            f"'{self.lifecycle_state.label}'; available: {available or 'none'}"
        )

    async def _carry_out(
        self,
        transition_id: int,
        *,
        timeout: float | None,
        inline: bool,
        forced: TransitionCallbackReturn | None = None,
        abandoned: threading.Event | None = None,
    ) -> TransitionCallbackReturn:
        """Drive one transition through rcl's state machine.

        :param abandoned: set when whoever asked was already answered
            ``success=false`` (the loop was stuck past the timeout): the
            transition then fails, whatever its callback returns late.
        """
        start = self.lifecycle_state
        self._failure = None
        self._machine("trigger_transition_by_id", transition_id, True)
        middle = self.lifecycle_state
        if start.label == "active":
            self._pause_timers()
        self._follow_state(middle)
        try:
            if forced is not None:
                outcome = forced
            else:
                outcome = await self._invoke(middle, start, timeout=timeout, inline=inline)
            if abandoned is not None and abandoned.is_set() and outcome == SUCCESS:
                self.get_logger().error(
                    f"{_CALLBACKS.get(middle.state_id, 'the callback')}() returned after its caller "
                    "was answered success=false; the transition fails"
                )
                outcome = FAILURE
            self._machine("trigger_transition_by_label", outcome.to_label(), True)
            if outcome == SUCCESS and middle.state_id == State.TRANSITION_STATE_CONFIGURING:
                self._warn_unread_parameters()
            if outcome == ERROR:
                recovery = await self._invoke(
                    self.lifecycle_state, start, timeout=timeout, inline=inline
                )
                self._machine("trigger_transition_by_label", recovery.to_label(), True)
        except asyncio.CancelledError:
            # Whoever waited gave up: never leave the node in a transition state.
            self._fail_back()
            raise
        finally:
            self._follow_state(self.lifecycle_state)
        return outcome

    @property
    def parameter_warnings(self) -> tuple[str, ...]:
        """The warnings about its parameter overrides logged so far (unread names, typos), in order.

        The container hands them to whoever loaded the node: the LoadNode
        answer, ``container run``'s summary at ready.
        """
        return tuple(self._parameter_warnings)

    def warn_likely_typos(self) -> list[str]:
        """Before the first configure: warn now of the overrides only a typo explains; return the warnings.

        The full check waits for configure (nodes often declare what
        configure reads), but an override next to a parameter the
        constructor declared (``rat`` for ``rate``) is a typo already, and
        whoever loads the node without autostart should hear of it in the
        answer. Configure's check does not repeat it.
        """
        warnings = checks.unread_parameters(self, self._unread_check or (), likely_typos=True)
        self._tell(warnings)
        return warnings

    def _warn_unread_parameters(self) -> None:
        """Once, after the first configure: overrides no declared parameter takes (a typo)."""
        names, self._unread_check = self._unread_check, None
        told = set(self._parameter_warnings)
        self._tell([warning for warning in checks.unread_parameters(self, names or ()) if warning not in told])

    def _tell(self, warnings: list[str]) -> None:
        for warning in warnings:
            self.get_logger().warning(warning)
        self._parameter_warnings.extend(warnings)

    def _fail_back(self) -> None:
        if self.lifecycle_state.state_id >= State.TRANSITION_STATE_CONFIGURING:
            self._machine("trigger_transition_by_label", FAILURE.to_label(), True)

    async def _invoke(
        self,
        state: LifecycleState,
        previous: LifecycleState,
        *,
        timeout: float | None,
        inline: bool,
    ) -> TransitionCallbackReturn:
        """Run the callback of transition state ``state``; translate what it did."""
        name = _CALLBACKS.get(state.state_id)
        if name is None:
            return SUCCESS
        callback: Callable[[LifecycleState], Any] = getattr(self, name)
        try:
            if inline:
                result = callback(previous)
                if inspect.isawaitable(result):
                    _discard(result)
                    raise TypeError(f"{name}() is asynchronous; await node.transition() instead")
            elif inspect.iscoroutinefunction(callback):
                # A task of its own, named for the loop watchdog's report.
                running = asyncio.ensure_future(contained(callback(previous)))
                running.set_name(f"{name}() of {self.get_fully_qualified_name()}")
                result = await asyncio.wait_for(running, timeout)
            else:
                result = await asyncio.wait_for(
                    in_thread(lambda: callback(previous), name=f"transition:{name}"), timeout
                )
        except TimeoutError:
            self._failure = f"{name}() did not finish within {timeout:g} s"
            self.get_logger().error(f"{self._failure}; the transition fails")
            return FAILURE
        except (KeyboardInterrupt, asyncio.CancelledError):
            raise
        except BaseException as exc:  # sys.exit() in a callback is an error, not an exit
            error = exc.error if isinstance(exc, Escaped) else exc
            # Clipped line by line: the error's text may echo a peer's value.
            details = "\n".join(
                clip(line, limit=MESSAGE_LIMIT) for line in "".join(traceback.format_exception(error)).splitlines()
            )
            self._failure = f"{name}() raised {type(error).__name__}: {clip(str(error), limit=MESSAGE_LIMIT)}"
            self.get_logger().error(f"{self._failure}\n{details}")
            return ERROR
        if not isinstance(result, TransitionCallbackReturn):
            self.get_logger().error(
                f"{name}() returned {result!r}, not a TransitionCallbackReturn"
            )
            return ERROR
        return result

    # -- rclpy's synchronous entry points -------------------------------------------
    def trigger_configure(self) -> TransitionCallbackReturn:
        return self._trigger_now("configure")

    def trigger_cleanup(self) -> TransitionCallbackReturn:
        return self._trigger_now("cleanup")

    def trigger_activate(self) -> TransitionCallbackReturn:
        return self._trigger_now("activate")

    def trigger_deactivate(self) -> TransitionCallbackReturn:
        return self._trigger_now("deactivate")

    def trigger_shutdown(self) -> TransitionCallbackReturn:
        return self._trigger_now("shutdown")

    def _trigger_now(self, request: str | int) -> TransitionCallbackReturn:
        """Run a transition to completion in the caller's thread (sync callbacks only).

        :raises TransitionError: the transition is unavailable, another one is
            running, or a callback is asynchronous.
        """
        label = str(request)
        name = self.get_fully_qualified_name()
        if self._transition_lock.locked():
            raise TransitionError("another transition is running", node=name, transition=label)
        transition_id = self._resolve(request)
        if transition_id is None:
            raise TransitionError(
                f"not available from state '{self.lifecycle_state.label}'",
                node=name,
                transition=label,
            )
        goal = next(t[4] for t in self._machine("available_transitions") if t[0] == transition_id)
        for callback_name in (_CALLBACKS[goal], "on_error"):
            if inspect.iscoroutinefunction(getattr(self, callback_name)):
                raise TransitionError(
                    f"{callback_name}() is asynchronous; await node.transition({label!r})",
                    node=name,
                    transition=label,
                )
        # With synchronous callbacks run inline the coroutine never suspends.
        step = self._carry_out(transition_id, timeout=None, inline=True)
        try:
            step.send(None)
        except StopIteration as done:
            outcome: TransitionCallbackReturn = done.value
            return outcome
        step.close()
        raise TransitionError("a callback returned an awaitable", node=name, transition=label)

    # -- the change_state service ------------------------------------------------
    def _serve_change_state(
        self,
        request: lifecycle_msgs.srv.ChangeState.Request,
        response: lifecycle_msgs.srv.ChangeState.Response,
    ) -> lifecycle_msgs.srv.ChangeState.Response:
        """Carry out a requested transition; answer within ``transition_timeout`` whatever happens.

        A plain callback, so it runs on a lane thread and waits there for the
        transition, which runs on the event loop: if an ``async def``
        callback blocks the loop itself, this still answers ``success=false``
        once ``transition_timeout`` (plus a second) has passed.
        """
        # rclpy resolves a label first when one is given; so do we.
        wanted: str | int = request.transition.label or request.transition.id
        loop = getattr(self.executor, "loop", None)
        if not isinstance(loop, asyncio.AbstractEventLoop):
            # An rclpy executor: run synchronous callbacks inline, as rclpy does.
            try:
                response.success = self._trigger_now(wanted) is SUCCESS
            except TransitionError as exc:
                self.get_logger().error(str(exc))
                response.success = False
            return response
        limit = self._timeout(None)
        services = self._lifecycle_services
        service: object = services.change_state if services is not None else self._serve_change_state

        async def requested() -> TransitionCallbackReturn | None:
            task = asyncio.current_task()
            if task is not None:  # named for the loop watchdog's report
                task.set_name(f"transition {clip(wanted, quote=True)} of {self.get_fully_qualified_name()}")
            # Posted from the service's thread, so no callback of the node
            # created it: the watchdog is told whose work this is.
            with working_for(self, service):
                return await self._request(wanted, timeout=None, abandoned=abandoned)

        abandoned = threading.Event()
        pending = run_coroutine(requested(), loop)
        try:
            response.success = pending.result(None if limit is None else limit + _ANSWER_MARGIN_S) is SUCCESS
        except concurrent.futures.TimeoutError:
            self.get_logger().error(
                f"Transition {clip(wanted, quote=True)} did not end within {limit:g} s (transition_timeout): "
                "is the event loop stuck in a callback? Answered success=false"
            )
            # The answer was failure: so is the outcome, once the loop gets to it.
            abandoned.set()
            pending.cancel()
            response.success = False
        except concurrent.futures.CancelledError:
            # Cut short by end_transition (the node is going away).
            response.success = False
        return response

    # -- entities that follow the state ---------------------------------------------
    def create_publisher(
        self,
        msg_type: Any,
        topic: str,
        qos_profile: QoSProfile | int,
        *,
        managed: bool = True,
        **kwargs: Any,
    ) -> Publisher[Any]:
        """Create a publisher that publishes only while the node is active.

        :param managed: ``False`` for an ordinary, always-on publisher.
        """
        if managed and self._entities_follow_state and "publisher_class" not in kwargs:
            publisher: Publisher[Any] = self.create_lifecycle_publisher(
                msg_type, topic, qos_profile, **kwargs
            )
            return publisher
        return super().create_publisher(msg_type, topic, qos_profile, **kwargs)

    def create_lifecycle_publisher(self, *args: Any, **kwargs: Any) -> LifecyclePublisher[Any]:
        if "publisher_class" in kwargs:
            raise TypeError("create_lifecycle_publisher() got an unexpected keyword argument 'publisher_class'")
        # rclpy's own calls Node.create_publisher by name, past the intra-process hooks.
        created = super().create_publisher(*args, publisher_class=LifecyclePublisher, **kwargs)
        publisher = cast("LifecyclePublisher[Any]", created)
        self.add_managed_entity(publisher)
        state = self.lifecycle_state
        if state.label in _PUBLISHING:
            publisher.on_activate(state)
        return publisher

    def destroy_lifecycle_publisher(self, publisher: LifecyclePublisher[Any]) -> bool:
        return self.destroy_publisher(publisher)

    def destroy_publisher(self, publisher: Publisher[Any]) -> bool:
        managed_entities(self).discard(publisher)
        return super().destroy_publisher(publisher)

    def create_timer(
        self,
        timer_period_sec: float,
        callback: Callable[..., Any] | None,
        callback_group: CallbackGroup | None = None,
        clock: Clock | None = None,
        autostart: bool = True,
        *,
        managed: bool = True,
    ) -> Timer:
        """Create a timer that runs only while the node is active.

        :param managed: ``False`` for an ordinary timer that runs in every state.
        """
        # ``callback`` may be None as in rclpy 9, whose signature this overrides;
        # rclpy 7 annotates it as not optional.
        if not (managed and self._entities_follow_state):
            return super().create_timer(timer_period_sec, callback, callback_group, clock, autostart)  # type: ignore[arg-type, unused-ignore]
        running = autostart and self.lifecycle_state.label == "active"
        timer = super().create_timer(timer_period_sec, callback, callback_group, clock, running)  # type: ignore[arg-type, unused-ignore]
        self._managed_timers.add(timer)
        if autostart and not running:
            self._paused_timers.add(timer)
        return timer

    def destroy_timer(self, timer: Timer) -> bool:
        self._managed_timers.discard(timer)
        self._paused_timers.discard(timer)
        return super().destroy_timer(timer)

    def _pause_timers(self) -> None:
        for timer in self._managed_timers:
            if not timer.is_canceled():
                timer.cancel()
                self._paused_timers.add(timer)

    def _follow_state(self, state: LifecycleState) -> None:
        enabled = state.label in _PUBLISHING
        for entity in list(managed_entities(self)):
            if isinstance(entity, LifecyclePublisher) and entity.is_activated != enabled:
                if enabled:
                    entity.on_activate(state)
                else:
                    entity.on_deactivate(state)
        if state.label == "active":
            for timer in self._paused_timers:
                timer.reset()
            self._paused_timers.clear()

    def destroy_node(self) -> None:
        if self._heartbeat is not None:
            self._heartbeat.close()
            self._heartbeat = None
        super().destroy_node()  # type: ignore[no-untyped-call, unused-ignore]  # rclpy 7's is untyped


def _discard(awaitable: Any) -> None:
    close = getattr(awaitable, "close", None)
    if close is not None:
        close()
