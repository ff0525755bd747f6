"""Intra-process communication: delivery in process, everything else over DDS, exactly once."""

from __future__ import annotations

import array
import itertools
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.client import Client
from rclpy.context import Context
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rclpy.subscription import Subscription
from sensor_msgs.msg import Image
from std_msgs.msg import Int64

from container import AsyncioExecutor, LifecycleNode, copy_message, enable_intra_process, hand_over
from container._config import parse_config
from container.intra import intra_process_enabled
from tests.component_support import ContainerClient, load_request, parameter
from tests.container_support import ContainerProcess

TIMEOUT = 10.0
#: A value no test sends: "everything sent before this has arrived".
MARK = -(2**62)


class Inbox:
    """What a subscription received, with a condition to wait on."""

    def __init__(self) -> None:
        self.messages: list[Any] = []
        self.infos: list[dict[str, Any]] = []
        self._changed = threading.Condition()

    def plain(self, message: Any, info: dict[str, Any]) -> None:
        with self._changed:
            self.messages.append(message)
            self.infos.append(info)
            self._changed.notify_all()

    async def coroutine(self, message: Any) -> None:
        with self._changed:
            self.messages.append(message)
            self._changed.notify_all()

    def data(self) -> list[Any]:
        with self._changed:
            return [message.data for message in self.messages]

    def wait_for_marks(self, count: int = 1, timeout: float = TIMEOUT) -> bool:
        """Wait for ``count`` marks (:data:`MARK`), then forget them: what is left came before."""
        def marks() -> int:
            return sum(message.data == MARK for message in self.messages)

        with self._changed:
            arrived = self._changed.wait_for(lambda: marks() >= count, timeout)
            kept = [index for index, message in enumerate(self.messages) if message.data != MARK]
            if len(self.infos) == len(self.messages):
                self.infos = [self.infos[index] for index in kept]
            self.messages = [self.messages[index] for index in kept]
            return arrived

    def wait_for(self, count: int, timeout: float = TIMEOUT) -> bool:
        with self._changed:
            return self._changed.wait_for(lambda: len(self.messages) >= count, timeout)


@pytest.fixture
def spin(executor: AsyncioExecutor) -> Iterator[Callable[[], None]]:
    """Start spinning ``executor`` on a thread (once its nodes are added)."""
    threads: list[threading.Thread] = []

    def start() -> None:
        thread = threading.Thread(target=executor.spin, daemon=True)
        thread.start()
        threads.append(thread)

    yield start
    executor.shutdown(timeout_sec=5.0)
    for thread in threads:
        thread.join(5.0)


#: The nodes of the running test, for graph queries.
_made: list[Node] = []


@pytest.fixture
def nodes(context: Context, executor: AsyncioExecutor) -> Iterator[Callable[..., Node]]:
    """Nodes on ``executor``: ``make(name, intra=True, **kwargs)``."""
    made = _made
    made.clear()

    def make(name: str, *, intra: bool = True, **kwargs: Any) -> Node:
        node = Node(name, context=context, **kwargs)
        if intra:
            enable_intra_process(node)
        executor.add_node(node)
        made.append(node)
        return node

    yield make
    for node in made:
        executor.remove_node(node)
        node.destroy_node()
    made.clear()


def subscribe(node: Node, *args: Any, **kwargs: Any) -> Subscription[Any]:
    """``node.create_subscription``; rclpy's annotation knows neither message info nor coroutines."""
    callback: Any = args[2]
    return node.create_subscription(args[0], args[1], callback, *args[3:], **kwargs)


def matched(publisher: Publisher[Any], count: int, *, publishers: int | None = 1) -> None:
    """Wait until ``count`` subscriptions matched, and the graph lists ``publishers`` on the topic.

    The graph may still list a publisher of an earlier test for a moment.
    """
    deadline = time.monotonic() + TIMEOUT
    node = _made[0]
    while publisher.get_subscription_count() < count or (
        publishers is not None and node.count_publishers(publisher.topic_name) != publishers
    ):
        assert time.monotonic() < deadline, f"{publisher.topic_name}: {count} subscriptions never matched"
        time.sleep(0.01)


