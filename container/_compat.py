"""Every private rclpy, asyncio and argparse name the project relies on, in one place.

The executor and the lifecycle base do what rclpy's own executors and
lifecycle node do, and for that they reach behind some underscores. Each such
name is wrapped here once, with the versions known to have it, so that a new
rclpy or Python that drops one breaks this module's test
(``tests/test_compat.py``, which checks every entry of :data:`PRIVATE_NAMES`)
instead of a callback somewhere at run time.

Checked against rclpy 7.1 (Jazzy) and 9.1 (Kilted), with the rclpy of
Rolling (10.x) where stated; CPython 3.11.7, 3.12.1 and 3.13.0, each run
of ``tests/test_compat.py`` on every leg of CI's matrix.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ctypes
import functools
import inspect
import os
import re
import signal
import sys
import warnings
from collections.abc import Callable, Sized
from types import FrameType
from typing import TYPE_CHECKING, Any, Protocol, TypeAlias

import rclpy.timer
from rclpy.event_handler import EventHandler
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.subscription import Subscription

if TYPE_CHECKING:
    from rclpy.executors import Executor
    from rclpy.guard_condition import GuardCondition
    from rclpy.node import Node
    from rclpy.task import Future
    from rclpy.timer import Timer
    from rclpy.waitable import Waitable

__all__ = [
    "PRIVATE_NAMES",
    "TIMER_INFO",
    "DoneCallbackRunner",
    "FdCallbackLoop",
    "InvalidROSArgsError",
    "RCLError",
    "RequestId",
    "SubParsers",
    "UnknownROSArgsError",
    "WaitSet",
    "adopt_future",
    "callback_attribute",
    "client_not_matched",
    "enter_task",
    "event_handle",
    "executor_guards",
    "finish_type_description_service",
    "fire_timer",
    "hand_signal_over",
    "is_built",
    "leave_task",
    "loop_is_idle",
    "loop_ready_queue",
    "managed_entities",
    "mark_event_ready",
    "raise_client_not_matched",
    "rcutils_log",
    "request_client",
    "running_loop",
    "runs_plain_callback",
    "set_event_index",
    "skip_in_log_calls",
    "sleeps_zero",
    "state_machine",
    "state_machine_if_built",
    "subscription_wants_info",
    "thread_frame",
    "waitable_futures",
    "wake_guard",
    "wraps_an_awaitable",
]

#: ``(owner, name, where known)`` of every private name used below; the test
#: asserts each still exists. Owners are dotted paths (module or class).
PRIVATE_NAMES: tuple[tuple[str, str, str], ...] = (
    ("asyncio.tasks", "_enter_task", "CPython 3.7-3.14; what Task.__step calls around each step"),
    ("asyncio.tasks", "_leave_task", "CPython 3.7-3.14"),
    ("asyncio", "_get_running_loop", "CPython 3.7-3.14; get_running_loop() without the raise"),
    ("asyncio.tasks", "__sleep0", "CPython 3.7-3.14; what asyncio.sleep(0) yields from"),
    ("rclpy.impl.implementation_singleton", "rclpy_implementation", "rclpy 1.0-10.x: the C extension"),
    (
        "rclpy.impl.implementation_singleton.rclpy_implementation",
        "rclpy_logging_rcutils_log",
        "rclpy 2.0-10.x; what RcutilsLogger.log ends in",
    ),
    (
        "rclpy.impl.rcutils_logger",
        "_internal_callers",
        "rclpy 1.0-10.x; files whose frames a logger skips looking for its caller (a list third parties may extend)",
    ),
    ("rclpy.event_handler.EventHandler", "_EventHandler__event", "rclpy 4.0-10.x (instance attribute)"),
    ("rclpy.event_handler.EventHandler", "_event_index", "rclpy 4.0-10.x (instance attribute)"),
    ("rclpy.event_handler.EventHandler", "_ready_to_take_data", "rclpy 4.0-10.x (instance attribute)"),
    ("rclpy.subscription.Subscription", "_callback_type", "rclpy 4.0-10.x (instance attribute)"),
    ("rclpy.subscription.Subscription", "_callback", "rclpy 4.0-10.x (instance attribute); what .callback returns"),
    ("rclpy.task.Future", "_set_executor", "rclpy 1.0-10.x"),
    ("rclpy.waitable.Waitable", "_futures", "rclpy 1.0-10.x (instance attribute)"),
    ("rclpy.executors.Executor", "_guard", "rclpy 1.0-10.x (instance attribute)"),
    ("rclpy.executors.Executor", "_sigint_gc", "rclpy 1.0-10.x (instance attribute)"),
    ("rclpy.lifecycle.LifecycleNodeMixin", "_state_machine", "rclpy 4.0-10.x (instance attribute)"),
    ("rclpy.lifecycle.LifecycleNodeMixin", "_managed_entities", "rclpy 4.0-10.x (instance attribute)"),
    ("rclpy.node.Node", "_Node__node", "rclpy 1.0-10.x (instance attribute)"),
    ("sys", "_current_frames", "CPython 2.5-3.14; what faulthandler and py-spy read"),
    ("sys", "_getframe", "CPython 2.1-3.14; what logging and inspect read a caller from"),
    (
        "rclpy.node.Node",
        "_wake_executor",
        "rclpy 1.0-10.x; what every create_*, add_waitable, destroy_* and remove_waitable calls",
    ),
    ("argparse", "_SubParsersAction", "CPython 3.2-3.14; what add_subparsers() returns"),
    (
        "rclpy.node.Node",
        "_type_description_service",
        "rclpy 7.0-10.x (instance attribute); the ~/get_type_description service's holder",
    ),
    (
        "rclpy.type_description_service.TypeDescriptionService",
        "_type_description_srv",
        "rclpy 7.0-10.x (instance attribute); None while the service is off",
    ),
    ("rclpy.action.server.ActionServer", "_execute_goal", "rclpy 1.0-10.x; create_task()s the execute callback"),
    ("asyncio.base_events.BaseEventLoop", "_ready", "CPython 3.4-3.14 (instance attribute)"),
    ("asyncio.base_events.BaseEventLoop", "_stopping", "CPython 3.4-3.14 (instance attribute)"),
    (
        "asyncio.selector_events.BaseSelectorEventLoop",
        "_add_reader",
        "CPython 3.4-3.14; add_reader() and the loop's own transports register readers through it",
    ),
    ("asyncio.selector_events.BaseSelectorEventLoop", "_add_writer", "CPython 3.4-3.14; as _add_reader, for writers"),
    (
        "asyncio.unix_events._UnixSelectorEventLoop",
        "_signal_handlers",
        "CPython 3.4-3.14 (instance attribute); the signals add_signal_handler took",
    ),
) + (
    # Checked where it exists: from 3.12 asyncio wraps such an awaitable in
    # a local ``async def``, an ordinary coroutine the task factory adapts.
    (("asyncio.tasks", "_wrap_awaitable", "CPython 3.5-3.11 only (a generator)"),)
    if sys.version_info < (3, 12)
    else ()
)

# -- asyncio ----------------------------------------------------------------------

#: Make ``task`` the loop's current task (``asyncio.current_task()``) while a
#: coroutine step runs outside ``Task.__step``: what 3.12's eager tasks do.
#: Not eager tasks themselves: a callback's first step in a reused runner
#: task costs 0.75 us with these, a new eager task 5.2 us (3.12.1; 4.3 us
#: on 3.13.0), several times what the rest of an async callback's dispatch costs.
enter_task: Callable[[asyncio.AbstractEventLoop, asyncio.Task[Any]], None] = asyncio.tasks._enter_task
leave_task: Callable[[asyncio.AbstractEventLoop, asyncio.Task[Any]], None] = asyncio.tasks._leave_task

#: The code of the generator ``asyncio.sleep(0)`` yields a bare ``None`` from.
_SLEEP0_CODE = getattr(asyncio.tasks, "__sleep0").__code__


#: The code of what ``asyncio.ensure_future()`` wraps a non-coroutine
#: awaitable in on 3.11, a generator; ``None`` from 3.12 (a coroutine there).
_WRAP_AWAITABLE_CODE: object = getattr(getattr(asyncio.tasks, "_wrap_awaitable", None), "__code__", None)


def wraps_an_awaitable(coro: object) -> bool:
    """Whether ``coro`` is Python 3.11's generator wrapping an awaitable that
    is no coroutine (``wait_for``, ``gather``, ``ensure_future`` of an rclpy
    future). Always ``False`` from 3.12, where that wrapper is a coroutine."""
    return _WRAP_AWAITABLE_CODE is not None and getattr(coro, "gi_code", None) is _WRAP_AWAITABLE_CODE


def sleeps_zero(coro: object) -> bool:
    """Whether ``coro``, which just yielded a bare ``None``, did so in
    ``asyncio.sleep(0)`` (asyncio's "run me again at once"), not in an
    rclpy future's ``await`` (which yields ``None`` until done)."""
    inner = coro
    while True:
        nxt = getattr(inner, "cr_await", None)
        if nxt is None:
            nxt = getattr(inner, "gi_yieldfrom", None)
        if nxt is None:
            return getattr(inner, "gi_code", None) is _SLEEP0_CODE
        inner = nxt


def running_loop() -> asyncio.AbstractEventLoop | None:
    """The running loop of this thread, or ``None`` (no exception on the hot path)."""
    return asyncio._get_running_loop()


def loop_is_idle(loop: asyncio.AbstractEventLoop) -> bool:
    """Whether asyncio has nothing to run before its next select: no ready callback, no stop asked."""
    return not loop._ready and not loop._stopping  # type: ignore[attr-defined]


def hand_signal_over(loop: asyncio.AbstractEventLoop, signum: int, handler: Callable[[int, Any], object]) -> None:
    """Take ``signum`` from ``loop``'s signal handlers and leave it to ``handler`` (a
    Python-level one), with no default disposition in between.

    asyncio's ``remove_signal_handler`` puts Python's default back first:
    for SIGINT ``default_int_handler``, whose ``KeyboardInterrupt`` a
    repeated Ctrl-C landing between that and the next ``signal.signal``
    raised in the middle of an orderly stop (a container ended 130 instead
    of 0, once in about a hundred runs of the signals test); for SIGTERM
    ``SIG_DFL``, which kills the process. Here ``handler`` is installed
    first, then the loop forgets the signal as ``remove_signal_handler``
    would (its entry, and the wake-up descriptor once none is left). A loop
    with no such table (not a Unix selector loop) goes through the public
    method.
    """
    handlers = getattr(loop, "_signal_handlers", None)
    if not isinstance(handlers, dict):
        loop.remove_signal_handler(signum)
        signal.signal(signum, handler)
        return
    signal.signal(signum, handler)
    if handlers.pop(signum, None) is not None and not handlers:
        with contextlib.suppress(ValueError, OSError):
            signal.set_wakeup_fd(-1)


def loop_ready_queue(loop: asyncio.AbstractEventLoop) -> Sized:
    """The queue of callbacks asyncio runs before its next select (non-empty: it has work)."""
    return loop._ready  # type: ignore[attr-defined, no-any-return]


class FdCallbackLoop(asyncio.SelectorEventLoop):
    """asyncio's selector loop, with one place that sees every file descriptor's callback.

    ``add_reader``/``add_writer`` and asyncio's own transports (sockets,
    pipes, subprocesses: they call ``_add_reader`` directly, past the public
    method) all register through ``_add_reader``/``_add_writer``, which hand
    each callback to :meth:`fd_callback` first. A serial transport
    (pyserial-asyncio) uses the public ``add_reader``, which ends there too.
    """

    def fd_callback(
        self, callback: Callable[..., Any], args: tuple[Any, ...]
    ) -> tuple[Callable[..., Any], tuple[Any, ...]]:
        """What the loop registers instead of ``callback(*args)`` (by default, that)."""
        return callback, args

    def _add_reader(self, fd: Any, callback: Callable[..., Any], *args: Any) -> Any:
        callback, args = self.fd_callback(callback, args)
        return super()._add_reader(fd, callback, *args)  # type: ignore[misc]

    def _add_writer(self, fd: Any, callback: Callable[..., Any], *args: Any) -> Any:
        callback, args = self.fd_callback(callback, args)
        return super()._add_writer(fd, callback, *args)  # type: ignore[misc]


def thread_frame(ident: int) -> FrameType | None:
    """The frame another thread is executing now (for a stuck thread's stack)."""
    return sys._current_frames().get(ident)


def caller_frame(depth: int) -> FrameType:
    """The frame ``depth`` calls above the one calling this (0: the caller's own)."""
    return sys._getframe(depth + 1)


# -- argparse ---------------------------------------------------------------------

#: What ``ArgumentParser.add_subparsers()`` returns; argparse names no public type.
SubParsers: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"

# -- the rclpy C extension ----------------------------------------------------------

#: rcl's wait set, which the executor caches instead of rebuilding per wait.
WaitSet: Any = rclpy_implementation.WaitSet
#: What rcl raises for malformed ``--ros-args``.
InvalidROSArgsError: type[Exception] = rclpy_implementation.RCLInvalidROSArgsError
#: What rcl raises for ``--ros-args`` it does not know (``--bogus``); ``args[0]`` lists them.
UnknownROSArgsError: type[Exception] = rclpy_implementation.UnknownROSArgsError
#: What rclpy raises when an rcl call fails (``send_response`` among them).
RCLError: type[Exception] = rclpy_implementation.RCLError
#: A service request's id (``rmw_request_id_t``), which a service's answer is sent to.
RequestId: type = rclpy_implementation.rmw_request_id_t

#: rcutils' log call, the one rclpy's loggers end in: ``(severity, logger name,
#: message, function, file, line)``. Called directly so that a Python log
#: record keeps its own place in the code (``RcutilsLogger.log`` records its
#: caller, and refuses one call site logging at two severities).
_RCUTILS_LOG: Callable[[int, str, str, str, str, int], None] = rclpy_implementation.rclpy_logging_rcutils_log


def rcutils_log(severity: int, name: str, message: str, *, function: str, file: str, line: int) -> None:
    """Log ``message`` through rcutils: its console format, and once rcl has
    configured logging, the log file and ``/rosout`` (for a node's loggers).

    Safe in a Python signal handler: rclpy's logging lock (a recursive
    mutex) is taken only inside its C calls (this one, a node's creation
    and destruction), which hold the GIL throughout and run no Python code
    but a warning when rcl fails to finalise a node. The code a signal
    interrupts therefore holds it only in that case, and then in the same
    thread, which may take it again.
    """
    _RCUTILS_LOG(severity, name, message, function, file, line)


def skip_in_log_calls(path: str) -> None:
    """Have rclpy's loggers skip the frames of ``path`` when they look for a
    line's call site, as they skip their own: a logger subclass's ``log``
    calling rclpy's (``container._logger``) would otherwise be every line's
    call site, and the ``once`` and throttle filters, which keep their state
    per call site, would take one site's lines for another's."""
    from rclpy.impl import rcutils_logger

    callers: list[str] = rcutils_logger._internal_callers
    resolved = os.path.realpath(path)
    if resolved not in callers:
        callers.append(resolved)


#: rclpy's words when rmw timed out waiting for a client's response reader.
_CLIENT_NOT_MATCHED = "failed to send response (timeout)"


def client_not_matched(error: BaseException) -> bool:
    """Whether ``error``, from rclpy's ``send_response``, says the client's response
    reader is not matched (yet): the answer can be sent again later.

    rclpy says it two ways. Where rcl passes rmw's timeout on (Jazzy, Kilted:
    ros2/rcl#1048), rclpy warns ``RuntimeWarning("failed to send response
    (timeout)...")`` from C++, which only an error filter makes catchable
    (:func:`raise_client_not_matched`); pybind11 then returns normally, and
    CPython raises ``SystemError`` with that warning as its cause. Otherwise
    rcl's error is an ``RCLError`` naming "will not receive response".
    """
    if isinstance(error, SystemError):
        error = error.__cause__ if isinstance(error.__cause__, RuntimeWarning) else error
    if isinstance(error, RuntimeWarning):
        return _CLIENT_NOT_MATCHED in str(error)
    return isinstance(error, RCLError) and "will not receive response" in str(error)


#: Where a pybind11 instance keeps the pointer to its C++ value: right after the
#: object header (pybind11's ``instance::simple_value_holder[0]``, since 2.2).
_PYBIND_VALUE_AT = object.__basicsize__
#: ``rmw_request_id_t``: ``int8_t writer_guid[16]`` then ``int64_t sequence_number``.
_GUID_SIZE = 16
_REQUEST_ID_SIZE = 24


def request_client(header: Any) -> bytes | None:
    """The client a request came from: the GUID in rclpy's request header (a
    ``rmw_service_info_t`` or its ``request_id``), or ``None`` if it cannot be read.

    rclpy's binding of ``rmw_request_id_t`` exposes the sequence number and
    not ``writer_guid`` (rclpy 7 and 9): the GUID is read from the C struct
    the pybind11 instance points to, and trusted only when the sequence
    number read beside it is the one rclpy reports (else ``None``: a
    layout this does not know).
    """
    request_id: Any = getattr(header, "request_id", header)
    kind = type(request_id)
    if kind is not RequestId:
        return None
    address = ctypes.c_void_p.from_address(id(request_id) + _PYBIND_VALUE_AT).value
    if not address:
        return None
    raw = ctypes.string_at(address, _REQUEST_ID_SIZE)
    if int.from_bytes(raw[_GUID_SIZE:], sys.byteorder, signed=True) != request_id.sequence_number:
        return None
    return raw[:_GUID_SIZE]


def raise_client_not_matched() -> None:
    """Make rclpy's unmatched-client warning an error, so that :func:`client_not_matched`
    sees it (for the whole process; calling again changes nothing)."""
    warnings.filterwarnings("error", message=re.escape(_CLIENT_NOT_MATCHED), category=RuntimeWarning)

# -- executors, entities, futures -------------------------------------------------


#: rclpy's node methods that wake the executor because they added an entity.
_ADDING = ("create_", "add_waitable")


def woken_by_an_addition() -> bool:
    """Whether the ``Executor.wake()`` calling this was called because a node added an entity.

    rclpy's nodes wake their executor through ``Node._wake_executor``, which
    every ``create_*`` and ``add_waitable`` calls once it added the entity,
    and every ``destroy_*``, ``remove_waitable`` and ``destroy_node`` once
    it removed one. Only a removal can leave work of an entity that is gone.
    ``False`` for any other caller: look for such work.
    """
    waker = caller_frame(2)  # 0: this, 1: the executor's wake(), 2: what called it
    if waker.f_code.co_name != "_wake_executor" or waker.f_back is None:
        return False
    return waker.f_back.f_code.co_name.startswith(_ADDING)


def wake_guard(executor: Executor) -> GuardCondition:
    """The guard condition the base class's ``wake()`` triggers (set until it shuts down)."""
    guard: GuardCondition | None = executor._guard
    if guard is None:
        raise RuntimeError("the executor is shut down: it has no wake-up guard")
    return guard


def executor_guards(executor: Executor) -> list[GuardCondition]:
    """The base class's wake-up guard and its SIGINT guard (``None``s skipped).

    ``Executor.wake()`` triggers the first; rclpy's signal handler the second.
    """
    guards = (executor._guard, executor._sigint_gc)
    return [guard for guard in guards if guard is not None]


def event_handle(handler: object) -> Any | None:
    """The rcl event handle inside a QoS ``EventHandler``, or ``None``.

    Adding the handle directly costs about a microsecond per wait less than
    the generic Waitable path; ``None`` (any other waitable, or an rclpy that
    renamed the attribute) falls back to that generic path.
    """
    if isinstance(handler, EventHandler):
        return getattr(handler, "_EventHandler__event", None)
    return None


def set_event_index(handler: object, index: int) -> None:
    """Tell an ``EventHandler`` where its handle sits in a wait set we filled."""
    handler._event_index = index  # type: ignore[attr-defined]


def mark_event_ready(handler: object) -> None:
    """Tell an ``EventHandler`` its event fired, as ``is_ready`` would after a wait.

    The executor learns it from rmw's event callback instead of a wait set;
    ``take_data`` takes the event only once told.
    """
    handler._ready_to_take_data = True  # type: ignore[attr-defined]


def subscription_wants_info(subscription: Subscription[Any]) -> bool:
    """Whether the callback takes ``(message, message_info)``; rclpy decides by signature."""
    return subscription._callback_type is not Subscription.CallbackType.MessageOnly


class DoneCallbackRunner(Protocol):
    """What rclpy's future needs of its executor: ``create_task(callback, future)``."""

    def create_task(self, callback: Callable[..., Any], *args: Any, **kwargs: Any) -> object: ...


def adopt_future(future: Future[Any], executor: Executor | DoneCallbackRunner) -> None:
    """Make ``executor`` run ``future``'s done-callbacks, as rclpy's executors do
    (rclpy's future calls its ``create_task(callback, future)`` for each)."""
    # rclpy 9 annotates an Executor; its future only calls create_task on it.
    future._set_executor(executor)  # type: ignore[arg-type, unused-ignore]


def runs_plain_callback(function: Callable[..., Any], args: tuple[Any, ...]) -> bool:
    """Whether a coroutine function will call a plain callback among ``args`` inline.

    rclpy's action server hands the user's execute callback to
    ``executor.create_task(self._execute_goal, execute_callback, goal_handle)``,
    a coroutine that runs it through ``await_or_execute``: a plain callback
    is then called inside the coroutine, and may block for the whole goal.
    Recognised by the coroutine's code naming ``await_or_execute``.
    """
    code = getattr(function, "__code__", None)
    if code is None or "await_or_execute" not in code.co_names:
        return False
    return any(callable(arg) and not inspect.iscoroutinefunction(arg) for arg in args)


def waitable_futures(waitable: Waitable[Any]) -> list[Future[Any]]:
    """The futures a waitable (an action client) completes when it executes."""
    futures: list[Future[Any]] = waitable._futures
    return futures


def callback_attribute(entity: object) -> str:
    """The attribute holding ``entity``'s callback, for code that reads it per call.

    rclpy's ``Subscription.callback`` is a property over ``_callback``: a
    Python call on every message where reading the attribute is a dict
    lookup. Both are current, so a callback replaced later is still seen.
    """
    if isinstance(entity, Subscription) and "_callback" in vars(entity):
        return "_callback"
    return "callback"


# -- timers ---------------------------------------------------------------------------

#: ``rclpy.timer.TimerInfo`` where rclpy has it (Kilted and later); ``None`` on Jazzy.
TIMER_INFO: type | None = getattr(rclpy.timer, "TimerInfo", None)


def fire_timer(timer: Timer) -> dict[str, Any] | None:
    """Mark a ready timer as called; the keyword arguments its callback takes.

    :return: ``None`` if the timer was not ready after all (cancelled or reset
        meanwhile); otherwise ``{}``, or ``{name: TimerInfo(...)}`` when rclpy
        has ``TimerInfo`` and the callback has a parameter annotated with it,
        which is how rclpy's own executors decide to pass one.
    """
    handle = timer.handle
    if not handle.is_timer_ready():
        return None
    call_with_info = getattr(handle, "call_timer_with_info", None)
    if TIMER_INFO is None or call_with_info is None:
        handle.call_timer()
        return {}
    info = call_with_info()
    name = timer_info_parameter(timer.callback)
    if name is None:
        return {}
    return {
        name: TIMER_INFO(
            expected_call_time=info["expected_call_time"],
            actual_call_time=info["actual_call_time"],
            clock_type=timer.clock.clock_type,
        )
    }


def timer_info_parameter(callback: Callable[..., Any] | None) -> str | None:
    """The name of ``callback``'s parameter annotated with ``TimerInfo``, if any."""
    if callback is None or TIMER_INFO is None:
        return None
    try:
        parameters = inspect.signature(callback).parameters.values()
    except (TypeError, ValueError):
        return None
    for parameter in parameters:
        if parameter.annotation is TIMER_INFO or parameter.annotation == TIMER_INFO.__name__:
            return parameter.name
    return None


# -- lifecycle --------------------------------------------------------------------


def is_built(node: Node) -> bool:
    """Whether ``Node.__init__`` got as far as creating the rcl node."""
    return getattr(node, "_Node__node", None) is not None


def state_machine_if_built(node: Node) -> Any | None:
    """The lifecycle state machine, if a (maybe half-built) node has one."""
    return getattr(node, "_state_machine", None)


# These take a ``Node``: container.LifecycleNode is a subclass of rclpy's
# LifecycleNode at run time, but type checkers see it through a facade
# (``container/lifecycle/_base.pyi``) that is a plain ``Node`` to them.


def state_machine(node: Node) -> Any:
    """The rcl lifecycle state machine of a lifecycle node (rclpy has no accessor).

    rclpy's C++ ``LifecycleStateMachine``; of it the node uses, holding it
    (``with machine:``), ``current_state``, ``available_states``,
    ``available_transitions``, ``transition_graph`` (the standard services'
    answers) and ``trigger_transition_by_id`` / ``_by_label`` (which publish
    ``transition_event``), rclpy 4.0-10.x.
    """
    return node._state_machine  # type: ignore[attr-defined]


def managed_entities(node: Node) -> set[Any]:
    """The entities (lifecycle publishers) a lifecycle node activates and deactivates."""
    entities: set[Any] = node._managed_entities  # type: ignore[attr-defined]
    return entities


# -- what rclpy leaves behind -------------------------------------------------------


@functools.cache
def _rcl_service_fini() -> Any:
    """rcl's ``rcl_service_fini``, typed: from the ``librcl.so`` rclpy loaded (by its
    soname, as ``_security`` reaches librcutils)."""
    fini = ctypes.CDLL("librcl.so").rcl_service_fini
    fini.argtypes = (ctypes.c_void_p, ctypes.c_void_p)
    fini.restype = ctypes.c_int
    return fini


def finish_type_description_service(node: Node) -> bool:
    """Finalise ``node``'s ``~/get_type_description`` service, which rclpy never does.

    rclpy's ``TypeDescriptionService`` (rclpy 7.0-10.x) wraps the
    ``rcl_service_t`` that ``rcl_node_type_description_service_init`` fills
    in a shared pointer with no deleter, and rcl leaves ``rcl_service_fini``
    to the caller: after ``destroy_node`` the service stays on the ROS graph
    (``ros2 service list`` shows it, with no node) and in Fast DDS (its reader
    and writer, about 100 kB of heap a node), for as long as the process
    lives. Measured here on Jazzy and Kilted: 200 bare nodes created and
    destroyed add 20 MiB of live heap a cycle, and each destroyed node's
    ``/<name>/get_type_description`` is still listed.

    Call it only once nothing waits on the node's entities (no wait set
    holds the service) and before the node is destroyed: rcl finalises the
    service through the node. rclpy's own destruction afterwards only frees
    the struct. :return: whether there was a service to finalise.
    """
    holder = getattr(node, "_type_description_service", None)
    service = getattr(holder, "_type_description_srv", None)
    if service is None:
        return False
    impl = service.impl
    with impl, node.handle:  # both alive until rcl is done with them
        ret = _rcl_service_fini()(impl.pointer, node.handle.pointer)
    if ret != 0:
        raise RCLError(f"rcl_service_fini of {node.get_fully_qualified_name()}'s type description service: {ret}")
    return True
