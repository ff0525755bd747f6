"""Containment: what one plugin or one peer does never takes the container down.

Each test runs a real ``container run`` beside the test's own client node and
drives it as a careless plugin or a hostile peer would.
"""

from __future__ import annotations

import itertools
import re
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

import pytest
from composition_interfaces.srv import LoadNode
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.client import Client
from rclpy.context import Context
from rclpy.node import Node
from std_msgs.msg import Int64, String

from container import AsyncioExecutor
from tests.component_support import (
    ContainerClient,
    graph_nodes,
    load_request,
    parameter,
)
from tests.container_support import ContainerProcess
from tests.waiting import wait_until

#: Short timeouts, so that a cut-short transition shows within a test.
CONTAINER = "container:\n  name: ComponentManager\n  unload_timeout: 1.0\n"


@pytest.fixture
def container(run_container: Callable[..., ContainerProcess], see_plugin: Callable[..., None]) -> ContainerProcess:
    """An empty container that also sees the ``tests-faults`` plugin."""
    see_plugin(distribution="tests-faults", module="tests.fault_plugin")
    return run_container(CONTAINER)


@pytest.fixture
def client(container: ContainerProcess, client_node: Node, executor: AsyncioExecutor) -> ContainerClient:
    return ContainerClient(client_node, executor, process=container)


def faulty(fault: str, where: str, *, style: str = "plain", name: str = "faulty") -> LoadNode.Request:
    plugin = "tests_faults::FaultyAsync" if style == "async" else "tests_faults::Faulty"
    return load_request(
        "tests_faults",
        plugin,
        name=name,
        parameters=[parameter("fault", fault), parameter("where", where)],
    )


def state_of(client: ContainerClient, name: str) -> str:
    getter: Client[Any, Any] = client.node.create_client(GetState, f"{name}/get_state")
    try:
        assert getter.wait_for_service(timeout_sec=10.0)
        return str(client.call(getter, GetState.Request()).current_state.label)
    finally:
        client.node.destroy_client(getter)


# A container process and a transition left hanging.
@pytest.mark.slow
@pytest.mark.parametrize("style", ["plain", "async"])
def test_unload_during_a_transition_cancels_it_and_answers_everyone(
    container: ContainerProcess, client: ContainerClient, executor: AsyncioExecutor, style: str
) -> None:
    loaded = client.load(faulty("await" if style == "async" else "sleep", "configure", style=style))
    assert loaded.success, loaded.error_message
    changer: Client[Any, Any] = client.node.create_client(ChangeState, "/faulty/change_state")
    assert changer.wait_for_service(timeout_sec=10.0)
    pending = changer.call_async(ChangeState.Request(transition=Transition(id=Transition.TRANSITION_CONFIGURE)))
    wait_until(
        lambda: state_of(client, "/faulty") == "configuring",
        "/faulty in configuring",
        timeout=20.0,
        executor=executor,
    )
    unloaded = client.unload(loaded.unique_id)
    assert unloaded.success
    assert "cancelled" in unloaded.error_message
    executor.spin_until_future_complete(pending, timeout_sec=10.0)
    assert pending.done(), f"the caller was left waiting; the container said:\n{container.output()}"
    answer = pending.result()
    assert answer is not None and not answer.success, container.output()
    assert client.list() == []
    # The process lives on, and serves a new node under the same name.
    again = client.load(faulty("raise", "timer", name="faulty"))
    assert again.success, again.error_message
    assert container.process.poll() is None


# A container process and a transition left hanging.
@pytest.mark.slow
def test_sigint_during_a_transition_exits_cleanly(container: ContainerProcess, client: ContainerClient) -> None:
    loaded = client.load(faulty("await", "configure", style="async"))
    assert loaded.success
    changer: Client[Any, Any] = client.node.create_client(ChangeState, "/faulty/change_state")
    assert changer.wait_for_service(timeout_sec=10.0)
    changer.call_async(ChangeState.Request(transition=Transition(id=Transition.TRANSITION_CONFIGURE)))
    wait_until(
        lambda: state_of(client, "/faulty") == "configuring",
        "/faulty in configuring",
        timeout=20.0,
        executor=client.executor,
    )
    code = container.stop(sig=signal.SIGINT)
    output = "\n".join(container.lines)
    assert code == 0, output  # 139 (SIGSEGV) before
    assert "cancelled" in output