def flush(publisher: Publisher[Any], *inboxes: Inbox) -> None:
    """Wait until everything ``publisher`` sent has reached ``inboxes``, any duplicate included.

    A mark sent after it, serialized (so over DDS only: never handed over in
    process), must arrive: DDS keeps one writer's order, and what was
    delivered in process was queued in the subscription's lane at publish,
    before the mark, which that lane runs after it.
    """
    publisher.publish(serialize_message(Int64(data=MARK)))
    for inbox in inboxes:
        assert inbox.wait_for_marks(), f"the mark on {publisher.topic_name} never arrived"


_markers = itertools.count()


def flush_unreached(
    make: Callable[..., Node], inbox: Inbox, topic: str, qos: QoSProfile | int, **node_kwargs: Any
) -> None:
    """Wait until anything handed to ``inbox``'s subscription in process so far has run.

    For a subscription the publisher under test must never reach (DDS would
    not match it either): a plain node's publisher that does match it sends
    a mark, which the subscription's lane runs after whatever a wrong
    in-process hand-over (made at publish, before) queued there.
    """
    marker = make(f"marker_{next(_markers)}", intra=False, **node_kwargs)
    publisher = marker.create_publisher(Int64, topic, qos)
    matched(publisher, 1, publishers=None)
    publisher.publish(Int64(data=MARK))
    assert inbox.wait_for_marks(), f"the mark on {publisher.topic_name} never arrived"


def test_in_process_and_dds_subscribers_each_get_every_message_once(
    nodes: Callable[..., Node], spin: Callable[[], None]
) -> None:
    talker, listener, other = nodes("talker"), nodes("listener"), nodes("other")
    plain_node = nodes("plain", intra=False)
    publisher = talker.create_publisher(Int64, "numbers", 100)
    in_process, in_process_async, over_dds = Inbox(), Inbox(), Inbox()
    subscribe(listener, Int64, "numbers", in_process.plain, 100)
    subscribe(other, Int64, "numbers", in_process_async.coroutine, 100)
    subscribe(plain_node, Int64, "numbers", over_dds.plain, 100)
    spin()
    matched(publisher, 3)
    sent = [Int64(data=value) for value in range(50)]
    for message in sent:
        hand_over(publisher, message)
    assert in_process.wait_for(50) and in_process_async.wait_for(50) and over_dds.wait_for(50)
    flush(publisher, in_process, in_process_async, over_dds)
    expected = list(range(50))
    assert in_process.data() == expected
    assert in_process_async.data() == expected
    assert over_dds.data() == expected
    # Handed over in process: the very objects; over DDS: deserialised copies.
    assert all(got is message for got, message in zip(in_process.messages, sent, strict=True))
    assert all(got is message for got, message in zip(in_process_async.messages, sent, strict=True))
    assert not any(got is message for got, message in zip(over_dds.messages, sent, strict=True))


def test_a_chain_of_in_process_deliveries_started_from_another_thread_keeps_going(
    executor: AsyncioExecutor, nodes: Callable[..., Node], spin: Callable[[], None]
) -> None:
    """A delivery made on the loop thread from inside a task (not from a
    dispatch) starts at the loop's next turn without any wake-up: the loop
    must not block in rcl while it waits."""
    a, b = nodes("intra_chain_a"), nodes("intra_chain_b")
    to_b = a.create_publisher(Int64, "intra_chain_to_b", 10)
    to_a = b.create_publisher(Int64, "intra_chain_to_a", 10)
    rounds = 500
    done = threading.Event()

    async def on_b(msg: Int64) -> None:
        to_a.publish(msg)

    async def on_a(msg: Int64) -> None:
        if msg.data >= rounds:
            done.set()
        else:
            to_b.publish(Int64(data=msg.data + 1))

    subscribe(b, Int64, "intra_chain_to_b", on_b, 10)
    subscribe(a, Int64, "intra_chain_to_a", on_a, 10)
    matched(to_b, 1)
    matched(to_a, 1)
    spin()
    # Once the loop sleeps in rcl, publish from this thread: the first
    # callback then runs in a task, and the rest follow from there.
    deadline = time.monotonic() + TIMEOUT
    while executor._dispatcher.busy_since is not None:
        assert time.monotonic() < deadline, "the loop never went to wait"
        time.sleep(0.01)
    to_b.publish(Int64(data=1))
    assert done.wait(TIMEOUT), "the chain stopped"


