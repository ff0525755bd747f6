"""Every private rclpy/asyncio name in ``container._compat`` still exists here.

When an rclpy or Python upgrade drops one, this is the test that fails, by
name, instead of a callback somewhere at run time.
"""

from __future__ import annotations

import asyncio
import importlib
import signal
import warnings
from collections.abc import Callable, Iterator
from types import SimpleNamespace
from typing import Any

import pytest
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.context import Context
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode
from rclpy.node import Node
from rclpy.waitable import Waitable
from std_msgs.msg import String

from container import _compat
from tests.waiting import wait_until


@pytest.fixture
def samples(context: Context) -> Iterator[dict[str, Callable[[], Any]]]:
    """Real instances of the classes whose private names are instance attributes."""
    node = LifecycleNode("compat_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    publisher = node.create_publisher(
        String, "probe", 10, event_callbacks=PublisherEventCallbacks(liveliness=lambda _: None)
    )
    subscription = node.create_subscription(String, "probe", lambda _: None, 10)
    handlers = [w for w in node.waitables if type(w).__name__ == "EventHandler"]
    loop = asyncio.new_event_loop()
    yield {
        "asyncio.base_events.BaseEventLoop": lambda: loop,
        "asyncio.unix_events._UnixSelectorEventLoop": lambda: loop,
        "rclpy.event_handler.EventHandler": lambda: handlers[0],
        "rclpy.subscription.Subscription": lambda: subscription,
        "rclpy.waitable.Waitable": lambda: Waitable(MutuallyExclusiveCallbackGroup()),
        "rclpy.executors.Executor": lambda: executor,
        "rclpy.lifecycle.LifecycleNodeMixin": lambda: node,
        "rclpy.node.Node": lambda: node,
        "rclpy.type_description_service.TypeDescriptionService": lambda: node._type_description_service,
    }
    loop.close()
    executor.shutdown()
    node.destroy_publisher(publisher)
    node.destroy_node()
    _compat.state_machine(node).destroy_when_not_in_use()


def _resolve(path: str) -> Any:
    module_name, _, attribute = path.rpartition(".")
    try:
        return importlib.import_module(path)
    except ImportError:
        return getattr(importlib.import_module(module_name), attribute)


@pytest.mark.parametrize(("owner", "name", "versions"), _compat.PRIVATE_NAMES, ids=lambda v: str(v))
def test_private_name_exists(owner: str, name: str, versions: str, samples: dict[str, Callable[[], Any]]) -> None:
    target = samples[owner]() if "instance attribute" in versions else _resolve(owner)
    assert hasattr(target, name), f"{owner}.{name} is gone ({versions}): update container/_compat.py"


def test_qos_event_handlers_take_the_direct_path(samples: dict[str, Callable[[], Any]]) -> None:
    """The fast path for QoS events needs the handle; its fallback would be silent."""
    assert _compat.event_handle(samples["rclpy.event_handler.EventHandler"]()) is not None


def test_enter_task_makes_a_task_current() -> None:
    async def probe() -> None:
        loop = asyncio.get_running_loop()
        other = loop.create_task(asyncio.sleep(0))
        current = asyncio.current_task()
        assert current is not None
        _compat.leave_task(loop, current)
        _compat.enter_task(loop, other)
        try:
            assert asyncio.current_task() is other
        finally:
            _compat.leave_task(loop, other)
            _compat.enter_task(loop, current)
        await other

    asyncio.run(probe())


class _FakeTimerInfo:
    """Stands in for rclpy's TimerInfo (Kilted and later) on Jazzy."""

    def __init__(self, *, expected_call_time: int, actual_call_time: int, clock_type: object) -> None:
        self.expected_call_time = expected_call_time
        self.actual_call_time = actual_call_time
        self.clock_type = clock_type


class _FakeHandle:
    def __init__(self, *, with_info: bool) -> None:
        self.calls: list[str] = []
        if with_info:
            self.call_timer_with_info = self._call_with_info

    def is_timer_ready(self) -> bool:
        return True

    def call_timer(self) -> None:
        self.calls.append("plain")

    def _call_with_info(self) -> dict[str, int]:
        self.calls.append("info")
        return {"expected_call_time": 10, "actual_call_time": 12}


