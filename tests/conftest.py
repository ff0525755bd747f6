"""Shared test set-up: an isolated ROS domain, contexts, executors, processes.

Every test session picks a random ``ROS_DOMAIN_ID`` and keeps discovery on
this host (one already exported wins), so concurrent runs never see each
other: ``container.testing``'s isolation, which its pytest plugin would do
too, done here first because this module imports rclpy. Child processes
inherit the same environment.
"""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from container.testing import isolate_ros

isolate_ros()

from rcl_interfaces.msg import Log  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

from container import AsyncioExecutor  # noqa: E402
from tests.colcon_support import Prebuild  # noqa: E402
from tests.component_support import IMPORT_ROOT, install_test_plugin  # noqa: E402
from tests.container_support import REPO, SHARED, ContainerProcess  # noqa: E402,F401
from tests.install_support import make_ros_wheels_venv  # noqa: E402
from tests.process_support import venv_ament_prefix_path  # noqa: E402
from tests.signal_support import signals_as_from_a_terminal  # noqa: E402


@pytest.fixture
def context(ros_context: Context) -> Context:
    """A fresh rclpy context, shut down after the test (container.testing's ``ros_context``)."""
    return ros_context


@pytest.fixture
def executor(context: Context) -> Iterator[AsyncioExecutor]:
    """An AsyncioExecutor on ``context``, shut down after the test."""
    ex = AsyncioExecutor(context=context)
    try:
        yield ex
    finally:
        ex.shutdown(timeout_sec=5.0)


@pytest.fixture
def spinning(executor: AsyncioExecutor) -> Iterator[AsyncioExecutor]:
    """``executor`` spinning on a thread of its own, as in a container or an application
    that builds nodes while it spins (a test module may define its own)."""
    spinner = threading.Thread(target=executor.spin, name="spin", daemon=True)
    spinner.start()
    yield executor
    executor.shutdown(timeout_sec=5.0)
    spinner.join(5.0)


@pytest.fixture
def host(context: Context, executor: AsyncioExecutor) -> Iterator[Callable[..., Any]]:
    """Create nodes on the test context, on ``executor``; destroyed afterwards."""
    nodes: list[Node] = []

    def make(cls: type[Node], name: str, **kwargs: Any) -> Any:
        node = cls(name, context=context, **kwargs)
        executor.add_node(node)
        nodes.append(node)
        return node

    yield make
    for node in nodes:
        executor.remove_node(node)
        node.destroy_node()
        # A lifecycle node's rcl state machine holds the rcl node, and with it
        # the node's /rosout registration, until collected; release it now.
        machine = getattr(node, "_state_machine", None)
        if machine is not None:
            machine.destroy_when_not_in_use()


@pytest.fixture
def client_node(context: Context, executor: AsyncioExecutor) -> Iterator[Node]:
    """A node of the test's own, on ``executor``, to call containers and nodes from."""
    node = Node("test_client", context=context)
    executor.add_node(node)
    yield node
    executor.remove_node(node)
    node.destroy_node()


@pytest.fixture
def rosout(client_node: Node) -> list[Log]:
    """Every line on ``/rosout`` from now on, and the ones still kept (transient local)."""
    heard: list[Log] = []
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    client_node.create_subscription(Log, "/rosout", heard.append, qos)
    return heard


@pytest.fixture
def ament_prefix_path(monkeypatch: pytest.MonkeyPatch) -> str:
    """AMENT_PREFIX_PATH as the virtualenv's activation sets it, for this process and its children
    (launch_ros finds the container's executable through it)."""
    path = venv_ament_prefix_path()
    monkeypatch.setenv("AMENT_PREFIX_PATH", path)
    return path


@pytest.fixture
def see_plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Callable[..., None]:
    """Make child processes see a test plugin distribution whose entry point is a module of tests/."""

    def see(*, distribution: str = "test-nodes", module: str = "tests.component_support") -> None:
        site = install_test_plugin(tmp_path / "site", distribution=distribution, module=module)
        path = os.pathsep.join([str(site), str(IMPORT_ROOT), os.environ.get("PYTHONPATH", "")])
        monkeypatch.setenv("PYTHONPATH", path.rstrip(os.pathsep))

    return see


#: Modules whose builds take minutes of CPU: run last, after every test that times something, so that
#: the builds started with the session (``colcon_prebuild``) had all the time those left idle. In this
#: order: test_wheels installs into the underlay that test_colcon builds over.
BUILDS_LAST = ("test_colcon.py", "test_wheels.py")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    last = [item for name in BUILDS_LAST for item in items if item.path.name == name]
    if last:
        moved = set(last)
        items[:] = [item for item in items if item not in moved] + last


@pytest.fixture(scope="session", autouse=True)
def colcon_prebuild(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Prebuild | None]:
    """tests/test_colcon.py's builds, started with the session at idle priority when it was collected."""
    if not any(item.path.name == "test_colcon.py" for item in request.session.items):
        yield None
        return
    prebuild = Prebuild(tmp_path_factory.mktemp("colcon"))
    try:
        yield prebuild
    finally:
        prebuild.stop()


@pytest.fixture(scope="session")
def underlay(colcon_prebuild: Prebuild | None, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A virtualenv of the ROS wheels, the ROS build tools and colcon, nothing of this project
    (tests/test_colcon.py builds over it; tests/test_wheels.py installs into it and
    uninstalls again): the colcon prebuild's, once it ended, if there is one."""
    if colcon_prebuild is not None:
        return colcon_prebuild.result().underlay
    return make_ros_wheels_venv(tmp_path_factory.mktemp("underlay") / "venv")


@pytest.fixture(scope="session")
def thirdparty_site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """examples/thirdparty_plugin, installed with pip into a directory of its own
    (put it on ``PYTHONPATH`` to see it: the test environment stays as set up)."""
    site = tmp_path_factory.mktemp("thirdparty-site")
    subprocess.run(
        [
            sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
            "--target", str(site), str(REPO / "examples" / "thirdparty_plugin"),
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    return site


@pytest.fixture
def run_container(tmp_path: Path) -> Iterator[Callable[..., ContainerProcess]]:
    """Start ``container run`` on YAML text; every process is stopped afterwards."""
    started: list[ContainerProcess] = []

    def start(config_text: str, *, args: tuple[str, ...] = (), ready: bool = True) -> ContainerProcess:
        path = tmp_path / f"container{len(started)}.yaml"
        path.write_text(config_text, encoding="utf-8")
        proc = ContainerProcess(path, args=args)
        started.append(proc)
        if ready:
            proc.wait_for_line("ready with")
        return proc

    yield start
    for proc in started:
        proc.close()


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "shared: reads ../shared (skipped when absent)")
    # Started in the background by a script, the suite would hand an ignored
    # SIGINT to every process it starts.
    signals_as_from_a_terminal()


def pytest_collection_finish(session: pytest.Session) -> None:
    # Every context's teardown collects garbage (container.testing), about
    # 80 ms a time over the modules and the collected tests; frozen, they
    # are not looked at again.
    gc.collect()
    gc.freeze()