def test_node_without_the_option_gets_messages_over_dds_only(
    nodes: Callable[..., Node], spin: Callable[[], None]
) -> None:
    talker = nodes("talker", intra=False)
    listener = nodes("listener")
    publisher = talker.create_publisher(Int64, "numbers", 10)
    inbox = Inbox()
    subscribe(listener, Int64, "numbers", inbox.plain, 10)
    spin()
    matched(publisher, 1)
    sent = Int64(data=7)
    hand_over(publisher, sent)
    assert inbox.wait_for(1)
    flush(publisher, inbox)
    assert inbox.data() == [7]
    assert inbox.messages[0] is not sent
    assert not intra_process_enabled(talker)


def test_subscriber_never_sees_a_mutation_after_publish(
    nodes: Callable[..., Node], spin: Callable[[], None]
) -> None:
    camera, viewer, second = nodes("camera"), nodes("viewer"), nodes("second")
    publisher = camera.create_publisher(Image, "image", 10)
    first, other = Inbox(), Inbox()
    gate = threading.Event()

    def slow(message: Image, info: dict[str, Any]) -> None:
        gate.wait(TIMEOUT)  # the publisher mutates meanwhile
        first.plain(message, info)

    subscribe(viewer, Image, "image", slow, 10)
    subscribe(second, Image, "image", other.plain, 10)
    spin()
    matched(publisher, 2)
    image = Image(height=1, width=4, encoding="mono8", step=4)
    image.data = array.array("B", [1, 2, 3, 4])
    image.header.frame_id = "first"
    publisher.publish(image)
    # The common pattern: reuse the message, change it in place, publish again.
    image.data[0] = 99
    image.header.frame_id = "second"
    publisher.publish(image)
    image.data[1] = 77
    gate.set()
    assert first.wait_for(2) and other.wait_for(2)
    for inbox in (first, other):
        assert [bytes(m.data) for m in inbox.messages] == [bytes([1, 2, 3, 4]), bytes([99, 2, 3, 4])]
        assert [m.header.frame_id for m in inbox.messages] == ["first", "second"]
    # One copy per publish, shared read-only by every subscription in process.
    assert first.messages[0] is other.messages[0]
    assert first.messages[0] is not image


def test_keep_last_depth_bounds_what_waits(nodes: Callable[..., Node], spin: Callable[[], None]) -> None:
    talker, listener = nodes("talker"), nodes("listener")
    publisher = talker.create_publisher(Int64, "numbers", 100)
    inbox = Inbox()
    gate = threading.Event()
    started = threading.Event()

    def blocking(message: Int64, info: dict[str, Any]) -> None:
        started.set()
        gate.wait(TIMEOUT)
        inbox.plain(message, info)

    subscribe(listener,
        Int64, "numbers", blocking, 5, callback_group=MutuallyExclusiveCallbackGroup()
    )
    spin()
    matched(publisher, 1)
    publisher.publish(Int64(data=0))
    assert started.wait(TIMEOUT)
    for value in range(1, 20):
        publisher.publish(Int64(data=value))
    gate.set()
    assert inbox.wait_for(6)
    flush(publisher, inbox)
    # The one running, then the last five: keep-last 5, as DDS would keep.
    assert inbox.data() == [0, 15, 16, 17, 18, 19]


