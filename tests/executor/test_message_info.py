"""``(message, info)`` callbacks get exactly what rclpy's own executor gives them.

The keys differ by distribution (rclpy 9 added ``publisher_gid``), so the
test holds AsyncioExecutor against rclpy's SingleThreadedExecutor on the
same messages, whatever rclpy is installed, for each way a message reaches
a callback here: rclpy's take, the compiled take (plain and ``async def``
callbacks), and intra-process delivery.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import pytest
from rclpy.context import Context
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import String

from container import AsyncioExecutor, LifecycleNode
from container.executor import HAS_PUBLISHER_GID, publisher_gid

TIMEOUT = 10.0
COUNT = 3

Info = Mapping[str, Any]


class Inbox:
    """Infos received by one subscription, with an event once ``COUNT`` arrived."""

    def __init__(self) -> None:
        self.infos: list[Info] = []
        self.full = threading.Event()

    def add(self, message: String, info: Info) -> None:
        self.infos.append(info)
        if len(self.infos) >= COUNT:
            self.full.set()

    def plain(self) -> Callable[[String, Info], None]:
        return self.add

    def coroutine(self) -> Callable[[String, Info], Any]:
        async def received(message: String, info: Info) -> None:
            self.add(message, info)

        return received


@pytest.fixture
def spinning(context: Context) -> Iterator[Callable[[Executor], Executor]]:
    """Spin executors in threads of their own; shut down afterwards."""
    started: list[tuple[Executor, threading.Thread]] = []

    def spin(executor: Executor) -> Executor:
        thread = threading.Thread(target=executor.spin, daemon=True)
        thread.start()
        started.append((executor, thread))
        return executor

    yield spin
    for executor, thread in started:
        executor.shutdown(timeout_sec=2.0)
        thread.join(5.0)


def _publish_until(publish: Callable[[], None], inboxes: list[Inbox]) -> None:
    """Publish until every inbox is full; discovery makes the first messages miss."""
    for _ in range(int(TIMEOUT / 0.05)):
        if all(inbox.full.is_set() for inbox in inboxes):
            return
        publish()
        if all(inbox.full.wait(0.05) for inbox in inboxes):
            return
    pytest.fail(f"not every subscription got {COUNT} messages: {[len(i.infos) for i in inboxes]}")


def _by_sequence(infos: list[Info]) -> dict[int, Info]:
    return {info["publication_sequence_number"]: info for info in infos}


def test_message_info_has_rclpy_s_keys_and_values(
    context: Context, spinning: Callable[[Executor], Executor]
) -> None:
    reference, plain, coroutine = Inbox(), Inbox(), Inbox()
    theirs = Node("info_rclpy", context=context)
    ours = Node("info_ours", context=context)
    source = Node("info_source", context=context)
    # rclpy 7 types subscription callbacks as one-argument (as rclpy, ours take two).
    theirs.create_subscription(String, "info_topic", reference.plain(), 10)  # type: ignore[arg-type, unused-ignore]
    ours.create_subscription(String, "info_topic", plain.plain(), 10)  # type: ignore[arg-type, unused-ignore]
    ours.create_subscription(String, "info_topic", coroutine.coroutine(), 10)  # type: ignore[arg-type, unused-ignore]
    publisher = source.create_publisher(String, "info_topic", 10)
    single = SingleThreadedExecutor(context=context)
    single.add_node(theirs)
    asyncio_executor = AsyncioExecutor(context=context)
    asyncio_executor.add_node(ours)
    spinning(single)
    spinning(asyncio_executor)
    try:
        _publish_until(lambda: publisher.publish(String(data="x")), [reference, plain, coroutine])
    finally:
        for node in (theirs, ours, source):
            node.destroy_node()
    expected = _by_sequence(reference.infos)
    for inbox in (plain, coroutine):
        got = _by_sequence(inbox.infos)
        common = sorted(set(expected) & set(got))
        assert len(common) >= COUNT - 1, (sorted(expected), sorted(got))
        for sequence in common:
            mine, rclpys = got[sequence], expected[sequence]
            assert sorted(mine) == sorted(rclpys)  # the same keys
            for key, value in rclpys.items():
                if key == "received_timestamp":  # each reader's own
                    assert type(mine[key]) is type(value) and mine[key] > 0
                else:
                    assert mine[key] == value, key
    assert ("publisher_gid" in expected[common[0]]) == HAS_PUBLISHER_GID


def test_intra_process_info_has_rclpy_s_keys_and_the_publisher_s_gid(
    context: Context, spinning: Callable[[Executor], Executor]
) -> None:
    reference, intra = Inbox(), Inbox()
    theirs = Node("intra_info_rclpy", context=context)
    sink = LifecycleNode("intra_info_sink", context=context, use_intra_process_comms=True)
    source = LifecycleNode("intra_info_source", context=context, use_intra_process_comms=True)
    # rclpy 7 types subscription callbacks as one-argument (as rclpy, ours take two).
    theirs.create_subscription(String, "intra_info_topic", reference.plain(), 10)  # type: ignore[arg-type, unused-ignore]
    sink.create_subscription(String, "intra_info_topic", intra.plain(), 10)  # type: ignore[arg-type, unused-ignore]
    publisher = source.create_publisher(String, "intra_info_topic", 10, managed=False)
    single = SingleThreadedExecutor(context=context)
    single.add_node(theirs)
    asyncio_executor = AsyncioExecutor(context=context)
    for node in (sink, source):
        asyncio_executor.add_node(node)
    spinning(single)
    spinning(asyncio_executor)
    try:
        _publish_until(lambda: publisher.publish(String(data="x")), [reference, intra])
        gid = publisher_gid(publisher, node=source)
    finally:
        for each in (theirs, sink, source):
            each.destroy_node()
    rclpys, mine = reference.infos[-1], intra.infos[-1]
    assert mine["received_timestamp"] == mine["source_timestamp"]  # delivered in process, not by DDS
    assert sorted(mine) == sorted(rclpys)
    if HAS_PUBLISHER_GID:
        assert gid is not None and mine["publisher_gid"] == gid == rclpys["publisher_gid"]
    else:
        assert gid is None
