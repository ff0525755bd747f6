"""The lifecycle manager: ordering, rollback, retries, heartbeats across processes."""

from __future__ import annotations

import asyncio
import contextlib
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from rclpy.client import Client
from rclpy.context import Context
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from std_srvs.srv import Trigger

from container import AsyncioExecutor, ConfigError
from container.lifecycle._manager import STARTUP, LifecycleManager, ManagerSettings
from container.lifecycle._node import LifecycleNode
from tests.container_support import ContainerProcess
from tests.lifecycle_support import TransitionLog, run
from tests.process_support import log_time

nav2_srv = pytest.importorskip("nav2_msgs.srv")
pytest.importorskip("bond.msg")
ManageLifecycleNodes = nav2_srv.ManageLifecycleNodes
Command = ManageLifecycleNodes.Request

PRIMARY = {"unconfigured", "inactive", "active", "finalized"}
SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE


class Managed(LifecycleNode):
    """A node whose configure fails ``failures`` times before it succeeds."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.failures = 0

    async def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        await asyncio.sleep(0)
        if self.failures:
            self.failures -= 1
            return FAILURE
        return SUCCESS


@pytest.fixture
def system(
    context: Context, executor: AsyncioExecutor
) -> Iterator[Callable[..., tuple[dict[str, Managed], LifecycleManager, TransitionLog, Node]]]:
    """Managed nodes /a, /b, /c, a manager for them, and an observer of their events."""
    nodes: list[Node] = []

    def build(**parameters: Any) -> tuple[dict[str, Managed], LifecycleManager, TransitionLog, Node]:
        managed = {name: Managed(name, context=context) for name in ("a", "b", "c")}
        settings = ManagerSettings.from_mapping(
            {"node_names": ["/a", "/b", "/c"], "bond_timeout": 0.0, **parameters}
        )
        manager = LifecycleManager(settings, context=context)
        observer = Node("observer", context=context)
        nodes.extend([*managed.values(), manager, observer])
        for node in nodes:
            executor.add_node(node)
        log = TransitionLog(observer, ["/a", "/b", "/c"])
        log.wait_matched()
        return managed, manager, log, observer

    yield build
    for node in nodes:
        executor.remove_node(node)
        node.destroy_node()


async def call_manager(observer: Node, command: int) -> tuple[bool, Trigger.Response]:
    manage: Client[Any, Any] = observer.create_client(ManageLifecycleNodes, "/lifecycle_manager/manage_nodes")
    is_active: Client[Any, Any] = observer.create_client(Trigger, "/lifecycle_manager/is_active")
    while not (manage.service_is_ready() and is_active.service_is_ready()):
        await asyncio.sleep(0.01)
    answer = await manage.call_async(Command(command=command))
    assert answer is not None
    state = await is_active.call_async(Trigger.Request())
    observer.destroy_client(manage)
    observer.destroy_client(is_active)
    return answer.success, state


def settled(log: TransitionLog, count: int) -> list[tuple[str, str]]:
    """The primary states reached, once ``count`` events have arrived."""
    deadline = time.monotonic() + 10.0
    while len(log) < count and time.monotonic() < deadline:
        time.sleep(0.01)
    return [(node, goal) for node, goal in log.steps() if goal in PRIMARY]


def test_startup_walks_forward_and_shutdown_in_reverse(
    executor: AsyncioExecutor, system: Callable[..., Any]
) -> None:
    _, _, log, observer = system()
    started, state = run(executor, call_manager(observer, Command.STARTUP))
    assert started and state.success
    assert settled(log, 12) == [
        ("/a", "inactive"),
        ("/b", "inactive"),
        ("/c", "inactive"),
        ("/a", "active"),
        ("/b", "active"),
        ("/c", "active"),
    ]
    stopped, state = run(executor, call_manager(observer, Command.SHUTDOWN))
    assert stopped and not state.success
    assert settled(log, 30)[6:] == [
        ("/c", "inactive"),
        ("/b", "inactive"),
        ("/a", "inactive"),
        ("/c", "unconfigured"),
        ("/b", "unconfigured"),
        ("/a", "unconfigured"),
        ("/c", "finalized"),
        ("/b", "finalized"),
        ("/a", "finalized"),
    ]


def test_failed_configure_rolls_the_others_back_and_says_why(
    executor: AsyncioExecutor, system: Callable[..., Any]
) -> None:
    managed, _manager, log, observer = system()
    managed["b"].failures = 1
    started, state = run(executor, call_manager(observer, Command.STARTUP))
    assert not started and not state.success
    assert "/b" in state.message and "'configure'" in state.message
    assert "success=false" in state.message and "rolled back /a" in state.message
    assert settled(log, 6) == [("/a", "inactive"), ("/b", "unconfigured"), ("/a", "unconfigured")]
    assert all(node.lifecycle_state.label == "unconfigured" for node in managed.values())


def test_failed_transition_is_retried_with_backoff(
    executor: AsyncioExecutor, system: Callable[..., Any]
) -> None:
    managed, _, log, observer = system(transition_retries=2, retry_delay=0.2, retry_backoff=2.0)
    managed["b"].failures = 2
    started_at = time.monotonic()
    started, _ = run(executor, call_manager(observer, Command.STARTUP))
    elapsed = time.monotonic() - started_at
    assert started
    assert 0.6 <= elapsed < 5.0  # 0.2 s, then 0.4 s
    assert [goal for node, goal in settled(log, 16) if node == "/b"] == [
        "unconfigured",
        "unconfigured",
        "inactive",
        "active",
    ]


def test_pause_resume_and_reset(executor: AsyncioExecutor, system: Callable[..., Any]) -> None:
    managed, _, _, observer = system()

    async def scenario() -> list[tuple[bool, set[str]]]:
        results = []
        for command in (Command.STARTUP, Command.PAUSE, Command.RESUME, Command.RESET):
            ok, _ = await call_manager(observer, command)
            results.append((ok, {node.lifecycle_state.label for node in managed.values()}))
        return results

    assert run(executor, scenario()) == [
        (True, {"active"}),
        (True, {"inactive"}),
        (True, {"active"}),
        (True, {"unconfigured"}),
    ]


# -- across processes ------------------------------------------------------------------

TALKER = """
nodes:
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: {name}
    parameters: [{{rate: 20.0, bond_heartbeat_period: 0.1}}]
