"""A wait set built again while nodes go away (``container/executor/_waitset.py``).

The loop's thread destroys a node's entities (its transitions, an unload)
while another thread may be collecting them into a new wait set: the relief
waiter (``rcl-waiter``) while the loop runs Python. A handle held for the
new table and destroyed before the compiled wait set took it made that build
fail with ``InvalidHandle``, and the half-built table was dropped with its
holds: a destroyed entity is let go only once nothing holds it, so the
entities it held stayed alive (a service stayed on the graph: this test).
Unloading 200 talkers from one container logged 115 such tracebacks
("dispatching ROS work failed").
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from rclpy.context import Context
from rclpy.node import Node
from std_msgs.msg import Empty
from std_srvs.srv import Trigger

from container import AsyncioExecutor
from container.executor import _entries, _waitset
from container.executor._dispatch import Dispatcher
from tests.waiting import wait_until


def _service_seen(peer: Node, name: str) -> bool:
    return any(found == name for found, _ in peer.get_service_names_and_types())


def test_entities_destroyed_while_the_wait_set_is_built_leave_the_graph(
    context: Context, executor: AsyncioExecutor, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    node = Node("rebuilt", context=context)
    peer = Node("rebuild_peer", context=context)  # not spun: it only looks at the graph
    timer = node.create_timer(0.5, lambda: None)
    service: Any = node.create_service(Trigger, "rebuilt_service", lambda request, response: response)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        wait_until(lambda: _service_seen(peer, "/rebuilt_service"), "the service on the graph")
        real = _entries.entities_of
        destroyed = threading.Event()

        def destroying_after(of: Node, kind: str) -> Iterator[Any]:
            yield from real(of, kind)
            if of is node and kind == "service" and not destroyed.is_set():
                # Every entity of the node is held for the table being built by now (services
                # are the last kind taken); destroyed before its wait set is built, as by
                # another thread.
                destroyed.set()
                node.destroy_timer(timer)
                node.destroy_service(service)

        monkeypatch.setattr(_waitset, "entities_of", destroying_after)
        with caplog.at_level(logging.ERROR, logger="container.executor"):
            executor.add_node(Node("rebuild_trigger", context=context))  # the table is built again
            wait_until(destroyed.is_set, "a table built")
            wait_until(lambda: not _service_seen(peer, "/rebuilt_service"), "the destroyed service off the graph")
        assert "dispatching ROS work failed" not in caplog.text
    finally:
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)
        for made in executor.get_nodes():
            made.destroy_node()
        node.destroy_node()
        peer.destroy_node()


def test_a_retired_node_no_longer_wakes_the_executor_as_it_is_destroyed(
    context: Context, executor: AsyncioExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An unload retires a node, then destroys it: each entity destroyed woke the executor,
    which collected every node's entities again, twice (its wait sets), and looked for
    work of entities gone: a hundred idle nodes' shutdown took 7.8 s."""
    node = Node("retired", context=context)
    for index in range(5):
        node.create_service(Trigger, f"retired_service_{index}", lambda request, response: response)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        stuck = asyncio.run_coroutine_threadsafe(executor.retire(node, timeout=1.0), executor.loop).result(10.0)
        assert stuck == []
        assert node.executor is None and node not in executor.get_nodes()
        woken: list[None] = []
        monkeypatch.setattr(executor, "wake", lambda: woken.append(None))
        node.destroy_node()
        assert woken == []
    finally:
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)