def test_timer_callbacks_get_timer_info_the_way_rclpy_passes_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where rclpy has TimerInfo, a parameter annotated with it receives one."""
    monkeypatch.setattr(_compat, "TIMER_INFO", _FakeTimerInfo)
    received: list[_FakeTimerInfo] = []

    def wants(info: _FakeTimerInfo) -> None:
        received.append(info)

    def plain() -> None:
        pass

    clock = SimpleNamespace(clock_type="steady")
    handle = _FakeHandle(with_info=True)
    arguments = _compat.fire_timer(SimpleNamespace(handle=handle, callback=wants, clock=clock))  # type: ignore[arg-type]
    assert arguments is not None and set(arguments) == {"info"}
    wants(**arguments)
    assert (received[0].expected_call_time, received[0].actual_call_time) == (10, 12)
    assert _compat.fire_timer(SimpleNamespace(handle=handle, callback=plain, clock=clock)) == {}  # type: ignore[arg-type]
    assert handle.calls == ["info", "info"]


def test_timers_on_jazzy_are_called_plainly(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(_compat, "TIMER_INFO", None)
    handle = _FakeHandle(with_info=False)
    timer = SimpleNamespace(handle=handle, callback=lambda: None, clock=None)
    assert _compat.fire_timer(timer) == {}  # type: ignore[arg-type]
    assert handle.calls == ["plain"]


def _caused_by(cause: BaseException) -> SystemError:
    """What CPython raises when pybind11 returns normally with ``cause`` set (a warning made an error)."""
    error = SystemError("<built-in method service_send_response> returned a result with an exception set")
    error.__cause__ = cause
    return error


@pytest.mark.parametrize(
    ("error", "unmatched"),
    [
        (RuntimeWarning("failed to send response (timeout): client will not receive response"), True),
        (_caused_by(RuntimeWarning("failed to send response (timeout): rmw gave up")), True),
        (_compat.RCLError("Failed to send response: client will not receive response"), True),
        (RuntimeWarning("some other warning"), False),
        (_caused_by(ValueError("failed to send response (timeout)")), False),
        (SystemError("returned a result with an exception set"), False),
        (_compat.RCLError("failed to send response"), False),
        (TypeError("a service callback returned str, not Trigger_Response"), False),
    ],
    ids=[
        "warning", "warning-as-cause", "rcl-error", "other-warning", "other-cause", "no-cause", "other-rcl-error",
        "wrong-type",
    ],
)
def test_an_unmatched_client_is_recognised_in_each_form_rclpy_reports_it(error: BaseException, unmatched: bool) -> None:
    assert _compat.client_not_matched(error) is unmatched


def test_rclpys_unmatched_client_warning_becomes_an_error_and_no_other() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _compat.raise_client_not_matched()
        _compat.raise_client_not_matched()  # once is enough; again changes nothing
        with pytest.raises(RuntimeWarning) as raised:
            warnings.warn("failed to send response (timeout): rmw gave up", RuntimeWarning, stacklevel=1)
        assert _compat.client_not_matched(raised.value)
        warnings.warn("another runtime warning", RuntimeWarning, stacklevel=1)  # ignored, as before


def test_a_finished_type_description_service_leaves_the_graph_with_its_node(context: Context) -> None:
    """rclpy's ``destroy_node`` leaves ``~/get_type_description`` on the graph; finished first, it goes."""
    watcher = Node("compat_graph_watcher", context=context)
    kept = Node("compat_kept", context=context)
    finished = Node("compat_finished", context=context)
    names = ("/compat_kept/get_type_description", "/compat_finished/get_type_description")

    def services() -> set[str]:
        return {name for name, _ in watcher.get_service_names_and_types()}

    try:
        wait_until(lambda: set(names) <= services(), lambda: f"both services listed: {sorted(services())}")
        assert _compat.finish_type_description_service(finished)
        kept.destroy_node()
        finished.destroy_node()
        wait_until(lambda: names[1] not in services(), f"{names[1]} gone")
        # rclpy's own: the kept node's service is still listed, with no node behind it.
        assert names[0] in services()
        assert "/compat_kept" not in {f"{ns.rstrip('/')}/{n}" for n, ns in watcher.get_node_names_and_namespaces()}
    finally:
        watcher.destroy_node()


def test_a_signal_is_handed_from_the_loop_to_a_handler_with_no_default_in_between(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """asyncio's remove_signal_handler puts Python's default back first (SIGINT's raises
    KeyboardInterrupt, SIGTERM's kills): a signal landing then met it."""
    loop = asyncio.new_event_loop()
    before = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
    set_to: list[tuple[int, object]] = []
    real = signal.signal

    def recording(signum: int, handler: Any) -> Any:
        set_to.append((signum, handler))
        return real(signum, handler)

    def mine(signum: int, frame: object) -> None:
        pass

    try:
        for signum in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(signum, lambda: None)
        monkeypatch.setattr(signal, "signal", recording)
        for signum in (signal.SIGINT, signal.SIGTERM):
            _compat.hand_signal_over(loop, signum, mine)
        assert set_to == [(signal.SIGINT, mine), (signal.SIGTERM, mine)]
        assert signal.getsignal(signal.SIGINT) is mine and signal.getsignal(signal.SIGTERM) is mine
        assert not loop.remove_signal_handler(signal.SIGINT)  # the loop has let it go
        assert signal.set_wakeup_fd(-1) == -1  # and its wake-up descriptor
    finally:
        monkeypatch.undo()
        loop.close()
        for signum, handler in before.items():
            signal.signal(signum, handler)
