"""Answers to a client whose response reader never matches cost the process nothing.

A client asking for transient-local answers (``TRANSIENT_LOCAL`` response
reader) never matches a service's volatile response writer: Fast DDS's rmw
waits 100 ms in every send to it and gives up. Such sends happen in the
resender thread, never on the loop: without the GIL (the compiled send), or
not at all while the graph shows the reader incompatible (rclpy's send, which
keeps the GIL: the Python engine, services the compiled path cannot serve);
the client is given up on once, with one log line.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import gc
import itertools
import logging
import threading
import time
import weakref
from collections.abc import Callable
from typing import Any

import pytest
from lifecycle_msgs.srv import GetState
from rclpy.client import Client
from rclpy.context import Context
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from container import AsyncioExecutor, LifecycleNode
from container.executor import _answers, _executor
from tests.waiting import wait_until

#: The client of the issue: keep-all, reliable, transient-local (its response reader never matches).
UNMATCHABLE = QoSProfile(
    history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)
#: A 20 Hz timer's period, and the largest gap allowed beside such a client: two periods.
PERIOD_S = 0.05


def _heard(client: Client[Any, Any], request_type: Any, futures: list[Any]) -> None:
    """Ask until the service takes a request of ``client`` (one sent before its request
    writer matched the service's reader is lost; its own ``wait_for_service`` never
    returns true: rmw waits for its response reader too)."""
    before = _answers._resender.dropped

    def answered() -> bool:
        if _answers._resender._waiting > 0 or _answers._resender.dropped > before:
            return True
        futures.append(client.call_async(request_type()))
        return False

    wait_until(answered, "a request of the unmatched client taken", timeout=20.0)


def _spin(executor: AsyncioExecutor) -> threading.Thread:
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    return thread


@pytest.mark.parametrize("kind", ["plain", "async", "lifecycle", "rclpy"])
def test_requests_from_a_client_that_never_matches_leave_a_20hz_timer_on_time(
    kind: str,
    executor: AsyncioExecutor,
    host: Callable[..., Any],
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """50 requests from a transient-local client: the timer beside the service
    keeps its period (largest gap under two), the answers are dropped after the
    (here shortened) deadline with one log line for the client, none arrives."""
    from container.executor import _waitset

    monkeypatch.setattr(_answers, "RETRY_S", 0.5)
    if kind == "rclpy":
        monkeypatch.setattr(_waitset, "_server", lambda service: None)
    served: list[int] = []

    def answer(request: Any, response: Any) -> Any:
        served.append(1)
        return response

    async def answer_async(request: Any, response: Any) -> Any:
        return answer(request, response)

    callers = host(Node, f"unmatched_callers_{kind}")
    if kind == "lifecycle":
        server = host(LifecycleNode, f"unmatched_server_{kind}")
        service_type: Any = GetState
        service_name = f"/unmatched_server_{kind}/get_state"
    else:
        server = host(Node, f"unmatched_server_{kind}")
        service_type = Trigger
        service_name = f"unmatched_{kind}"
        # Keep-all, as the container's own services: every request is taken and answered.
        server.create_service(
            Trigger, service_name, answer_async if kind == "async" else answer,
            qos_profile=QoSProfile(history=HistoryPolicy.KEEP_ALL),
        )  # fmt: skip
    ticks: list[float] = []
    callers.create_timer(PERIOD_S, lambda: ticks.append(time.perf_counter()))
    unmatched: Client[Any, Any] = callers.create_client(service_type, service_name, qos_profile=UNMATCHABLE)
    good: Client[Any, Any] = callers.create_client(service_type, service_name)
    thread = _spin(executor)
    try:
        # The unmatched client's wait_for_service never returns true: rmw asks for its reader too.
        assert good.wait_for_service(timeout_sec=10.0)
        wait_until(lambda: len(ticks) >= 3, "the timer ticking")
        with caplog.at_level(logging.WARNING, logger=_answers.__name__):
            first_tick = len(ticks)
            futures: list[Any] = []
            _heard(unmatched, service_type.Request, futures)
            futures += [unmatched.call_async(service_type.Request()) for _ in range(50 - len(futures))]
            # A well-formed client of the same service is answered meanwhile.
            response: Any = good.call(service_type.Request(), timeout_sec=5.0)
            assert response is not None
            wait_until(lambda: "did not match" in caplog.text, "the client given up on", timeout=15.0)
            last_tick = len(ticks)
            wait_until(lambda: len(ticks) >= last_tick + 3, "the timer ticking after")
        lines = [record for record in caplog.records if "did not match" in record.getMessage()]
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
    assert not any(future.done() for future in futures)  # it really never matched
    assert len(lines) == 1, [record.getMessage() for record in lines]
    if kind != "lifecycle":
        assert len(served) >= 51  # the good client's, and the unmatched one's
    gaps = [later - earlier for earlier, later in itertools.pairwise(ticks[first_tick - 1 :])]
    lost = sum(max(0.0, gap - PERIOD_S) for gap in gaps)
    assert max(gaps) < 2 * PERIOD_S, f"largest gap {max(gaps) * 1000:.0f} ms, {lost:.2f} s lost"


def test_a_client_given_up_on_has_its_later_answers_dropped_at_once(
    executor: AsyncioExecutor, host: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """After the deadline, the client's further answers wait nowhere (nothing held for it)."""
    monkeypatch.setattr(_answers, "RETRY_S", 0.3)
    server, callers = host(Node, "given_up_server"), host(Node, "given_up_callers")
    server.create_service(
        Trigger, "given_up", lambda request, response: response, qos_profile=QoSProfile(history=HistoryPolicy.KEEP_ALL)
    )
    unmatched: Client[Any, Any] = callers.create_client(Trigger, "given_up", qos_profile=UNMATCHABLE)
    thread = _spin(executor)
    resender = _answers._resender
    try:
        dropped = resender.dropped
        _heard(unmatched, Trigger.Request, [])
        wait_until(lambda: resender.dropped > dropped, "the first answers dropped", timeout=10.0)
        before = resender.dropped
        for _ in range(20):
            unmatched.call_async(Trigger.Request())
        wait_until(lambda: resender.dropped >= before + 20, "the later answers dropped", timeout=5.0)
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)


