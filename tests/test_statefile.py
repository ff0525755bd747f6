"""The state file alone: its format read back as written, every way a file is refused, the atomic write."""

from __future__ import annotations

import json
import math
import os
import stat
from pathlib import Path
from typing import Any

import pytest
from rclpy.parameter import Parameter

from container._errors import StateFileError
from container._statefile import (
    FORMAT,
    ContainerState,
    NodeRecord,
    decode,
    encode,
    read_state,
    same_parameters,
    set_aside,
    temporary_files,
    write_atomically,
)

EVERY_TYPE: tuple[Parameter[Any], ...] = (
    Parameter("flag", value=True),
    Parameter("count", value=3),
    Parameter("rate", value=5.0),
    Parameter("message", value="héllo \"quoted\"\nline"),
    Parameter("raw", Parameter.Type.BYTE_ARRAY, [b"\x00", b"\xff"]),
    Parameter("flags", value=[True, False]),
    Parameter("counts", value=[1, 2]),
    Parameter("rates", value=[1.0, 2.5]),
    Parameter("names", value=["a", "b"]),
)

STATE = ContainerState(
    "/launch_ns/my_container",
    5,
    (
        NodeRecord(
            unique_id=1, package="lifecycle_container", plugin="lifecycle_container::Talker", name="talker",
            namespace="/demo", full_name="/demo/talker", remap_rules=("chatter:=/demo/chatter",),
            parameters=EVERY_TYPE, changed_parameters=(Parameter("rate", value=7.5),),
            extra_arguments=(Parameter("use_intra_process_comms", value=True),), log_level=10, state="active",
        ),
        NodeRecord(
            unique_id=4, package="test_nodes", plugin="test_nodes::Idle", name=None, namespace=None,
            full_name="/idle",
        ),
    ),
)


def typed(parameters: tuple[Parameter[Any], ...]) -> list[tuple[str, Parameter.Type, Any]]:
    return [(p.name, p.type_, list(p.value) if isinstance(p.value, list | tuple) else p.value) for p in parameters]


def document(**changes: Any) -> dict[str, Any]:
    """A valid file's JSON, with ``changes`` made to its top level."""
    loaded: dict[str, Any] = json.loads(encode(STATE))
    loaded.update(changes)
    return loaded


def as_bytes(value: Any) -> bytes:
    return json.dumps(value).encode()


def test_a_state_reads_back_as_written_every_parameter_keeping_its_type() -> None:
    read = decode(encode(STATE, pid=42, now=0.0), source="state.json")
    assert (read.container, read.next_unique_id, read.pid, read.written) == (
        "/launch_ns/my_container", 5, 42, "1970-01-01T00:00:00Z"
    )
    talker, idle = read.nodes
    assert typed(talker.parameters) == typed(EVERY_TYPE)
    assert [type(p.value) for p in talker.parameters[:3]] == [bool, int, float]
    assert typed(talker.changed_parameters) == [("rate", Parameter.Type.DOUBLE, 7.5)]
    assert typed(talker.extra_arguments) == [("use_intra_process_comms", Parameter.Type.BOOL, True)]
    assert (talker.remap_rules, talker.log_level, talker.state, talker.type_label) == (
        ("chatter:=/demo/chatter",), 10, "active", "lifecycle_container::Talker"
    )
    assert (idle.name, idle.namespace, idle.state, idle.parameters) == (None, None, None, ())


def test_a_double_written_by_hand_as_a_whole_number_is_still_a_double() -> None:
    edited = document()
    edited["nodes"][1]["parameters"] = [{"name": "rate", "type": "double", "value": 5}]
    (rate,) = decode(as_bytes(edited), source="s").nodes[1].parameters
    assert (rate.type_, rate.value) == (Parameter.Type.DOUBLE, 5.0)


def test_nan_survives_and_compares_equal_to_itself() -> None:
    nan = (Parameter("x", value=math.nan),)
    record = NodeRecord(unique_id=1, package="p", plugin="p::T", name="n", namespace=None, full_name="/n",
                        parameters=nan)
    (read,) = decode(encode(ContainerState("/c", 2, (record,))), source="s").nodes[0].parameters
    assert math.isnan(read.value)
    assert same_parameters(nan, (read,))
    assert not same_parameters(nan, (Parameter("x", value=1.0),))
    assert not same_parameters((Parameter("x", value=1),), (Parameter("x", value=1.0),))