def test_only_a_removed_entity_makes_the_executor_look_for_work_of_entities_gone(
    context: Context, executor: AsyncioExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every entity a node creates or destroys wakes the executor (rclpy's nodes do so).
    Looking for work of entities that left walks every entity of every node, and only
    a removal can need it: done for each creation too, it was 58% of the configure of
    a hundred demo nodes."""
    swept: list[str] = []
    real = Dispatcher._sweep_tokens

    def counted(self: Dispatcher) -> None:
        swept.append("swept")
        real(self)

    monkeypatch.setattr(Dispatcher, "_sweep_tokens", counted)
    node = Node("sweeper", context=context)
    executor.add_node(node)
    swept.clear()
    publisher = node.create_publisher(Empty, "swept", 10)  # and its QoS event handlers: add_waitable
    subscription = node.create_subscription(Empty, "swept", lambda message: None, 10)
    timer = node.create_timer(1.0, lambda: None)
    service: Any = node.create_service(Trigger, "swept_service", lambda request, response: response)
    client: Any = node.create_client(Trigger, "swept_service")
    guard = node.create_guard_condition(lambda: None)
    assert swept == []
    removals: list[tuple[str, Callable[[], object]]] = [
        ("destroy_timer", lambda: node.destroy_timer(timer)),
        ("destroy_subscription", lambda: node.destroy_subscription(subscription)),
        ("destroy_service", lambda: node.destroy_service(service)),
        ("destroy_client", lambda: node.destroy_client(client)),
        ("destroy_guard_condition", lambda: node.destroy_guard_condition(guard)),
        ("destroy_publisher", lambda: node.destroy_publisher(publisher)),
    ]
    for name, remove in removals:
        before = len(swept)
        remove()
        assert len(swept) > before, f"{name} did not look for work of what it removed"
    before = len(swept)
    executor.remove_node(node)
    node.destroy_node()
    assert len(swept) > before


def test_a_node_destroyed_once_retired_is_off_the_graph_at_once(
    context: Context, executor: AsyncioExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A destroyed entity that a wait set still holds is destroyed when the wait set lets
    go of it, at its next rebuild. ``retire`` returned before that rebuild, so an unload
    was answered with the node still on the graph, and a node of the same name loaded
    next found the old one's ``/rosout`` publisher registered (the soak of
    ``test_unload_leaks`` saw the node left, in three CI legs of four). Rebuilds are
    spaced here by a million times their time (seconds at least): retire waives that
    for the rebuild it waits for, so it returns at once, the node released."""
    monkeypatch.setattr(_waitset, "_REBUILD_SPACED_FROM_NS", 0)
    monkeypatch.setattr(_waitset, "_REBUILD_SPACING", 1_000_000)
    peer = Node("graph_watcher", context=context)
    node = Node("retired", context=context)
    fired = threading.Event()
    node.create_timer(0.01, fired.set)
    node.create_service(Trigger, "retired_service", lambda request, response: response)
    executor.add_node(node)  # before the spin: its first rebuild holds the node
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        assert fired.wait(10.0), "the node's timer never fired: the wait set does not hold it"
        started = time.monotonic()
        stuck = asyncio.run_coroutine_threadsafe(executor.retire(node, timeout=1.0), executor.loop).result(10.0)
        took = time.monotonic() - started
        assert stuck == []
        node.destroy_node()
        assert "retired" not in peer.get_node_names()
        assert not _service_seen(peer, "/retired/retired_service")
        assert took < 1.0, f"retire took {took:.3f} s: the rebuild it waits for was spaced"
    finally:
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)
        peer.destroy_node()


def test_entities_created_one_by_one_cost_a_few_rebuilds_and_all_run(
    context: Context, executor: AsyncioExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After a rebuild, the next waits a multiple of its time: thirty timers created one
    by one (a big container's configure creates a node's entities so) are collected a
    few at a time, not one rebuild each; each still fires, and one destroyed meanwhile
    never does. Spaced here from any rebuild, by 200 times its time, so that a small
    wait set's rebuilds (well under a millisecond) are spaced as a big one's are."""
    monkeypatch.setattr(_waitset, "_REBUILD_SPACED_FROM_NS", 0)
    monkeypatch.setattr(_waitset, "_REBUILD_SPACING", 200)
    rebuilds: list[None] = []
    real = _waitset.EntityWaitSet._rebuild

    def counted(self: _waitset.EntityWaitSet) -> None:
        rebuilds.append(None)
        real(self)

    monkeypatch.setattr(_waitset.EntityWaitSet, "_rebuild", counted)
    node = Node("spaced", context=context)
    executor.add_node(node)
    fired: set[int] = set()
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        wait_until(lambda: len(rebuilds) >= 1, "the first rebuild")
        before = len(rebuilds)
        timers = []
        for index in range(30):
            timers.append(node.create_timer(0.01, lambda index=index: fired.add(index)))
            time.sleep(0.001)  # one by one, as a configure creates them
        node.destroy_timer(timers[-1])
        wait_until(lambda: fired >= set(range(29)), lambda: f"every timer to fire ({sorted(fired)})")
        # Two wait sets (hot and cold), each rebuilt for a few of the 31 changes.
        assert len(rebuilds) - before < 30, f"{len(rebuilds) - before} rebuilds for 31 changes"
        fired.clear()
        wait_until(lambda: fired >= set(range(29)), "every timer to fire again")
        assert 29 not in fired
    finally:
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)
        node.destroy_node()
