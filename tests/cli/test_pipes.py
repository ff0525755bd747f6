"""Every command's output closed early (``container list | head -1``): exit 0, no traceback.

Each command runs as its own process, its standard output a real pipe whose
reader goes away: after the first line with unbuffered output (each line is
a write, as under ``ros2 launch``), and before anything is written with
Python's default block buffering (the command's last flush, at its exit, is
the write that fails). Standard error goes to a file, read afterwards.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

from tests.component_support import IMPORT_ROOT, install_test_plugin
from tests.container_support import REPO, ContainerProcess
from tests.waiting import wait_until

pytestmark = pytest.mark.slow  # one container and about thirty command processes

CONTAINER = """\
container:
  name: ComponentManager
nodes:
  - package: lifecycle_container
    plugin: lifecycle_container::Talker
    name: talker
  - package: lifecycle_container
    plugin: lifecycle_container::Listener
    name: listener
"""

#: Commands that only read: each prints more than one line against the container above.
READING: list[tuple[str, ...]] = [
    ("list",),
    ("list", "/ComponentManager"),
    ("types",),
    ("lifecycle", "nodes"),
    ("lifecycle", "get"),
    ("lifecycle", "list", "/talker"),
    ("top",),
    ("top", "--once"),
    ("top", "--json"),
]

#: What a command's standard error must never hold when its output closed early.
NOISE = ("Traceback", "BrokenPipeError", "Exception ignored")


@pytest.fixture(scope="module")
def container(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ContainerProcess]:
    path = tmp_path_factory.mktemp("pipes") / "container.yaml"
    path.write_text(CONTAINER, encoding="utf-8")
    process = ContainerProcess(path)
    try:
        process.wait_for_line("ready with 2 node(s)")
        yield process
    finally:
        process.close()


def environment(*, buffered: bool) -> dict[str, str]:
    env = dict(os.environ)
    env.pop("PYTHONUNBUFFERED", None)
    if not buffered:
        env["PYTHONUNBUFFERED"] = "1"
    return env


def command(args: Sequence[str]) -> list[str]:
    return [sys.executable, "-m", "container", *args]


def clean(stderr: Path) -> str:
    text = stderr.read_text(encoding="utf-8", errors="replace")
    assert not [word for word in NOISE if word in text], text
    return text


def closed_after_first_line(args: Sequence[str], stderr: Path) -> tuple[int, str]:
    """Run ``container ARGS``; read one line of its output, close the pipe, wait: its status and first line."""
    with stderr.open("w", encoding="utf-8") as errors:
        process = subprocess.Popen(
            command(args), cwd=REPO, stdout=subprocess.PIPE, stderr=errors, text=True,
            env=environment(buffered=False),
        )
        assert process.stdout is not None
        first = process.stdout.readline()
        process.stdout.close()
        try:
            return process.wait(timeout=30), first
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()


def closed_at_once(args: Sequence[str], stderr: Path) -> int:
    """Run ``container ARGS`` with an output pipe nobody reads from the start: its status."""
    reader, writer = os.pipe()
    try:
        with stderr.open("w", encoding="utf-8") as errors:
            process = subprocess.Popen(
                command(args), cwd=REPO, stdout=writer, stderr=errors, env=environment(buffered=True)
            )
    finally:
        os.close(writer)
        os.close(reader)
    try:
        return process.wait(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def output(args: Sequence[str]) -> str:
    result = subprocess.run(command(args), cwd=REPO, capture_output=True, text=True, timeout=30)
    assert result.returncode == 0, result.stderr
    return result.stdout


@pytest.mark.parametrize("args", READING, ids=" ".join)
def test_a_reading_command_ends_quietly_when_its_reader_goes_after_one_line(
    container: ContainerProcess, args: tuple[str, ...], tmp_path: Path
) -> None:
    code, first = closed_after_first_line(args, tmp_path / "stderr")
    assert first, "no first line"
    assert code == 0, clean(tmp_path / "stderr")
    clean(tmp_path / "stderr")


@pytest.mark.parametrize("args", READING, ids=" ".join)
def test_a_reading_command_ends_quietly_when_its_output_is_closed_from_the_start(
    container: ContainerProcess, args: tuple[str, ...], tmp_path: Path
) -> None:
    code = closed_at_once(args, tmp_path / "stderr")
    assert code == 0, clean(tmp_path / "stderr")
    clean(tmp_path / "stderr")


#: Every command line with ``--json`` output (tests/cli/test_json.py keeps the list whole).
JSON_OUTPUT: list[tuple[str, ...]] = [
    ("top", "--json"), ("top", "--json", "--once"), ("top", "--json", "/ComponentManager"),
]


@pytest.mark.parametrize("args", JSON_OUTPUT, ids=" ".join)
def test_json_output_is_one_document(container: ContainerProcess, args: tuple[str, ...]) -> None:
    (load,) = json.loads(output(args))
    assert load["container"] == "/ComponentManager"


def test_acting_commands_do_all_they_were_asked_with_nobody_reading(
    container: ContainerProcess, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    stderr = tmp_path / "stderr"
    for name in ("one", "two"):
        load = ("load", "/ComponentManager", "lifecycle_container", "lifecycle_container::Talker", "-n", name)
        assert closed_at_once(load, stderr) == 0, clean(stderr)
        clean(stderr)
    listed = output(("list", "/ComponentManager")).splitlines()
    ids = [line.split()[0] for line in listed if line.split()[1] in ("/one", "/two")]
    assert len(ids) == 2, listed

    # Its first line read, the pipe closed: the second unload still happens.
    code, first = closed_after_first_line(("unload", "/ComponentManager", *ids), stderr)
    assert (code, first) == (0, f"Unloaded component {ids[0]} from '/ComponentManager' container node\n"), clean(stderr)
    clean(stderr)
    assert output(("list", "/ComponentManager")) == "1  /talker\n2  /listener\n"

    assert closed_at_once(("lifecycle", "set", "/talker", "configure"), stderr) == 0, clean(stderr)
    clean(stderr)
    assert output(("lifecycle", "get", "/talker")) == "inactive [2]\n"

    # Two plugins in no prefix of their own: both registered in the one named.
    prefix = tmp_path / "prefix"
    sites = [install_test_plugin(tmp_path / "site", distribution="test-nodes"),
             install_test_plugin(tmp_path / "faults", distribution="test-faults", module="tests.fault_plugin")]
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([*map(str, sites), str(IMPORT_ROOT)]))
    code, first = closed_after_first_line(("index", "--prefix", str(prefix)), stderr)
    assert (code, first.startswith(f"ament index of {prefix}")) == (0, True), clean(stderr)
    clean(stderr)
    for package in ("test_nodes", "test_faults"):
        assert (prefix / "share" / "ament_index" / "resource_index" / "rclcpp_components" / package).is_file()


def test_a_server_whose_log_reader_goes_serves_on_and_stops_cleanly(tmp_path: Path) -> None:
    """``container run FILE 2>&1 | head -1``: the container outlives its reader; SIGINT then ends it with 0."""
    config = tmp_path / "unread.yaml"
    config.write_text(
        "container:\n  name: Unread\nnodes:\n"
        "  - {package: lifecycle_container, plugin: lifecycle_container::Listener, name: unread_ear}\n",
        encoding="utf-8",
    )
    process = subprocess.Popen(
        command(("run", str(config))), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=environment(buffered=False),
    )
    try:
        assert process.stdout is not None
        assert process.stdout.readline(), "no first line"
        process.stdout.close()
        # Its one node is listed once loaded, just before it says it is ready.
        wait_until(
            lambda: "/unread_ear" in output(("list", "/Unread", "--spin-time", "5")),
            "the unread container's node",
            timeout=30,
        )
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=20) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def test_a_manager_whose_log_reader_goes_serves_on_and_stops_cleanly() -> None:
    """``container manager 2>&1 | head -1``: its first line comes once it is ready; SIGINT then ends it with 0."""
    args = ("manager", "--name", "unread_manager", "-p", "node_names:=[/absent]", "-p", "autostart:=true")
    process = subprocess.Popen(
        command(args), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=environment(buffered=False),
    )
    try:
        assert process.stdout is not None
        assert "STARTUP" in process.stdout.readline()
        process.stdout.close()
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=20) == 0
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def test_a_failure_keeps_its_status_with_nobody_reading(container: ContainerProcess, tmp_path: Path) -> None:
    code = closed_at_once(("lifecycle", "get", "/absent", "--spin-time", "0.3"), tmp_path / "stderr")
    assert code == 1
    assert clean(tmp_path / "stderr") == "Node not found\n"
