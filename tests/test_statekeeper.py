"""The state file kept by a container: what it records, what a container restores from it, and
every file it refuses (in process; tests/test_respawn.py does it with launch_ros's processes).

A container here is ``ContainerApp.serve`` on the test's context, as ``container run`` runs it;
a process killed with ``kill -9`` is played by saving the file as it stands and writing it back
after the container stopped (a clean stop removes it).
"""

from __future__ import annotations

import asyncio
import fcntl
import json
import os
import threading
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from rcl_interfaces.msg import ParameterEvent
from rclpy.context import Context
from rclpy.exceptions import InvalidParameterTypeException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_parameter_events

import container._statefile as statefile
import container._statekeeper as statekeeper
from container import AsyncioExecutor, LoadError
from container._app import ContainerApp
from container._config import parse_config
from container._container import LoadRequest
from container._statefile import ContainerState, NodeRecord, encode, read_state, same_parameters
from container.lifecycle import is_lifecycle, state_of, transition
from tests import component_support
from tests.waiting import wait_until_async

pytestmark = pytest.mark.timeout(60)

Body = Callable[[ContainerApp], Awaitable[None]]


def container_file(path: Path, nodes: str = "[]") -> str:
    """A container file whose container node is given ``state_file: path``."""
    return f"container:\n  parameters: [{{state_file: '{path}'}}]\nnodes: {nodes}\n"


def run(context: Context, text: str, body: Body | None = None) -> None:
    """Serve the container file ``text`` until ready, run ``body``, then stop it cleanly."""
    app = ContainerApp.create(parse_config(yaml.safe_load(text)), context=context)
    app.registry.add_plugin(component_support, distribution="test-nodes")

    async def main() -> None:
        stopping = asyncio.Event()
        ready = asyncio.Event()
        serving = asyncio.ensure_future(app.serve(stopping=stopping, on_ready=ready.set))
        try:
            await asyncio.wait_for(asyncio.shield(ready.wait()), 20.0)
            if body is not None:
                await body(app)
        finally:
            stopping.set()
            await serving

    try:
        app.executor.spin_until_future_complete(main(), timeout_sec=50)
    finally:
        app.close()
        app.executor.shutdown()


def recorded(path: Path) -> dict[str, tuple[int, str | None]]:
    """What the file records: each node's unique id and state, by full name."""
    state = read_state(path)
    return {} if state is None else {node.full_name: (node.unique_id, node.state) for node in state.nodes}


def record(unique_id: int, name: str, plugin: str = "lifecycle_container::Talker", **fields: Any) -> NodeRecord:
    package = plugin.split("::")[0]
    return NodeRecord(unique_id=unique_id, package=package, plugin=plugin, name=name, namespace=None,
                      full_name=f"/{name}", **fields)


def held(app: ContainerApp) -> dict[str, tuple[int, str | None]]:
    """What the container holds: each node's unique id and state (``None``: no lifecycle), by full name."""
    return {
        loaded.full_name: (loaded.unique_id, state_of(loaded.node) if is_lifecycle(loaded.node) else None)
        for loaded in app.manager.loaded()
    }


def talker(name: str = "talker", **fields: Any) -> LoadRequest:
    return LoadRequest("lifecycle_container", "lifecycle_container::Talker", name=name, **fields)