def test_remapped_and_namespaced_topics_meet_by_resolved_name(
    nodes: Callable[..., Node], spin: Callable[[], None]
) -> None:
    talker = nodes("talker", namespace="/robot", cli_args=["--ros-args", "-r", "chatter:=/shared/news"])
    listener = nodes("listener", namespace="/shared")
    bystander = nodes("bystander", namespace="/robot")
    publisher = talker.create_publisher(Int64, "chatter", 10)
    assert publisher.topic_name == "/shared/news"
    heard, not_heard = Inbox(), Inbox()
    subscribe(listener, Int64, "news", heard.plain, 10)
    subscribe(bystander, Int64, "chatter", not_heard.plain, 10)  # /robot/chatter
    spin()
    matched(publisher, 1)
    sent = Int64(data=1)
    hand_over(publisher, sent)
    assert heard.wait_for(1)
    flush(publisher, heard)
    flush_unreached(nodes, not_heard, "chatter", 10, namespace="/robot")
    assert heard.messages == [sent] and heard.messages[0] is sent
    assert not_heard.messages == []


def test_qos_mismatch_is_not_delivered(nodes: Callable[..., Node], spin: Callable[[], None]) -> None:
    talker = nodes("talker")
    best_effort = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
    publisher = talker.create_publisher(Int64, "numbers", best_effort)
    wants_reliable, wants_durable, compatible = Inbox(), Inbox(), Inbox()
    subscribe(nodes("reliable"), Int64, "numbers", wants_reliable.plain, 10)
    subscribe(nodes("durable"),
        Int64,
        "numbers",
        wants_durable.plain,
        QoSProfile(
            depth=10,
            reliability=ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        ),
    )
    subscribe(nodes("sensor"), Int64, "numbers", compatible.plain, best_effort)
    spin()
    matched(publisher, 1)
    for value in range(5):
        publisher.publish(Int64(data=value))
    assert compatible.wait_for(5)
    flush(publisher, compatible)
    assert compatible.data() == [0, 1, 2, 3, 4]
    # The marks' publishers reach the compatible subscription too: asked above already.
    flush_unreached(nodes, wants_reliable, "numbers", 10)
    flush_unreached(
        nodes,
        wants_durable,
        "numbers",
        QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.TRANSIENT_LOCAL),
    )
    assert wants_reliable.messages == [] and wants_durable.messages == []


def test_a_publisher_outside_the_domain_on_the_same_topic_never_causes_duplicates(
    nodes: Callable[..., Node], spin: Callable[[], None]
) -> None:
    ours = nodes("ours").create_publisher(Int64, "numbers", 100)
    theirs = nodes("theirs", intra=False).create_publisher(Int64, "numbers", 100)
    in_process, over_dds = Inbox(), Inbox()
    subscribe(nodes("listener"), Int64, "numbers", in_process.plain, 100)
    subscribe(nodes("plain", intra=False), Int64, "numbers", over_dds.plain, 100)
    spin()
    matched(ours, 2, publishers=2)
    matched(theirs, 2, publishers=2)
    for value in range(20):
        ours.publish(Int64(data=value))
        theirs.publish(Int64(data=100 + value))
    assert in_process.wait_for(40) and over_dds.wait_for(40)
    flush(ours, in_process, over_dds)
    flush(theirs, in_process, over_dds)
    for inbox in (in_process, over_dds):
        data = inbox.data()
        assert sorted(data) == sorted([*range(20), *range(100, 120)])
        assert [value for value in data if value < 100] == list(range(20))  # per-publisher order