"""

WITH_MANAGER = """
nodes:
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: a
    parameters: [{rate: 20.0}]
  - package: lifecycle_container
    plugin: lifecycle_container::Listener
    name: c
manager:
  node_names: [/a, /b, /c]
  autostart: true
  bond_timeout: 1.0
  bond_heartbeat_period: 0.1
  bond_respawn_max_duration: 30.0
  service_timeout: 10.0
"""

BOND_TIMEOUT = 1.0
MARGIN = 1.0
#: How long Fast DDS was seen to block a write of the container's (a service
#: request: the watchdog reported the loop stuck in ``send_request`` for
#: 1.4 s) right after a peer process was killed.
FAST_DDS_STALL = 2.0


@dataclass
class System:
    """Node /b in a process of its own, /a and /c with the manager in another, and an observer."""

    remote: ContainerProcess
    main: ContainerProcess
    observer: Node
    log: TransitionLog


@contextlib.contextmanager
def managed_system(
    run_container: Callable[..., ContainerProcess],
    context: Context,
    executor: AsyncioExecutor,
    *,
    manager: str = WITH_MANAGER,
    watched: tuple[str, ...] = ("/a", "/c"),
) -> Iterator[System]:
    """Bring the system up and spin ``executor`` for the observer until the test ends."""
    remote = run_container(TALKER.format(name="b"))
    main = run_container(manager)
    try:
        main.wait_for_line("Managed nodes are active")
    except AssertionError as failed:
        raise AssertionError(f"{failed}\nthe container of /b:\n{remote.output()}") from None
    observer = Node("observer", context=context)
    executor.add_node(observer)
    log = TransitionLog(observer, list(watched))
    log.wait_matched()
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    try:
        yield System(remote, main, observer, log)
    finally:
        executor.shutdown(timeout_sec=5.0)
        spinner.join(5.0)
        observer.destroy_node()


# Container processes, one killed and respawned.
@pytest.mark.slow
def test_killed_node_in_another_process_resets_the_rest_and_respawn_restarts_them(
    run_container: Callable[..., ContainerProcess], context: Context, executor: AsyncioExecutor
) -> None:
    with managed_system(run_container, context, executor) as system:
        remote, main = system.remote, system.main
        mark = len(main.lines)
        remote.process.send_signal(signal.SIGKILL)
        killed_at = time.time()
        remote.process.wait(10)
        # Timed by the manager's own log lines. Transition events reach this
        # test's observer through Fast DDS, which for a second or so after a
        # peer process is killed can hold deliveries back (measured up to
        # 1.3 s, the same messages late with rclpy's SingleThreadedExecutor
        # as the receiver), and can block the container's own writes too.
        lost = main.wait_for_line("Heartbeat of /b lost", start=mark, timeout=BOND_TIMEOUT + 10)
        assert log_time(lost) - killed_at < BOND_TIMEOUT + MARGIN, main.output()
        for node in ("/c", "/a"):
            line = main.wait_for_line(f"{node}: deactivate -> inactive", start=mark, timeout=10)
            assert log_time(line) - log_time(lost) < MARGIN + FAST_DDS_STALL, main.output()
        # Asked, not watched: this process's transition_event readers heard
        # nothing for 10 s after the kill in one full-suite run of some forty
        # (Fast DDS, right after a peer process was killed), though the
        # container logged the reset within a second.
        for node in ("/a", "/c"):
            _wait_for_state(node, "unconfigured [1]", main)

        run_container(TALKER.format(name="b"))
        main.wait_for_line("/b back; starting up again", start=mark, timeout=30)
        main.wait_for_line("Managed nodes are active", start=mark, timeout=30)
        for node in ("/a", "/c"):
            _wait_for_state(node, "active [3]", main)
    assert main.stop() == 0


def _wait_for_state(node: str, state: str, container: ContainerProcess, *, timeout: float = 15.0) -> None:
    """Until ``container lifecycle get NODE`` (a process of its own, so a participant of its own) says ``state``."""
    deadline = time.monotonic() + timeout
    said = ""
    while said != state and time.monotonic() < deadline:
        said = subprocess.run(
            [sys.executable, "-m", "container", "lifecycle", "get", node], capture_output=True, text=True, timeout=30
        ).stdout.strip()
    assert said == state, f"{node}: {said!r}, not {state!r}\n{container.output()}"


class Hanging(Managed):
    """A managed timer whose callback blocks its callback group while ``hang`` is set."""

    def __init__(self, name: str, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.hang = threading.Event()
        self.unhang = threading.Event()
        self.create_timer(0.02, self._tick)

    def _tick(self) -> None:
        if self.hang.is_set():
            self.unhang.wait(30.0)
            self.hang.clear()


def test_hung_node_resets_the_rest_and_recovery_restarts_them(
    context: Context, executor: AsyncioExecutor
) -> None:
    names = ("a", "b", "c")
    managed = {n: (Hanging if n == "b" else Managed)(n, context=context) for n in names}
    settings = ManagerSettings.from_mapping(
        {"node_names": ["/a", "/b", "/c"], "bond_timeout": 0.5, "bond_heartbeat_period": 0.05}
    )
    manager = LifecycleManager(settings, context=context)
    observer = Node("observer", context=context)
    nodes: list[Node] = [*managed.values(), manager, observer]
    for node in nodes:
        executor.add_node(node)
    log = TransitionLog(observer, ["/a", "/c"])
    log.wait_matched()
    hanging = managed["b"]
    assert isinstance(hanging, Hanging)
    try:

        def active() -> bool:
            """Whether the manager reports the system active (set by its own tasks)."""
            return manager.system_active

        async def scenario() -> float:
            assert await manager.command(STARTUP)
            mark = len(log)
            hung_at = time.monotonic()
            hanging.hang.set()
            reset = await log.wait_for_async("/a", "unconfigured", after=mark)
            await log.wait_for_async("/c", "unconfigured", after=mark)
            assert not manager.system_active and "/b" in manager.status
            back = len(log)
            hanging.unhang.set()
            await log.wait_for_async("/a", "active", after=back)
            await log.wait_for_async("/c", "active", after=back)
            while not active():
                await asyncio.sleep(0.01)
            return reset.received - hung_at

        took = run(executor, scenario(), timeout=30.0)
        assert took < 0.5 + MARGIN
        assert {n.lifecycle_state.label for n in managed.values()} == {"active"}
    finally:
        hanging.unhang.set()
        for node in nodes:
            executor.remove_node(node)
            node.destroy_node()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("-p", "bogus"), "expected 'name:=value', not 'bogus'"),
        (("/nonexistent/manager.yaml",), "cannot read"),
        (("-p", "bond_timeout:=soon"), "bond_timeout"),
    ],
)
def test_manager_command_refuses_bad_input_with_exit_2(
    args: tuple[str, ...], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from container.cli import main

    try:
        code = main(["manager", *args])
    except SystemExit as exc:  # argparse's usage errors
        code = int(exc.code or 0)
    assert code == 2
    assert message in capsys.readouterr().err


def test_heartbeat_periods_below_10_ms_are_refused() -> None:
    with pytest.raises(ConfigError, match=r"bond_heartbeat_period: must be >= 0.01"):
        ManagerSettings.from_mapping({"bond_heartbeat_period": 1e-9})
    assert ManagerSettings.from_mapping({"bond_heartbeat_period": 0.01}).parameters["bond_heartbeat_period"] == 0.01


# A container process, a node killed, the bond timeout waited out.
@pytest.mark.slow
def test_a_heartbeat_from_another_instance_never_hides_a_crash(
    run_container: Callable[..., ContainerProcess], context: Context, executor: AsyncioExecutor
) -> None:
    """A peer beating ``active`` for a killed node, under another instance id, is not the node."""
    from bond.msg import Status

    with managed_system(run_container, context, executor) as system:
        publisher = system.observer.create_publisher(Status, "/bond", 10)
        system.observer.create_timer(
            0.05, lambda: publisher.publish(Status(id="/b", instance_id="impostor", active=True))
        )
        mark = len(system.main.lines)
        system.remote.process.send_signal(signal.SIGKILL)
        killed_at = time.monotonic()
        system.main.wait_for_line("Heartbeat of /b lost", start=mark, timeout=BOND_TIMEOUT + 10)
        assert time.monotonic() - killed_at < BOND_TIMEOUT + MARGIN + 0.5


# A container process, a node killed, the respawn window waited out.
@pytest.mark.slow
def test_a_node_back_after_the_respawn_window_is_reset_like_its_peers(
    run_container: Callable[..., ContainerProcess], context: Context, executor: AsyncioExecutor
) -> None:
    """Stopped past the window, a node comes back active; it must not stay active alone."""
    short_window = WITH_MANAGER.replace("bond_respawn_max_duration: 30.0", "bond_respawn_max_duration: 1.0")
    with managed_system(run_container, context, executor, manager=short_window) as system:
        mark = len(system.main.lines)
        system.remote.process.send_signal(signal.SIGSTOP)
        try:
            system.main.wait_for_line("/b did not come back", start=mark, timeout=BOND_TIMEOUT + 10)
        finally:
            system.remote.process.send_signal(signal.SIGCONT)
        system.main.wait_for_line("/b came back after the respawn window", start=mark, timeout=10)
        # Asked, not watched: transition events sent while discovery
        # re-matches the resumed process can be missed.
        _wait_for_state("/b", "unconfigured [1]", system.main)