def test_what_a_container_recorded_comes_back_ids_states_and_parameters(context: Context, tmp_path: Path) -> None:
    path = tmp_path / "state.json"
    died_with: list[bytes] = []

    async def first(app: ContainerApp) -> None:
        manager = app.manager
        one = await manager.load(talker(parameters=[Parameter("rate", value=5.0)]))
        two = await manager.load(LoadRequest("lifecycle_container", "Listener", name="listener",
                                             namespace="demo", remap_rules=["chatter:=/talk"]))
        gone = await manager.load(talker("gone"))
        busy = await manager.load(LoadRequest("test_nodes", "test_nodes::Busy"))  # rclpy's own LifecycleNode
        await manager.load(LoadRequest("test_nodes", "test_nodes::Idle"))  # no lifecycle
        await manager.unload(gone.unique_id)
        await manager.start(one, timeout=5.0)
        await manager.start(two, timeout=5.0, until="inactive")
        await transition(app.executor, busy.node, "configure", timeout=5.0)  # seen on its transition_event
        one.node.set_parameters([Parameter("message", value="Changed at runtime"), Parameter("rate", value=9.0)])
        expected = {"/talker": (1, "active"), "/demo/listener": (2, "inactive"), "/busy": (4, "inactive"),
                    "/idle": (5, None)}
        await wait_until_async(lambda: recorded(path) == expected, lambda: f"{recorded(path)}")
        await wait_until_async(lambda: len(read_node(path, "/talker").changed_parameters) == 2, "the parameters set")
        died_with.append(path.read_bytes())

    run(context, container_file(path), first)
    assert not path.exists(), "a clean stop leaves no state file"
    path.write_bytes(died_with[0])  # as a kill -9 would have left it
    talker_record = read_node(path, "/talker")
    assert [(p.name, p.value) for p in talker_record.parameters] == [("rate", 5.0)]
    assert sorted((p.name, p.value) for p in talker_record.changed_parameters) == [
        ("message", "Changed at runtime"), ("rate", 9.0)
    ]

    async def second(app: ContainerApp) -> None:
        assert held(app) == {"/talker": (1, "active"), "/demo/listener": (2, "inactive"), "/busy": (4, "inactive"),
                             "/idle": (5, None)}
        restored = {loaded.full_name: loaded for loaded in app.manager.loaded()}
        node = restored["/talker"].node
        assert (node.get_parameter("rate").value, node.get_parameter("message").value) == (9.0, "Changed at runtime")
        # As loaded, the changes apart (what a launch file's load is compared with).
        assert same_parameters(restored["/talker"].parameters, talker_record.parameters)
        # Ids are never reused: 3 went with its node, 6 is the next.
        assert (await app.manager.load(talker("late"))).unique_id == 6
        # The changes carried over are recorded again.
        await wait_until_async(lambda: "/late" in recorded(path), "the new node recorded")
        assert len(read_node(path, "/talker").changed_parameters) == 2

    run(context, container_file(path), second)


def read_node(path: Path, full_name: str) -> NodeRecord:
    state = read_state(path)
    assert state is not None
    (found,) = [node for node in state.nodes if node.full_name == full_name]
    return found


def test_a_forged_parameter_event_records_only_what_the_node_really_has(context: Context, tmp_path: Path) -> None:
    path = tmp_path / "state.json"

    async def body(app: ContainerApp) -> None:
        await app.manager.load(talker(parameters=[Parameter("rate", value=5.0)]))
        await wait_until_async(lambda: "/talker" in recorded(path), "the node recorded")
        # Any participant may publish on /parameter_events.
        forger = Node("forger", context=app.context)
        try:
            publisher = forger.create_publisher(ParameterEvent, "/parameter_events", qos_profile_parameter_events)
            forged = ParameterEvent(node="/talker", changed_parameters=[
                Parameter("rate", value=99.0).to_parameter_msg(), Parameter("made_up", value=1).to_parameter_msg()
            ])
            await wait_until_async(lambda: publisher.get_subscription_count() > 0, "the keeper's subscription")
            publisher.publish(forged)
            await wait_until_async(lambda: read_node(path, "/talker").changed_parameters, "the event handled")
        finally:
            forger.destroy_node()
        assert [(p.name, p.value) for p in read_node(path, "/talker").changed_parameters] == [("rate", 5.0)]

    run(context, container_file(path), body)


