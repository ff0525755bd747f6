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
from collections.abc import Iterator
from typing import Any

import pytest
from rclpy.context import Context
from rclpy.node import Node
from std_srvs.srv import Trigger

from container import AsyncioExecutor
from container.executor import _entries, _waitset
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