def test_the_resender_ends_when_asked_and_when_idle(
    executor: AsyncioExecutor, host: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The container's own thread: ended by ``end_resender`` (a session's end),
    or by itself after a while with nothing to send."""
    monkeypatch.setattr(_answers, "IDLE_S", 0.2)
    monkeypatch.setattr(_answers, "RETRY_S", 0.3)
    server, callers = host(Node, "resender_end_server"), host(Node, "resender_end_callers")
    server.create_service(Trigger, "resender_end", lambda request, response: response)
    unmatched: Client[Any, Any] = callers.create_client(Trigger, "resender_end", qos_profile=UNMATCHABLE)
    thread = _spin(executor)

    def resender() -> list[threading.Thread]:
        return [t for t in threading.enumerate() if t.name == "respond-again"]

    try:
        _heard(unmatched, Trigger.Request, [])
        wait_until(resender, "the resender started")
        _answers.end_resender(timeout=2.0)
        assert not resender()
        unmatched.call_async(Trigger.Request())
        wait_until(resender, "the resender started again")
        wait_until(lambda: not resender(), "the resender ended, idle", timeout=10.0)
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)


def test_a_well_formed_clients_first_answer_is_sent_inline(
    executor: AsyncioExecutor, host: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The graph knows its response reader, with a QoS the service's writer offers:
    no hand-over to the resender, even for its first answer (an answer sent just
    before its service goes away still goes out)."""
    handed: list[Any] = []
    add = _answers._resender.add

    def spy(*args: Any, **kwargs: Any) -> None:
        handed.append(args)
        add(*args, **kwargs)

    monkeypatch.setattr(_answers._resender, "add", spy)
    server, callers = host(Node, "inline_server"), host(Node, "inline_callers")
    server.create_service(Trigger, "inline", lambda request, response: response)
    client: Client[Any, Any] = callers.create_client(Trigger, "inline")
    thread = _spin(executor)
    try:
        assert client.wait_for_service(timeout_sec=10.0)
        response: Any = client.call(Trigger.Request(), timeout_sec=5.0)
        assert response is not None
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
    assert handed == []