BAD_FILES = [
    ("corrupt", b'{"format": "lifecycle_container.state", "version": 1, "nod', "not JSON"),
    ("another version", json.dumps({"format": "lifecycle_container.state", "version": 7}).encode(),
     "state file version 7: this container reads version 1 only"),
    ("another container's", encode(ContainerState("/other/container", 2, (record(1, "t"),))),
     "it holds the nodes of container '/other/container', not of '/ComponentManager'"),
]


@pytest.mark.parametrize(("data", "reason"), [(d, r) for _, d, r in BAD_FILES], ids=[w for w, _, _ in BAD_FILES])
def test_a_file_it_cannot_use_is_moved_aside_and_the_container_starts_with_its_files_nodes(
    context: Context, tmp_path: Path, capfd: pytest.CaptureFixture[str], data: bytes, reason: str
) -> None:
    path = tmp_path / "state.json"
    path.write_bytes(data)

    async def body(app: ContainerApp) -> None:
        assert list(held(app)) == ["/listed"]
        await wait_until_async(lambda: recorded(path) == {"/listed": (1, "active")}, "a fresh state file")

    run(context, container_file(path, "[{package: lifecycle_container, plugin: Talker, name: listed, "
                                      "autostart: true}]"), body)
    (aside,) = tmp_path.glob("state.json.bad-*")
    assert aside.read_bytes() == data, "the evidence is kept as it was"
    errors = [line for line in capfd.readouterr().err.splitlines() if "[ERROR]" in line]
    assert len(errors) == 1, errors
    assert f"state file '{path}': " in errors[0] and reason in errors[0], errors[0]
    assert errors[0].endswith(f"; moved aside to '{aside}', and the container starts without its nodes")


