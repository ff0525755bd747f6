"""The greeter plugin's own tests, written as a plugin author would.

The fixtures come from lifecycle-container's pytest plugin
(``container.testing``), installed with it: no conftest needed. Run them
with the plugin installed: ``pip install ./examples/thirdparty_plugin &&
pytest examples/thirdparty_plugin/tests``.
"""

from __future__ import annotations

import pytest
from std_msgs.msg import String

from container import TransitionError
from container.testing import ContainerHost

pytestmark = pytest.mark.asyncio


async def test_greets_by_name_while_active(container_host: ContainerHost) -> None:
    greeter = await container_host.load("greeter_nodes::Greeter", parameters={"name": "tests"})

    message = await container_host.wait_for_message(String, "/greeting", timeout=5.0)

    assert message.data == "Hello, tests!"
    assert container_host.state_of(greeter) == "active"


async def test_is_quiet_once_deactivated(container_host: ContainerHost) -> None:
    greeter = await container_host.load("greeter_nodes::Greeter", name="quiet_greeter")
    await container_host.wait_for_message(String, "/greeting")

    await container_host.transition(greeter, "deactivate")

    with pytest.raises(TimeoutError):
        await container_host.wait_for_message(String, "/greeting", timeout=2.5)


async def test_unload_leaves_nothing_on_the_graph(container_host: ContainerHost) -> None:
    greeter = await container_host.load("greeter_nodes::Greeter")
    await container_host.unload(greeter)

    await container_host.wait_until(
        lambda: "greeter" not in container_host.client.get_node_names(), what="/greeter gone from the graph"
    )


async def test_cannot_activate_twice(container_host: ContainerHost) -> None:
    greeter = await container_host.load("greeter_nodes::Greeter")

    with pytest.raises(TransitionError):
        await container_host.transition(greeter, "activate")