def test_what_is_remembered_of_clients_keeps_no_service_or_node_alive(
    executor: AsyncioExecutor, context: Context, host: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A client answered (remembered as matched) and a client given up on (remembered
    for its later answers) hold their service weakly: an unloaded node goes, with its
    services and what their callbacks hold; the resender's thread, idle, holds
    nothing either (its last try once kept the service, and the node, until its
    next answer: the service was then destroyed on that thread, under the GIL,
    200-300 ms of the whole process in the middle of other nodes' work)."""
    monkeypatch.setattr(_answers, "RETRY_S", 0.3)
    monkeypatch.setattr(_answers, "IDLE_S", 60.0)  # the thread outlives the node

    class Served(Node):
        def __init__(self) -> None:
            super().__init__("remembered_server", context=context)
            keep_all = QoSProfile(history=HistoryPolicy.KEEP_ALL)
            self.create_service(Trigger, "remembered", self.answer, qos_profile=keep_all)

        def answer(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
            return response

    server = Served()
    callers = host(Node, "remembered_callers")
    client: Client[Any, Any] = callers.create_client(Trigger, "remembered")
    unmatched: Client[Any, Any] = callers.create_client(Trigger, "remembered", qos_profile=UNMATCHABLE)
    executor.add_node(server)
    thread = _spin(executor)
    resender = _answers._resender
    try:
        assert client.wait_for_service(timeout_sec=10.0)
        assert client.call(Trigger.Request(), timeout_sec=5.0) is not None
        dropped = resender.dropped
        _heard(unmatched, Trigger.Request, [])
        wait_until(lambda: resender.dropped > dropped, "the unmatched client given up on", timeout=10.0)
        remembered = len(_answers._matched) + len(resender._clients)
        assert remembered >= 2, "neither client is remembered: nothing here is tested"
        # Unloaded, as the container unloads a node; the executor spins on.
        executor.remove_node(server)
        gone = weakref.ref(server)
        server.destroy_node()
        del server
        wait_until(lambda: gc.collect() >= 0 and gone() is None, "the unloaded node collected", timeout=5.0)
        assert resender._thread is not None, "the resender ended: nothing here is tested"
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
        _answers.end_resender(timeout=2.0)


def _served(context: Context, name: str, style: str) -> tuple[Node, Any]:
    """A node (not on any executor yet) with a ``Trigger`` service, its callback plain or ``async def``."""
    node = Node(name, context=context)

    def plain(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return response

    async def coroutine(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return response

    return node, node.create_service(Trigger, name, plain if style == "plain" else coroutine)


@pytest.mark.parametrize("style", ["plain", "async"])
def test_retiring_a_node_sends_the_answers_waiting_for_a_client_still_being_discovered(
    context: Context,
    executor: AsyncioExecutor,
    host: Callable[..., Any],
    monkeypatch: pytest.MonkeyPatch,
    style: str,
) -> None:
    """An answer to a client the service's graph does not know yet goes through the
    resender; destroying the service dropped it, and a caller whose ``change_state``
    an unload cancelled (CI, under load) was left waiting for good. Retiring the
    node (an unload, before it destroys it) now waits until such answers went out."""
    # The client's response reader not discovered yet: what a busy machine's graph says for a while.
    monkeypatch.setattr(_answers, "_in_graph", lambda node, srv, guid: False)
    monkeypatch.setattr(_executor, "_ANSWERS_WAIT_S", 30.0)  # the bound is another test's
    node, service = _served(context, "answered_at_unload", style)
    trying, go = threading.Event(), threading.Event()
    real_try = _answers._Resender._try

    def held(client: Any, entry: Any, srv: Any, server: Any, owner: Any) -> bool | None:
        if srv is service:  # ours, not an answer left by another test
            trying.set()
            go.wait(20.0)
        return real_try(client, entry, srv, server, owner)

    monkeypatch.setattr(_answers._Resender, "_try", staticmethod(held))
    executor.add_node(node)
    client: Client[Any, Any] = host(Node, "answered_at_unload_callers").create_client(Trigger, "answered_at_unload")
    thread = _spin(executor)
    try:
        assert client.wait_for_service(timeout_sec=10.0)
        pending = client.call_async(Trigger.Request())
        assert trying.wait(20.0), "the answer never reached the resender: nothing here is tested"
        retiring = asyncio.run_coroutine_threadsafe(executor.retire(node, timeout=30.0), executor.loop)
        with pytest.raises(concurrent.futures.TimeoutError):
            retiring.result(0.5)  # retired while its answer still waits: the old code returned here
        assert _answers.waiting_for(node) == 1
        go.set()
        assert retiring.result(20.0) == []
        node.destroy_node()
        wait_until(pending.done, "the caller answered", timeout=10.0)
        assert pending.result() is not None
    finally:
        go.set()
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
        node.destroy_node()
        _answers.end_resender(timeout=2.0)


def test_a_client_that_never_matches_holds_a_retiring_node_at_most_a_second(
    context: Context, executor: AsyncioExecutor, host: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Its answers would wait :data:`_answers.RETRY_S` to be given up on: an unload
    waits for them no longer than :data:`_executor._ANSWERS_WAIT_S`, then drops them."""
    monkeypatch.setattr(_answers, "RETRY_S", 30.0)
    node, _ = _served(context, "unmatched_at_unload", "plain")
    executor.add_node(node)
    unmatched: Client[Any, Any] = host(Node, "unmatched_at_unload_callers").create_client(
        Trigger, "unmatched_at_unload", qos_profile=UNMATCHABLE
    )
    thread = _spin(executor)
    try:
        _heard(unmatched, Trigger.Request, [])
        assert _answers.waiting_for(node) > 0
        started = time.monotonic()
        retiring = asyncio.run_coroutine_threadsafe(executor.retire(node, timeout=30.0), executor.loop)
        assert retiring.result(20.0) == []
        took = time.monotonic() - started
        assert _executor._ANSWERS_WAIT_S <= took < _executor._ANSWERS_WAIT_S + 5.0, took
        node.destroy_node()
        wait_until(lambda: _answers.waiting_for(node) == 0, "the dropped answers gone", timeout=10.0)
    finally:
        executor.shutdown(timeout_sec=5.0)
        thread.join(5.0)
        node.destroy_node()
        _answers.end_resender(timeout=2.0)


def test_a_service_without_client_guids_lets_go_of_its_node_once_its_answers_expired(
    context: Context, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A binding whose headers name no client (``guid`` ``None``) has its answers sent
    from the resender for a while; expired there, they let go of the service and
    its node as a client's dropped answers do (it kept both until forgotten)."""
    monkeypatch.setattr(_answers, "RETRY_S", 0.2)
    monkeypatch.setattr(_answers, "_sent", lambda *args, **kwargs: False)  # never matched
    node, service = _served(context, "guidless", "plain")
    resender = _answers._Resender()
    key = (weakref.ref(service), None)
    try:
        resender.add(key, service, None, Trigger.Response(), object(), tried=True, node=node)
        assert resender.waiting_for(node) == 1
        wait_until(lambda: resender.dropped == 1, "the answer expired", timeout=10.0)
        assert resender.waiting_for(node) == 0
        client = resender._clients[key]
        assert client.srv is None and client.node is None
    finally:
        resender.end(timeout=2.0)
        node.destroy_node()