def test_a_node_whose_plugin_is_gone_is_reported_and_skipped_the_others_restored(
    context: Context, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "state.json"
    path.write_bytes(encode(ContainerState("/ComponentManager", 7, (
        record(1, "first", state="active"),
        record(2, "thing", "gone_nodes::Thing", state="active"),
        record(3, "third", "lifecycle_container::Listener", state="inactive"),
    ))))

    async def body(app: ContainerApp) -> None:
        assert held(app) == {"/first": (1, "active"), "/third": (3, "inactive")}
        await wait_until_async(lambda: recorded(path) == {"/first": (1, "active"), "/third": (3, "inactive")},
                               lambda: f"the file without the skipped node: {recorded(path)}")
        state = read_state(path)
        assert state is not None and state.next_unique_id == 7

    run(context, container_file(path), body)
    err = capfd.readouterr().err
    assert (
        "Could not restore '/thing' (unique_id 2, gone_nodes::Thing): Could not find requested resource in ament "
        "index; skipped, and dropped from the state file"
    ) in err, err
    assert "Restored '/first' (unique_id 1): active" in err
    assert "Restored '/third' (unique_id 3): inactive" in err
    assert "Restored 2 of the 3 node(s) of the state file in " in err


def test_a_container_files_nodes_give_way_to_what_the_state_file_recorded_of_them(
    context: Context, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "state.json"
    # The file's node, deactivated at runtime; one loaded later; one shut down for good.
    path.write_bytes(encode(ContainerState("/ComponentManager", 4, (
        record(1, "listed", state="inactive"),
        record(2, "later", "lifecycle_container::Listener", state="active"),
        record(3, "done", state="finalized"),
    )), pid=4242))

    async def body(app: ContainerApp) -> None:
        assert held(app) == {"/listed": (1, "inactive"), "/later": (2, "active"), "/done": (3, "finalized")}

    run(context, container_file(path, "[{package: lifecycle_container, plugin: Talker, name: listed, "
                                      "autostart: true}]"), body)
    err = capfd.readouterr().err
    assert f"Restoring 3 node(s) from the state file '{path}' (written " in err
    assert "by process 4242), in place of the 1 node(s) the file lists" in err


def test_a_load_asking_for_a_restored_node_is_answered_with_it_and_one_asking_otherwise_replaces_it(
    context: Context, tmp_path: Path
) -> None:
    path = tmp_path / "state.json"
    rate = (Parameter("rate", value=5.0),)
    path.write_bytes(encode(ContainerState("/ComponentManager", 3, (
        record(1, "talker", parameters=rate, state="active"),
        record(2, "other", parameters=rate, state="inactive"),
    ))))

    async def body(app: ContainerApp) -> None:
        manager = app.manager
        restored = {loaded.full_name: loaded for loaded in manager.loaded()}
        # What a launch file started again sends: the same load.
        same = await manager.load(talker(parameters=[Parameter("rate", value=5.0)]))
        assert same is restored["/talker"] and state_of(same.node) == "active"
        # Asked for once: from now on another load of it is a duplicate, as always.
        with pytest.raises(LoadError, match="'/talker' is already loaded"):
            await manager.load(talker(parameters=[Parameter("rate", value=5.0)]))
        # The launch file changed since: its load wins.
        replaced = await manager.load(talker("other", parameters=[Parameter("rate", value=6.0)]))
        assert replaced.unique_id == 3 and not manager.holds(restored["/other"])
        assert state_of(replaced.node) == "unconfigured"

    run(context, container_file(path), body)


def test_writes_run_off_the_loop_and_changes_during_one_make_one_more(
    context: Context, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "state.json"
    release = threading.Event()
    writers: list[str] = []
    write = statefile.write_atomically

    def slow_write(target: Path, data: bytes) -> None:
        writers.append(threading.current_thread().name)
        release.wait(10.0)  # a disk that takes its time
        write(target, data)

    monkeypatch.setattr(statekeeper, "write_atomically", slow_write)

    async def body(app: ContainerApp) -> None:
        keeper = app.state
        assert keeper is not None
        await wait_until_async(lambda: writers, "the first write under way")
        started = keeper.writes
        # The loop goes on: nodes load while the write waits for the disk.
        for index in range(5):
            await app.manager.load(talker(f"t{index}"))
        assert keeper.writes == started and len(writers) == 1
        release.set()
        await keeper.flush()
        assert keeper.writes == started + 2, "the changes made during a write make one more write"
        assert set(recorded(path)) == {f"/t{index}" for index in range(5)}
        assert threading.current_thread().name not in writers

    run(context, container_file(path), body)


def test_a_second_container_on_the_same_file_neither_restores_nor_records(
    context: Context, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "state.json"
    evidence = encode(ContainerState("/ComponentManager", 2, (record(1, "talker", state="active"),)))
    path.write_bytes(evidence)
    lock = os.open(path.with_name("state.json.lock"), os.O_RDWR | os.O_CREAT)
    fcntl.flock(lock, fcntl.LOCK_EX)  # the first container, still running
    try:

        async def body(app: ContainerApp) -> None:
            assert held(app) == {}
            await app.manager.load(talker())

        run(context, container_file(path), body)
    finally:
        os.close(lock)
    assert path.read_bytes() == evidence, "neither rewritten nor removed"
    assert (
        f"state file '{path}': is in use by another container process (it holds '{path}.lock'); "
        "this container neither restores nor records its nodes"
    ) in capfd.readouterr().err


def test_the_state_file_parameter_must_be_a_string(context: Context, executor: AsyncioExecutor) -> None:
    # container run makes it a usage error, exit 2 (as any container parameter of the wrong type).
    with pytest.raises(InvalidParameterTypeException):
        ContainerApp.create(
            parse_config({"container": {"parameters": [{"state_file": 5}]}}), context=context, executor=executor
        )


def test_a_directory_named_as_the_state_file_is_left_alone(
    context: Context, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "kept").touch()

    async def body(app: ContainerApp) -> None:
        await app.manager.load(talker())

    run(context, container_file(tmp_path), body)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["kept"], "nothing moved, written or locked"
    assert (
        f"state file '{tmp_path}' is a directory: name a file in it; this container neither restores nor records "
        "its nodes"
    ) in capfd.readouterr().err