@pytest.mark.parametrize("style", ["plain", "async"])
def test_sys_exit_in_a_callback_sends_only_that_node_through_error_processing(
    container: ContainerProcess, client: ContainerClient, style: str
) -> None:
    healthy = client.load(load_request(name="talker"))
    loaded = client.load(faulty("exit", "timer", style=style))
    assert healthy.success and loaded.success
    changer: Client[Any, Any] = client.node.create_client(ChangeState, "/faulty/change_state")
    assert changer.wait_for_service(timeout_sec=10.0)
    for transition in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
        assert client.call(changer, ChangeState.Request(transition=Transition(id=transition))).success
    container.wait_for_line("raised SystemExit")
    container.wait_for_line("Error processing done: the node is unconfigured")
    assert state_of(client, "/faulty") == "unconfigured"
    assert container.process.poll() is None
    assert client.unload(loaded.unique_id).success
    assert [name for _, name in client.list()] == ["/talker"]


@pytest.mark.parametrize("fault", ["exit", "raise"])
def test_a_constructor_that_fails_leaves_nothing_behind(
    container: ContainerProcess, client: ContainerClient, executor: AsyncioExecutor, fault: str
) -> None:
    refused = client.load(faulty(fault, "constructor"))
    assert not refused.success
    assert "Component constructor threw an exception" in refused.error_message
    # A parameter of the wrong type: refused by the constructor half way.
    wrong = client.load(load_request(name="talker", parameters=[parameter("rate", 5)]))
    assert not wrong.success
    wait_until(
        lambda: not {"/faulty", "/talker"} & graph_nodes(client.node),
        "/faulty and /talker gone from the graph",
        timeout=20.0,
        executor=executor,
    )
    right = client.load(load_request(name="talker", parameters=[parameter("rate", 5.0)]))
    assert right.success
    wait_until(lambda: "/talker" in graph_nodes(client.node), "/talker in the graph", timeout=20.0, executor=executor)
    names = [name for name, _ in client.node.get_node_names_and_namespaces()]
    assert names.count("talker") == 1
    assert container.process.poll() is None


@pytest.mark.usefixtures("fault_site")
def test_a_blocking_constructor_is_refused_in_time_and_blocks_no_one(
    run_container: Callable[..., ContainerProcess], client_node: Node, executor: AsyncioExecutor
) -> None:
    container = run_container("container:\n  load_timeout: 1.0\n")
    client = ContainerClient(client_node, executor)
    pending = client.load_client.call_async(faulty("busy", "constructor"))
    # While the constructor spins, the container still answers.
    assert client.list() == []
    executor.spin_until_future_complete(pending, timeout_sec=20.0)
    assert pending.done()
    answer = pending.result()
    assert answer is not None
    assert not answer.success
    assert "did not return within 1 s" in answer.error_message
    assert container.process.poll() is None


def test_request_strings_are_clipped_in_logs_and_answers(
    container: ContainerProcess, client: ContainerClient
) -> None:
    huge = "x" * 1_000_000
    refused = client.load(load_request(huge, f"{huge}::Node"))
    assert not refused.success
    assert len(refused.error_message) < 1000
    line = container.wait_for_line("Refused to load")
    assert len(line) < 1000 and "characters)" in line


#: A megabyte in each field of a LoadNode request that is echoed, and the words
#: around it in the answer (None: loaded, and echoed in the log only).
HUGE = "x" * 1_000_000
ECHOES = {
    "node name": (load_request(name=HUGE), "Invalid node name 'xxx"),
    "namespace": (load_request(name="n1", namespace=HUGE), "Invalid namespace '/xxx"),
    "remap rule": (load_request(name="n2", remap_rules=[HUGE]), "Invalid remap rule 'xxx"),
    "parameter value": (
        load_request(name="n3", parameters=[parameter("rate", HUGE)]),
        "Component constructor threw an exception",
    ),
    "parameter name": (  # told at configure
        load_request(name="n4", parameters=[parameter(HUGE, 1)], extra_arguments=[parameter("autostart", True)]),
        None,
    ),
    "extra argument": (load_request(name="n5", extra_arguments=[parameter(HUGE, 1)]), None),
}