def test_transient_local_late_joiner_gets_the_last_messages_once(
    nodes: Callable[..., Node], spin: Callable[[], None], executor: AsyncioExecutor
) -> None:
    latched = QoSProfile(depth=3, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publisher = nodes("map_server").create_publisher(Int64, "map", latched)
    spin()
    for value in range(5):
        publisher.publish(Int64(data=value))
    late = Inbox()
    subscribe(nodes("late"), Int64, "map", late.plain, latched)
    assert late.wait_for(3)
    publisher.publish(Int64(data=5))
    assert late.wait_for(4)
    flush(publisher, late)
    assert late.data() == [2, 3, 4, 5]


def test_message_info_is_filled_in(nodes: Callable[..., Node], spin: Callable[[], None]) -> None:
    publisher = nodes("talker").create_publisher(Int64, "numbers", 10)
    inbox = Inbox()
    subscribe(nodes("listener"), Int64, "numbers", inbox.plain, 10)
    spin()
    matched(publisher, 1)
    before = time.time_ns()
    publisher.publish(Int64(data=1))
    publisher.publish(Int64(data=2))
    assert inbox.wait_for(2)
    first, second = inbox.infos
    assert before <= first["source_timestamp"] <= second["source_timestamp"] <= time.time_ns()
    assert first["received_timestamp"] >= first["source_timestamp"]
    assert second["publication_sequence_number"] == first["publication_sequence_number"] + 1


def test_unloading_a_subscriber_or_publisher_mid_stream_leaves_no_delivery(
    nodes: Callable[..., Node], spin: Callable[[], None], executor: AsyncioExecutor
) -> None:
    import asyncio

    from rclpy.serialization import serialize_message

    from tests.waiting import wait_until

    talker, listener = nodes("talker"), nodes("listener")
    publisher = talker.create_publisher(Int64, "numbers", 10)
    inbox = Inbox()
    subscribe(listener, Int64, "numbers", inbox.plain, 10)
    spin()
    matched(publisher, 1)
    stop = threading.Event()
    errors: list[BaseException] = []
    published = [0]  # the next number of the stream

    def stream() -> None:
        while not stop.is_set():
            try:
                publisher.publish(Int64(data=published[0]))
            except BaseException as exc:
                errors.append(exc)
                return
            published[0] += 1
            time.sleep(0.001)  # pacing the stream, not waiting for anything

    streamer = threading.Thread(target=stream, daemon=True)
    streamer.start()
    assert inbox.wait_for(20)
    # What the container's unload does: retire the node (remove it, wait for
    # its callbacks already running), then destroy it.
    retiring = asyncio.run_coroutine_threadsafe(executor.retire(listener, timeout=TIMEOUT), executor.loop)
    assert retiring.result(TIMEOUT) == [], "a callback of the removed node kept running"
    listener.destroy_node()
    count = len(inbox.messages)
    # A new subscriber still gets the stream. Its ten messages, all published
    # after the removal and run by the same executor, mark "after": a callback
    # of the removed node would have run by then.
    fresh = Inbox()
    subscribe(nodes("fresh"), Int64, "numbers", fresh.plain, 10)
    assert fresh.wait_for(10)
    assert len(inbox.messages) == count, "a callback ran after its node was removed"
    # Then the publisher goes. Its last message is sent serialized, which goes
    # over DDS only (no in-process hand-over); DDS keeps one writer's order,
    # and in-process deliveries were queued at publish: once it arrives,
    # everything published before it, and any duplicate DDS carried, has.
    stop.set()
    streamer.join(TIMEOUT)
    matched(publisher, 1)  # the fresh subscription's DDS reader too
    last = published[0]
    publisher.publish(serialize_message(Int64(data=last)))
    wait_until(lambda: last in fresh.data(), "the publisher's last message, over DDS")
    talker.destroy_publisher(publisher)
    assert fresh.data()[-1] == last, "a message arrived after the publisher's last"
    assert errors == []
    data = fresh.data()
    assert data == sorted(set(data))  # in order, none twice

def test_copy_message_shares_nothing_mutable() -> None:
    image = Image(height=1, width=2, encoding="mono8", step=2)
    image.data = array.array("B", [1, 2])
    copied = copy_message(image)
    assert copied == image
    assert copied.data is not image.data and copied.header is not image.header
    with pytest.raises(TypeError):
        copy_message(object())


def test_lifecycle_node_keyword_enables_intra_process(context: Context) -> None:
    node = LifecycleNode("keyword", context=context, use_intra_process_comms=True)
    plain = LifecycleNode("no_keyword", context=context)
    try:
        assert intra_process_enabled(node)
        assert not intra_process_enabled(plain)
    finally:
        node.destroy_node()
        plain.destroy_node()


def test_config_takes_a_container_wide_default() -> None:
    config = parse_config(
        {
            "container": {"use_intra_process_comms": True},
            "nodes": [{"package": "p", "plugin": "p::T", "extra_arguments": [{"use_intra_process_comms": False}]}],
        }
    )
    assert config.use_intra_process_comms is True
    assert config.nodes[0].extra_arguments == {"use_intra_process_comms": False}


def change_state(node: Node, executor: AsyncioExecutor, target: str, transition: int) -> None:
    client: Client[Any, Any] = node.create_client(ChangeState, f"{target}/change_state")
    try:
        assert client.wait_for_service(timeout_sec=TIMEOUT)
        future = client.call_async(ChangeState.Request(transition=Transition(id=transition)))
        executor.spin_until_future_complete(future, timeout_sec=TIMEOUT)
        assert future.done()
        answer = future.result()
        assert answer is not None and answer.success
    finally:
        node.destroy_client(client)


OUTSIDE = textwrap.dedent(
    """
    import sys, time, rclpy
    from rclpy.node import Node
    from sensor_msgs.msg import Image
    rclpy.init()
    node = Node("outside_viewer")
    frames = []
    sub = node.create_subscription(Image, "/image", lambda m: frames.append(m.header.frame_id), 100)
    print("subscribed", flush=True)
    while not node.get_publishers_info_by_topic("/image") or sub.get_publisher_count() < 1:
        rclpy.spin_once(node, timeout_sec=0.05)
    print("matched", flush=True)
    deadline = time.monotonic() + 30
    while len(frames) < int(sys.argv[1]) and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.5)
    missing = sorted(set(range(int(sys.argv[1]))) - {int(f) for f in frames})
    print("outside got", len(frames), len(set(frames)), "missing", missing, flush=True)
    """
)


def test_container_nodes_exchange_images_in_process_while_another_process_sees_every_frame(
    run_container: Callable[..., ContainerProcess],
    see_plugin: Callable[..., None],
    client_node: Node,
    executor: AsyncioExecutor,
) -> None:
    see_plugin(distribution="intra-nodes", module="tests.intra_support")
    frames = 60
    container = run_container(
        textwrap.dedent(
            """
            container: {use_intra_process_comms: false}
            nodes:
              - {package: intra_nodes, plugin: Viewer, extra_arguments: [{use_intra_process_comms: true}]}
            """
        )
    )
    outside = subprocess.Popen(
        [sys.executable, "-c", OUTSIDE, str(frames)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert outside.stdout is not None
        assert outside.stdout.readline().strip() == "subscribed"
        client = ContainerClient(client_node, executor)
        response = client.load(
            load_request(
                "intra_nodes",
                "Camera",
                parameters=[
                    parameter("rate", 30.0), parameter("frames", frames), parameter("subscribers", 2)
                ],
                extra_arguments=[parameter("use_intra_process_comms", True)],
            )
        )
        assert response.success, response.error_message
        # Activate once the outside reader has matched the camera's writer
        # from its own side: DDS gives a volatile reader nothing written before.
        change_state(client_node, executor, "/camera", Transition.TRANSITION_CONFIGURE)
        assert outside.stdout.readline().strip() == "matched"
        change_state(client_node, executor, "/camera", Transition.TRANSITION_ACTIVATE)
        line = container.wait_for_line("viewer got", timeout=30)
        assert f"viewer got {frames} frames, {frames} distinct, {frames} handed over in process" in line
        output, _ = outside.communicate(timeout=40)
        assert f"outside got {frames} {frames}" in output
        assert outside.returncode == 0
    finally:
        if outside.poll() is None:
            outside.kill()
            outside.wait()
