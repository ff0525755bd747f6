"""The fault matrix: every way a plugin can misbehave, beside a healthy talker.

A node of ``tests_faults`` raises, calls ``sys.exit()``, blocks (a busy
loop, ``time.sleep``, awaiting forever) or leaks a non-daemon thread, in its
constructor, in each transition, or in a timer, subscription or service
callback, with plain and ``async def`` callbacks: 93 cells, all in one
container beside a talker publishing at 5 Hz. For every cell the container
survives, the talker keeps its rate, the faulty node ends in the state the
containment guide's table gives (``docs/guide/containment.md``), and
unloading it works.

"Forever" lasts :data:`FOREVER` seconds here, longer than every timeout the
container applies (:data:`TIMEOUT`), so that one container can run every
cell in turn.

On one CPU, this process and the container it starts both::

    taskset -c 0 .venv/bin/python -m pytest tests/test_fault_matrix.py

Twice in a row here, all 93 cells passed (97-106 s), the talker's largest
gap 0.41 s (an ``async def`` busy loop in ``cleanup``), under its bound.
"""

from __future__ import annotations

import itertools
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import rclpy
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.client import Client
from rclpy.context import Context
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import try_shutdown
from std_msgs.msg import String
from std_srvs.srv import Trigger

from container import AsyncioExecutor
from tests.component_support import (
    IMPORT_ROOT,
    ContainerClient,
    install_test_plugin,
    load_request,
    parameter,
)
from tests.container_support import ContainerProcess
from tests.fault_plugin import TRANSITIONS, WHERES
from tests.waiting import wait_until

# 93 cells, one container process: about 90 s.
pytestmark = pytest.mark.slow

#: Every timeout the container and the faulty node apply, in seconds.
TIMEOUT = 0.5
#: How long a blocking fault blocks: beyond every timeout.
FOREVER = 2.0
#: The talker's period. It never misses three in a row: no gap between its
#: publications reaches four periods. A plain callback busy-looping in Python
#: competes with it for the GIL and the CPU: gaps of 0.25-0.42 s beside one
#: here (the code before the services change alike), 0.61 s once in CI.
PERIOD = 0.2

CONTAINER = f"""
container: {{unload_timeout: {TIMEOUT}, load_timeout: {TIMEOUT}, shutdown_timeout: 2.0}}
nodes:
  - {{package: lifecycle_container, plugin: lifecycle_container::Talker, name: talker,
     parameters: [{{rate: {1 / PERIOD}}}], autostart: true}}
"""

PLAIN_FAULTS = ("raise", "exit", "busy", "sleep", "thread")
ASYNC_FAULTS = ("raise", "exit", "busy", "sleep", "await", "thread")
CELLS = [("plain", fault, where) for fault in PLAIN_FAULTS for where in WHERES] + [
    ("async", fault, where) for fault in ASYNC_FAULTS for where in WHERES if where != "constructor"
]

#: Where each transition starts, and how to get there from unconfigured.
START = {"configure": "unconfigured", "activate": "inactive", "deactivate": "active",
         "cleanup": "inactive", "shutdown": "unconfigured"}  # fmt: skip
GOAL = {"configure": "inactive", "activate": "active", "deactivate": "inactive",
        "cleanup": "unconfigured", "shutdown": "finalized"}  # fmt: skip
BEFORE = {"configure": [], "activate": ["configure"], "deactivate": ["configure", "activate"],
          "cleanup": ["configure"], "shutdown": []}  # fmt: skip
IDS = {"configure": Transition.TRANSITION_CONFIGURE, "activate": Transition.TRANSITION_ACTIVATE,
       "deactivate": Transition.TRANSITION_DEACTIVATE, "cleanup": Transition.TRANSITION_CLEANUP,
       "shutdown": Transition.TRANSITION_UNCONFIGURED_SHUTDOWN}  # fmt: skip


def expected_state(style: str, fault: str, where: str) -> str:
    """The state the containment guide's table promises after the fault ("refused": never loaded)."""
    if where == "constructor":
        return "unconfigured" if fault == "thread" else "refused"
    if where in TRANSITIONS:
        if fault == "thread":
            return GOAL[where]
        if fault in ("raise", "exit"):
            return "unconfigured"  # error processing; on_error succeeds
        # Timed out: the transition fails, back to its start state; rcl's
        # shutdown ends in finalized whether it succeeds or fails.
        return "finalized" if where == "shutdown" else START[where]
    return "unconfigured" if fault in ("raise", "exit") else "active"


def blocks_the_loop(style: str, fault: str) -> bool:
    return style == "async" and fault in ("busy", "sleep")


@dataclass
class Rig:
    """The container, a client and what the talker published."""

    container: ContainerProcess
    client: ContainerClient
    stamps: list[float]
    lock: threading.Lock


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    site = install_test_plugin(
        tmp_path_factory.mktemp("site"), distribution="tests-faults", module="tests.fault_plugin"
    )
    saved = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join([str(site), str(IMPORT_ROOT)])
    path = Path(tmp_path_factory.mktemp("matrix")) / "container.yaml"
    path.write_text(CONTAINER, encoding="utf-8")
    container = ContainerProcess(path)
    if saved is None:
        del os.environ["PYTHONPATH"]
    else:
        os.environ["PYTHONPATH"] = saved
    context = Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    executor = AsyncioExecutor(context=context)
    node = Node("matrix_client", context=context)
    executor.add_node(node)
    stamps: list[float] = []
    lock = threading.Lock()

    def heard(message: String, info: Any) -> None:
        # The talker's own publication time: our spinning does not move it.
        with lock:
            stamps.append(info["source_timestamp"] / 1e9)

    # rclpy 7 types subscription callbacks as one-argument; rclpy hands this one the message info too.
    node.create_subscription(String, "/chatter", heard, QoSProfile(depth=1000))  # type: ignore[arg-type, unused-ignore]
    try:
        container.wait_for_line("ready with")
        rig = Rig(container, ContainerClient(node, executor), stamps, lock)
        wait_until(lambda: len(stamps) >= 2, "the talker's first messages", timeout=20.0, executor=executor)
        yield rig
    finally:
        container.close()
        executor.shutdown(timeout_sec=5.0)
        node.destroy_node()
        try_shutdown(context=context)