@pytest.mark.parametrize("field", list(ECHOES))
def test_a_megabyte_in_any_field_is_echoed_clipped_with_its_length(
    container: ContainerProcess, client: ContainerClient, field: str
) -> None:
    request, refusal = ECHOES[field]
    answer = client.load(request)
    if refusal is None:
        assert answer.success, answer.error_message
        # Told in a warning: "Unknown parameter 'xxx…' (1000000 characters) ignored", "Extra component argument ...".
        container.wait_for_line("(1000000 characters)")
    else:
        assert not answer.success
        assert refusal in answer.error_message and len(answer.error_message) < 1000, answer.error_message[:1000]
        container.wait_for_line("Refused to load")
    assert max(len(line) for line in container.lines) < 1000


@pytest.mark.parametrize("how", ["remove_node", "destroy_node"])
def test_removed_node_starts_none_of_its_queued_callbacks(
    context: Context, executor: AsyncioExecutor, how: str
) -> None:
    listener = Node("removal_listener", context=context)
    talker = Node("removal_talker", context=context)
    started: list[int] = []
    release = threading.Event()
    first = threading.Event()

    def slow(message: Int64) -> None:
        started.append(message.data)
        first.set()
        release.wait(10.0)

    listener.create_subscription(Int64, "removal", slow, 10)
    sentinel = threading.Event()
    talker.create_subscription(Int64, "removal", lambda _: sentinel.set() if release.is_set() else None, 10)
    publisher = talker.create_publisher(Int64, "removal", 10)
    executor.add_node(listener)
    executor.add_node(talker)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        # Discovery offers no event to wait on (rclpy#929).
        wait_until(lambda: publisher.get_subscription_count() >= 2, "both subscriptions matched")
        for number in range(10):
            publisher.publish(Int64(data=number))
        assert first.wait(10.0)
        if how == "remove_node":
            executor.remove_node(listener)
        else:
            listener.destroy_node()  # rclpy's executors start none of its queued callbacks either
        release.set()
        # A later message, through the same executor, marks "after": by the
        # time it arrives, anything queued before would have started.
        publisher.publish(Int64(data=99))
        assert sentinel.wait(10.0)
        assert started == [0]
    finally:
        release.set()
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)
        if how == "remove_node":
            listener.destroy_node()
        talker.destroy_node()


@pytest.fixture
def fault_site(see_plugin: Callable[..., None]) -> None:
    """Child processes see the ``tests-faults`` plugin."""
    see_plugin(distribution="tests-faults", module="tests.fault_plugin")


@pytest.mark.usefixtures("fault_site")
def test_threads_a_plugin_leaves_behind_are_named_and_do_not_hold_the_exit(
    run_container: Callable[..., ContainerProcess],
) -> None:
    container = run_container(
        "nodes:\n"
        "  - {package: tests_faults, plugin: tests_faults::Faulty, name: leaky,\n"
        "     parameters: [{fault: thread, where: constructor}]}\n"
    )
    started = time.monotonic()
    code = container.stop(sig=signal.SIGINT, timeout=10.0)
    output = "\n".join(container.lines)
    assert code != 0, output
    # The exit summary is a ROS log line too (the container node is gone: the process's name).
    summary = r"^\[ERROR\] \[\d+\.\d+\] \[container\]: threads left behind: leaked-by-constructor$"
    assert re.search(summary, output, re.MULTILINE), output
    assert time.monotonic() - started < 5.0 + 2.0  # the shutdown timeout, plus 2 s


@pytest.mark.usefixtures("fault_site")
def test_a_third_sigint_exits_at_once_without_a_traceback(
    run_container: Callable[..., ContainerProcess],
) -> None:
    container = run_container(
        "container: {unload_timeout: 60.0}\n"
        "nodes:\n"
        "  - {package: tests_faults, plugin: tests_faults::FaultyAsync, name: stubborn, autostart: true,\n"
        "     parameters: [{fault: await, where: deactivate, transition_timeout: 60.0}]}\n"
    )
    container.process.send_signal(signal.SIGINT)
    container.wait_for_line("Shutting down")
    # The second is absorbed (launch forwards one more to Ctrl-C's own).
    container.process.send_signal(signal.SIGINT)
    container.wait_for_line("SIGINT again: already shutting down")
    started = time.monotonic()
    code = container.stop(sig=signal.SIGINT, timeout=5.0)
    output = "\n".join(container.lines)
    assert code == 130, output
    assert time.monotonic() - started < 2.0
    assert "Traceback" not in output