BAD = [
    ("truncated", encode(STATE)[:-40], "not JSON (Unterminated string"),
    ("empty", b"", "not JSON (Expecting value at line 1 column 1)"),
    ("not UTF-8", b"\xff\xfe{}", "not UTF-8 text"),
    ("some other JSON", as_bytes({"nodes": []}),
     'not a container state file (no "format": "lifecycle_container.state")'),
    ("a list", as_bytes([1, 2]), "not a container state file"),
    ("a newer version", as_bytes(document(version=2)),
     "state file version 2: this container reads version 1 only (written by another release"),
    ("no version", as_bytes({"format": FORMAT}), "state file version None"),
    ("next id of the wrong type", as_bytes(document(next_unique_id="5")), "next_unique_id: expected an integer >= 1"),
    ("a node that is no object", as_bytes(document(nodes=[3])), "nodes[0]: expected an object, not int"),
    ("an unknown state", as_bytes(document(nodes=[{**document()["nodes"][1], "state": "dancing"}])),
     "nodes[0].state: expected one of unconfigured, inactive, active, finalized or null, not 'dancing'"),
    ("an unknown parameter type", as_bytes(document(nodes=[{
        **document()["nodes"][1], "parameters": [{"name": "x", "type": "float", "value": 1.0}]}])),
     "nodes[0].parameters[0].type: expected one of bool, integer, double"),
    ("a value of the wrong type", as_bytes(document(nodes=[{
        **document()["nodes"][1], "parameters": [{"name": "x", "type": "integer", "value": "one"}]}])),
     "nodes[0].parameters[0].value: does not fit the type 'integer'"),
    ("a byte out of range", as_bytes(document(nodes=[{
        **document()["nodes"][1], "parameters": [{"name": "x", "type": "byte_array", "value": [256]}]}])),
     "nodes[0].parameters[0].value: does not fit the type 'byte_array': expected integers 0 to 255"),
    ("a unique id twice", as_bytes(document(nodes=[document()["nodes"][1]] * 2)), "unique_id 4 is recorded twice"),
    ("an id the next one does not pass", as_bytes(document(next_unique_id=4)),
     "unique_id 4 is not below next_unique_id 4"),
    ("a node without its type", as_bytes(document(nodes=[{"unique_id": 1}])), "nodes[0]: missing 'package'"),
]


@pytest.mark.parametrize(("data", "message"), [(data, message) for _, data, message in BAD], ids=[w for w, _, _ in BAD])
def test_a_file_that_is_not_a_state_this_container_reads_is_refused_whole(data: bytes, message: str) -> None:
    with pytest.raises(StateFileError) as caught:
        decode(data, source="/var/lib/state.json")
    assert str(caught.value).startswith("state file '/var/lib/state.json': "), str(caught.value)
    assert message in caught.value.reason, caught.value.reason
    assert caught.value.path == "/var/lib/state.json"


def test_read_state_is_none_without_a_file_and_refuses_what_it_cannot_read(tmp_path: Path) -> None:
    path = tmp_path / "state.json"
    assert read_state(path) is None
    path.mkdir()  # something that is there but cannot be read as a file
    with pytest.raises(StateFileError, match="cannot be read: Is a directory"):
        read_state(path)
    path.rmdir()
    with path.open("wb") as file:
        file.truncate(16 * 1024 * 1024 + 1)
    with pytest.raises(StateFileError, match="larger than 16 MiB: not a state file"):
        read_state(path)


def test_a_write_replaces_the_file_whole_readable_by_its_owner_only(tmp_path: Path) -> None:
    path = tmp_path / "state.json"
    path.write_bytes(b"old")
    write_atomically(path, encode(STATE))
    assert read_state(path) is not None
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]


def test_a_write_that_fails_midway_leaves_the_old_file_and_no_temporary_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "state.json"
    write_atomically(path, encode(STATE))
    before = path.read_bytes()

    def full_disk(descriptor: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full_disk)
    with pytest.raises(OSError, match="No space left"):
        write_atomically(path, encode(ContainerState("/launch_ns/my_container", 9)))
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]


def test_the_temporary_file_of_a_write_cut_short_is_found(tmp_path: Path) -> None:
    path = tmp_path / "state.json"
    leftover = tmp_path / ".state.json.k2j3h4.tmp"  # mkstemp's name for a write to path
    leftover.write_bytes(b"{")
    (tmp_path / ".other.json.abc.tmp").write_bytes(b"{")
    assert temporary_files(path) == [leftover]


def test_a_bad_file_is_set_aside_never_over_an_earlier_one(tmp_path: Path) -> None:
    path = tmp_path / "state.json"
    path.write_bytes(b"first")
    first = set_aside(path, now=0.0)
    path.write_bytes(b"second")
    second = set_aside(path, now=0.0)
    assert first.name.startswith("state.json.bad-19") and second.name == f"{first.name}-2"
    assert (first.read_bytes(), second.read_bytes(), path.exists()) == (b"first", b"second", False)
