"""``container.testing``: the pytest plugin plugin authors test with.

The fixtures come from the installed entry point (``pytest11``), as in a
plugin's own test suite; the container they give serves on the test's own
event loop (``spin_async`` on a loop the executor did not create).
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Any, ClassVar

import pytest
from lifecycle_msgs.srv import GetState
from rclpy.lifecycle import TransitionCallbackReturn
from std_msgs.msg import String

from container import ComponentManager, LifecycleNode, LoadError, LoadRequest, PluginRegistry, hookimpl
from container.executor import AsyncioExecutor
from container.lifecycle._transitions import state_of
from container.testing import ContainerHost, open_container_host
from tests.container_support import REPO

pytestmark = pytest.mark.timeout(60)


async def test_a_loaded_talker_is_active_and_heard(container_host: ContainerHost) -> None:
    talker = await container_host.load("lifecycle_container::Talker", parameters={"rate": 20.0, "message": "hi"})

    message = await container_host.wait_for_message(String, "/chatter", where=lambda m: m.data.startswith("hi:"))

    assert message.data.startswith("hi: ")
    assert container_host.state_of(talker) == "active"
    response = await container_host.call(GetState, "/talker/get_state", GetState.Request())
    assert response.current_state.label == "active"


async def test_transitions_and_unload_go_through_the_container(container_host: ContainerHost) -> None:
    talker = await container_host.load("lifecycle_container::Talker", name="quiet", autostart=False)
    assert container_host.state_of(talker) == "unconfigured"

    await container_host.transition(talker, "configure")
    assert container_host.state_of(talker) == "inactive"
    await container_host.unload(talker)

    assert container_host.manager.loaded() == []


async def test_waiting_for_a_message_that_never_comes_times_out_plainly(container_host: ContainerHost) -> None:
    with pytest.raises(TimeoutError, match=r"no std_msgs/String message on '/nobody' within 0.2 s"):
        await container_host.wait_for_message(String, "/nobody", timeout=0.2)


class Recorder(LifecycleNode):
    """Records the transitions it went through in a list shared by the test."""

    seen: ClassVar[list[str]] = []

    def on_configure(self, state: object) -> TransitionCallbackReturn:
        self.seen.append("configure")
        return TransitionCallbackReturn.SUCCESS

    async def on_activate(self, state: object) -> TransitionCallbackReturn:
        await asyncio.sleep(0.01)
        self.seen.append("activate")
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: object) -> TransitionCallbackReturn:
        self.seen.append("deactivate")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: object) -> TransitionCallbackReturn:
        self.seen.append("cleanup")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: object) -> TransitionCallbackReturn:
        self.seen.append("shutdown")
        return TransitionCallbackReturn.SUCCESS


class RecorderPlugin:
    @hookimpl
    def register_node_types(self, register: object) -> None:
        register(Recorder)  # type: ignore[operator]


async def test_leaving_the_host_takes_every_node_down_its_lifecycle(ros_context: object) -> None:
    registry = PluginRegistry(group="container.test_plugins.none")
    registry.add_plugin(RecorderPlugin(), distribution="recorder")
    Recorder.seen = []
    async with open_container_host(context=ros_context, registry=registry) as host:  # type: ignore[arg-type]
        await host.load("recorder::Recorder", name="recorder")
        assert Recorder.seen == ["configure", "activate"]

    assert Recorder.seen == ["configure", "activate", "deactivate", "cleanup", "shutdown"]


class SlowToConstruct(LifecycleNode):
    """A node whose constructor takes a second: a load of it is under way that long."""

    began: ClassVar[threading.Event] = threading.Event()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        SlowToConstruct.began.set()
        time.sleep(1.0)
        super().__init__(*args, **kwargs)


class SlowPlugin:
    @hookimpl
    def register_node_types(self, register: object) -> None:
        register(SlowToConstruct)  # type: ignore[operator]


async def test_unloading_everything_waits_for_a_load_under_way_and_loads_nothing_after(ros_context: object) -> None:
    """A shutdown that unloads every node while a load (a service's, a reload's) is under way: the
    load ends first and its node is unloaded too, and later loads are refused, not left loaded."""
    registry = PluginRegistry(group="container.test_plugins.none")
    registry.add_plugin(SlowPlugin(), distribution="slow")
    SlowToConstruct.began.clear()
    async with open_container_host(context=ros_context, registry=registry) as host:  # type: ignore[arg-type]
        manager = host.manager

        async def load_as_a_service_does() -> object:
            async with manager.changing:
                return await manager.load(LoadRequest("slow", "SlowToConstruct", name="late"))

        loading = asyncio.ensure_future(load_as_a_service_does())
        await host.wait_until(SlowToConstruct.began.is_set, what="the slow constructor began")
        await manager.unload_all()
        await loading

        assert manager.loaded() == [], [loaded.full_name for loaded in manager.loaded()]
        with pytest.raises(LoadError, match="shutting down"):
            await manager.load(LoadRequest("slow", "SlowToConstruct", name="later"))


@pytest.mark.parametrize("plugin", ["Talker", "Listener"])
async def test_load_and_start_on_a_loop_of_the_users_own(ros_context: object, plugin: str) -> None:
    # The executor's documentation promises spin_async on an already running loop; autostart
    # there once waited for a loop turn that only the executor's own loop takes.
    executor = AsyncioExecutor(context=ros_context)  # type: ignore[arg-type]
    manager = ComponentManager(registry=PluginRegistry(), executor=executor, context=ros_context)  # type: ignore[arg-type]
    executor.add_node(manager)
    spinning = asyncio.ensure_future(executor.spin_async())
    try:
        loaded = await asyncio.wait_for(
            manager.load_and_start(LoadRequest("lifecycle_container", plugin, autostart=True), timeout=3.0), 10.0
        )
        assert loaded.node.get_fully_qualified_name() == f"/{plugin.lower()}"
        assert state_of(loaded.node) == "active"
        await manager.unload_all()
    finally:
        executor.shutdown(timeout_sec=5.0)
        await spinning
        manager.destroy_node()


def test_a_plugins_own_suite_gets_the_fixtures_from_the_entry_point(tmp_path: Path) -> None:
    # A test file with no conftest, run by pytest as a plugin author would.
    test = tmp_path / "test_plugin.py"
    test.write_text(
        textwrap.dedent(
            """
            import os

            import pytest
            from std_msgs.msg import String

            @pytest.mark.asyncio
            async def test_talker(container_host):
                assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
                assert os.environ["ROS_DOMAIN_ID"] == "17"
                await container_host.load("lifecycle_container::Talker", parameters={"rate": 50.0})
                message = await container_host.wait_for_message(String, "/chatter")
                assert message.data.startswith("Hello World: ")
            """
        )
    )
    env = {
        k: v for k, v in os.environ.items() if k not in {"ROS_AUTOMATIC_DISCOVERY_RANGE", "PYTEST_ADDOPTS"}
    }
    env["ROS_DOMAIN_ID"] = "17"  # exported: wins over the plugin's random one
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(test)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "1 passed" in result.stdout


# Installs the example with pip and runs its suite in a child pytest.
@pytest.mark.slow
def test_the_example_plugins_own_suite_passes(thirdparty_site: Path) -> None:
    # examples/thirdparty_plugin/tests, run as its author would after
    # `pip install ./examples/thirdparty_plugin`: its own directory, no conftest.
    example = REPO / "examples" / "thirdparty_plugin"
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(thirdparty_site), env.get("PYTHONPATH")]))
    env.pop("PYTEST_ADDOPTS", None)
    result = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests"],
        cwd=example,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "4 passed" in result.stdout


@pytest.mark.parametrize(
    ("request_fields", "message"),
    [
        ({"name": "a\x00b"}, r"Invalid node name 'a\\x00b': must not contain a NUL character"),
        ({"namespace": "/ns\x00x"}, r"Invalid namespace '/ns\\x00x': must not contain a NUL character"),
        ({"remap_rules": ["chatter:=a\x00b"]}, r"Invalid remap rule 'chatter:=a\\x00b': must not contain a NUL"),
        ({"parameters": [{"": 1}]}, r"parameter name '' must not be empty"),
        ({"parameters": [{"a..b//c": 1}]}, r"parameter name 'a\.\.b//c' must be words"),
        ({"parameters": [{"a": {"": 1}}]}, r"parameter name 'a\.' must be words"),
    ],
    ids=["nul-name", "nul-namespace", "nul-remap", "empty-parameter", "dots-and-slashes", "empty-part"],
)
async def test_names_rcl_would_refuse_or_cut_short_are_refused(
    container_host: ContainerHost, request_fields: dict[str, object], message: str
) -> None:
    # A NUL never arrives through a service (rclpy's message conversion cuts
    # a string at it, on the sender's side); a container file or the Python
    # API can still carry one.
    with pytest.raises(LoadError, match=message):
        await container_host.manager.load(
            LoadRequest("lifecycle_container", "Talker", **request_fields)  # type: ignore[arg-type]
        )
    assert container_host.manager.loaded() == []
    # What rcl takes: '/' after '.' (rclcpp's QoS overrides name topics so).
    ok = await container_host.load(
        "lifecycle_container::Talker", parameters={"qos_overrides./chatter.publisher.depth": 5}
    )
    assert container_host.state_of(ok) == "active"