def test_every_change_state_request_is_answered_while_a_transition_runs(
    container: ContainerProcess, client: ContainerClient, context: Context
) -> None:
    """Twenty peers ask at once during a slow configure; the busy lane once kept only the last ten.

    All twenty are sent together: the node's services keep every request
    (rcl's own kept 10, and this test paced its peers 15 ms apart then), and
    pace their answers, each of which every peer receives.
    """
    assert client.load(faulty("slow", "configure", style="async")).success
    peers = Node("containment_peers", context=context)
    burst = AsyncioExecutor(context=context)
    burst.add_node(peers)
    spinner = threading.Thread(target=burst.spin, daemon=True)
    spinner.start()
    try:
        changers: list[Client[Any, Any]] = [peers.create_client(ChangeState, "/faulty/change_state") for _ in range(20)]
        assert all(changer.wait_for_service(timeout_sec=10.0) for changer in changers)
        request = ChangeState.Request(transition=Transition(id=Transition.TRANSITION_CONFIGURE))
        answered = threading.Semaphore(0)
        pending = []
        for changer in changers:
            future = changer.call_async(request)
            future.add_done_callback(lambda _: answered.release())
            pending.append(future)
        deadline = time.monotonic() + 20.0
        for _ in pending:
            answered.acquire(timeout=max(0.0, deadline - time.monotonic()))
        assert "".join("x" if future.done() else "." for future in pending) == "x" * 20, container.output()
        answers = [future.result() for future in pending]
        assert sum(answer is not None and answer.success for answer in answers) == 1
    finally:
        burst.shutdown(timeout_sec=5.0)
        spinner.join(5.0)
        peers.destroy_node()


def test_a_heartbeat_period_below_10_ms_is_refused(container: ContainerProcess, client: ContainerClient) -> None:
    refused = client.load(load_request(name="talker", parameters=[parameter("bond_heartbeat_period", 1e-9)]))
    assert not refused.success
    assert "at least 0.01 s" in refused.error_message
    off = client.load(load_request(name="talker", parameters=[parameter("bond_heartbeat_period", 0.0)]))
    assert off.success, off.error_message


STUCK_LOOP = """
container: {shutdown_timeout: 1.0, watchdog_threshold: 0.3}
nodes:
  - {package: lifecycle_container, plugin: lifecycle_container::Talker, name: talker,
     parameters: [{rate: 10.0}], autostart: true}
  - {package: tests_faults, plugin: tests_faults::FaultyAsync, name: hog, autostart: true,
     parameters: [{fault: busy, where: timer}]}
"""


# A container process whose loop stays stuck for seconds.
@pytest.mark.slow
@pytest.mark.usefixtures("fault_site")
def test_a_loop_stuck_in_an_async_callback_stops_neither_plain_nodes_nor_the_exit(
    run_container: Callable[..., ContainerProcess], client_node: Node, executor: AsyncioExecutor
) -> None:
    container = run_container(STUCK_LOOP)
    heard: list[float] = []
    client_node.create_subscription(String, "/chatter", lambda _: heard.append(time.monotonic()), 10)
    statuses: list[DiagnosticStatus] = []

    def diagnosed(message: DiagnosticArray) -> None:
        statuses.extend(message.status)

    client_node.create_subscription(DiagnosticArray, "/diagnostics", diagnosed, 10)
    report = container.wait_for_line("event loop stuck for")
    assert "hog" in report and "_tick" in report
    # Reported at the file's threshold (0.3 s), not the default 1 s.
    assert float(report.split("event loop stuck for ")[1].split(" s")[0]) < 1.0, report
    # The plain talker keeps its rate, the diagnostics say what is stuck,
    # and the container still answers.
    wait_until(lambda: len(heard) >= 20, "20 messages on /chatter", executor=executor)
    assert max(b - a for a, b in itertools.pairwise(heard[-20:])) < 3 * 0.1
    wait_until(
        lambda: any(s.level == DiagnosticStatus.ERROR and "stuck" in s.message for s in statuses),
        "an error status saying what is stuck",
        timeout=20.0,
        executor=executor,
    )
    assert [name for _, name in ContainerClient(client_node, executor).list()] == ["/talker", "/hog"]
    started = time.monotonic()
    code = container.stop(sig=signal.SIGINT, timeout=10.0)
    output = "\n".join(container.lines)
    assert code != 0, output
    assert time.monotonic() - started < 1.0 + 2.0
    assert "exiting without a clean shutdown" in output