def call(rig: Rig, srv_type: Any, name: str, request: Any, *, timeout: float = 10.0) -> Any:
    client: Client[Any, Any] = rig.client.node.create_client(srv_type, name)
    try:
        assert client.wait_for_service(timeout_sec=10.0), f"{name} never appeared"
        return rig.client.call(client, request, timeout=timeout)
    finally:
        rig.client.node.destroy_client(client)


def state(rig: Rig, name: str) -> str:
    return str(call(rig, GetState, f"/{name}/get_state", GetState.Request()).current_state.label)


PRIMARY = ("unconfigured", "inactive", "active", "finalized")


def settled_state(rig: Rig, name: str, *, timeout: float = 10.0) -> str:
    """The node's state once no transition is in progress (a late one may still be ending)."""
    deadline = time.monotonic() + timeout
    while (now := state(rig, name)) not in PRIMARY and time.monotonic() < deadline:
        rig.client.executor.spin_once(timeout_sec=0.05)
    return now


def change(rig: Rig, name: str, label: str) -> bool:
    request = ChangeState.Request(transition=Transition(id=IDS[label], label=label))
    # Answered within transition_timeout (+1 s) whatever the callback does.
    return bool(call(rig, ChangeState, f"/{name}/change_state", request, timeout=TIMEOUT + 5.0).success)


def trigger(rig: Rig, name: str, where: str, *, struck: str, mark: int) -> None:
    """Make the node's subscription or service callback run (its timer runs by itself)."""
    node = rig.client.node
    if where == "subscription":
        publisher = node.create_publisher(String, f"/{name}/poke", 10)
        deadline = time.monotonic() + 10.0
        # Published until the callback ran: the first ones may go out
        # before the subscription has matched.
        while not any(struck in line for line in rig.container.lines[mark:]) and time.monotonic() < deadline:
            publisher.publish(String(data="poke"))
            rig.client.executor.spin_once(timeout_sec=0.05)
        node.destroy_publisher(publisher)
    elif where == "service":
        poke: Client[Any, Any] = node.create_client(Trigger, f"/{name}/poke")
        assert poke.wait_for_service(timeout_sec=10.0)
        poke.call_async(Trigger.Request())  # may never be answered: the callback is the fault


def largest_gap(rig: Rig, since: float, until: float) -> float:
    """The talker's largest gap between publications over ``[since, until]``, edges included."""

    def after_until() -> bool:
        with rig.lock:
            return bool(rig.stamps) and rig.stamps[-1] > until

    # Messages wait in the subscription's history until the client spins.
    wait_until(after_until, "a talker message after the window", executor=rig.client.executor)
    with rig.lock:
        stamps = sorted(rig.stamps)
    first = max((i for i, s in enumerate(stamps) if s < since), default=0)
    last = min(i for i, s in enumerate(stamps) if s > until)
    window = stamps[first : last + 1]
    return max(b - a for a, b in itertools.pairwise(window))


@pytest.mark.parametrize(("style", "fault", "where"), CELLS, ids=["-".join(cell) for cell in CELLS])
def test_fault_cell(rig: Rig, style: str, fault: str, where: str) -> None:
    name = f"{style}_{fault}_{where}"
    started = time.time()
    mark = len(rig.container.lines)
    plugin = "tests_faults::FaultyAsync" if style == "async" else "tests_faults::Faulty"
    request = load_request(
        "tests_faults",
        plugin,
        name=name,
        parameters=[
            parameter("fault", fault),
            parameter("where", where),
            parameter("forever", FOREVER),
            parameter("transition_timeout", TIMEOUT),
        ],
    )
    loaded = rig.client.load(request)
    expected = expected_state(style, fault, where)
    if expected == "refused":
        assert not loaded.success
        final = "refused"
    else:
        assert loaded.success, loaded.error_message
        if where in TRANSITIONS:
            for step in BEFORE[where]:
                assert change(rig, name, step)
            assert change(rig, name, where) == (fault == "thread")
        elif where != "constructor":
            assert change(rig, name, "configure") and change(rig, name, "activate")
            trigger(rig, name, where, struck=f"misbehaving: {fault} in {where}", mark=mark)
        if where != "constructor":
            rig.container.wait_for_line(f"misbehaving: {fault} in {where}", start=mark)
        if blocks_the_loop(style, fault):
            rig.container.wait_for_line("event loop stuck", start=mark)
            rig.container.wait_for_line("event loop free again", start=mark, timeout=FOREVER + 10.0)
        if fault in ("raise", "exit") and where not in TRANSITIONS:
            rig.container.wait_for_line("Error processing done", start=mark)
        final = settled_state(rig, name)
        unloaded = rig.client.unload(loaded.unique_id)
        assert unloaded.success
        assert name not in [full.lstrip("/") for _, full in rig.client.list()]
    assert rig.container.process.poll() is None, "the container died"
    assert final == expected, f"{final}\n" + "\n".join(rig.container.lines[mark:])
    assert largest_gap(rig, started, time.time()) < 4 * PERIOD
