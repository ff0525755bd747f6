"""How a container file's nodes come up: all constructed, then served, then
configured in order, then activated in order (Nav2's bring-up)."""

from __future__ import annotations

import asyncio
import sys
from typing import Any

import pytest
import yaml
from rclpy.context import Context
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn

from container import LifecycleNode, hookimpl
from container._app import ContainerApp
from container._config import parse_config
from container.lifecycle import state_of

pytestmark = pytest.mark.timeout(60)

#: What the recording nodes did, in order: (event, node name, nodes the executor served then).
EVENTS: list[tuple[str, str, int]] = []


class Recording(LifecycleNode):
    """Notes its construction and transitions; ``fail_configure`` makes configure fail."""

    def __init__(self, node_name: str = "recording", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("fail_configure", False)
        EVENTS.append(("construct", self.get_name(), -1))

    def _served(self) -> int:
        assert self.executor is not None
        return len(self.executor.get_nodes())

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        EVENTS.append(("configure", self.get_name(), self._served()))
        if self.get_parameter("fail_configure").value:
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        EVENTS.append(("activate", self.get_name(), self._served()))
        return TransitionCallbackReturn.SUCCESS


def serve_file(context: Context, text: str) -> tuple[list[str], dict[str, str]]:
    """Run ``serve`` for the file ``text`` until ready, then stop it.

    :return: what failed, and each loaded node's state when it was ready.
    """
    EVENTS.clear()
    app = ContainerApp.create(parse_config(yaml.safe_load(text)), context=context)
    app.registry.add_plugin(sys.modules[__name__], distribution="recording-nodes")
    failed: list[str] = []
    states: dict[str, str] = {}

    async def main() -> None:
        stopping = asyncio.Event()

        def ready() -> None:
            states.update((loaded.node.get_name(), state_of(loaded.node)) for loaded in app.manager.loaded())
            stopping.set()

        failed.extend(await app.serve(stopping=stopping, on_ready=ready))

    try:
        app.executor.spin_until_future_complete(main(), timeout_sec=45)
    finally:
        app.close()
        app.executor.shutdown()
    return failed, states


@hookimpl
def register_node_types(register: Any) -> None:
    register(Recording)


FILE = """
nodes:
  - {package: recording_nodes, plugin: recording_nodes::Recording, name: a, autostart: true}
  - {package: recording_nodes, plugin: recording_nodes::Recording, name: b, autostart: true,
     parameters: [{fail_configure: %s}]}
  - {package: recording_nodes, plugin: recording_nodes::Recording, name: c}
  - {package: recording_nodes, plugin: recording_nodes::Recording, name: d, autostart: true}
"""


def test_a_files_nodes_are_constructed_then_configured_then_activated_in_order(context: Context) -> None:
    failed, states = serve_file(context, FILE % "false")
    assert failed == []
    assert [(event, name) for event, name, _ in EVENTS] == [
        ("construct", "a"), ("construct", "b"), ("construct", "c"), ("construct", "d"),
        ("configure", "a"), ("configure", "b"), ("configure", "d"),
        ("activate", "a"), ("activate", "b"), ("activate", "d"),
    ]
    # The container's own node and the four listed: all served before the
    # first transition.
    served = {served for event, _, served in EVENTS if event != "construct"}
    assert len(served) == 1 and served.pop() >= 5, EVENTS
    assert states == {"a": "active", "b": "active", "c": "unconfigured", "d": "active"}


def test_a_node_that_fails_to_configure_is_named_and_never_activated(context: Context) -> None:
    failed, states = serve_file(context, FILE % "true")
    assert len(failed) == 1 and failed[0].startswith("nodes[1] (name: b): "), failed
    assert [(event, name) for event, name, _ in EVENTS if event != "construct"] == [
        ("configure", "a"), ("configure", "b"), ("configure", "d"),
        ("activate", "a"), ("activate", "d"),
    ]
    assert states == {"a": "active", "b": "unconfigured", "c": "unconfigured", "d": "active"}
