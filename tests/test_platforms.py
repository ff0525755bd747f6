"""The platform choices: ROS distribution and Python at set-up, the Fast DDS profile variable.

Each runs on whatever leg of CI's matrix runs it (``.ci/run``): the same
assertions hold on Jazzy and Kilted, Python 3.11 to 3.13.
"""

from __future__ import annotations

import importlib.metadata
import os
import signal
import subprocess
import sys
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path

import pytest

from container._runtime import PROFILE_VARIABLES, dds_profile, fast_dds_major, profile_variable
from tests.container_support import REPO
from tests.process_support import LoggedProcess

#: A profile of "the user's": Fast DDS names the file in its complaint about
#: the unknown element, which shows which profile it read.
USER_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <participant profile_name="users_own" is_default_profile="true">
    <rtps><element_only_the_users_profile_has>1</element_only_the_users_profile_has></rtps>
  </participant>
</profiles>
"""


def _distro() -> str:
    """The ROS distribution of the running rclpy, from the wheels' own metadata."""
    for distro in ("jazzy", "kilted"):
        try:
            importlib.metadata.version(f"ros-{distro}-rclpy")
        except importlib.metadata.PackageNotFoundError:
            continue
        return distro
    pytest.skip("rclpy is not from the ROS wheels of a known distribution")


def _environ(**changes: str) -> dict[str, str]:
    """This process's environment without any profile variable, plus ``changes``."""
    env = {key: value for key, value in os.environ.items() if key not in PROFILE_VARIABLES}
    env.update(changes)
    return env


@pytest.fixture
def empty_container(tmp_path: Path) -> Iterator[Path]:
    config = tmp_path / "empty.yaml"
    config.write_text("container: {name: platform_probe}\n", encoding="utf-8")
    yield config


def _run_until_ready(config: Path, env: dict[str, str]) -> list[str]:
    proc = LoggedProcess([sys.executable, "-m", "container", "run", str(config)], env=env, name="container")
    try:
        proc.wait_for_line("ready with")
        assert proc.stop() == 0, proc.output()
    finally:
        proc.close()
    return proc.lines


# -- the Fast DDS profile ----------------------------------------------------------------


def test_the_profile_variable_is_the_one_this_fast_dds_reads() -> None:
    """Fast DDS 3 (Kilted) reads FASTDDS_..., 2 (Jazzy) FASTRTPS_...: told by the library itself."""
    lib = Path(sys.prefix) / "lib"
    if any(lib.glob("libfastdds.so.3*")):
        assert (fast_dds_major(), profile_variable()) == (3, "FASTDDS_DEFAULT_PROFILES_FILE")
    elif any(lib.glob("libfastrtps.so.2*")):
        assert (fast_dds_major(), profile_variable()) == (2, "FASTRTPS_DEFAULT_PROFILES_FILE")
    else:
        pytest.skip(f"no Fast DDS library in {lib}")


# A container process.
@pytest.mark.slow
def test_the_projects_profile_is_used_quietly_when_the_user_names_none(empty_container: Path) -> None:
    code = (
        "import os; from container._runtime import use_fast_discovery; use_fast_discovery();"
        " print(sorted((k, v) for k, v in os.environ.items() if k.endswith('_DEFAULT_PROFILES_FILE')))"
    )
    out = subprocess.run([sys.executable, "-c", code], env=_environ(), capture_output=True, text=True, check=True)
    assert out.stdout.strip() == str([(profile_variable(), str(dds_profile()))])
    lines = _run_until_ready(empty_container, _environ())
    # Kilted warned on every start while the project set FASTRTPS_... there;
    # and Fast DDS refuses the whole file over one element it does not know.
    assert not [line for line in lines if "deprecated" in line or "PROFILES_FILE" in line or "XMLPARSER" in line], lines


#: Elements Fast DDS 2.x names otherwise than 3.x: (2.x, 3.x).
_RENAMED_IN_FAST_DDS_3 = {"heartbeatPeriod": "heartbeat_period"}


def test_the_profiles_for_both_fast_dds_majors_say_the_same() -> None:
    """One profile a major (each refuses the other's names); what they set must not drift apart."""

    def settings(element: ET.Element) -> object:
        tag = _RENAMED_IN_FAST_DDS_3.get(element.tag.rpartition("}")[2], element.tag.rpartition("}")[2])
        return (tag, sorted(element.attrib.items()), (element.text or "").strip(), [settings(e) for e in element])

    profiles = {major: ET.parse(dds_profile(major=major)).getroot() for major in (2, 3)}
    assert settings(profiles[2]) == settings(profiles[3])
    assert any(e.tag.endswith("}heartbeatPeriod") for e in profiles[2].iter())


# A container process.
@pytest.mark.slow
@pytest.mark.parametrize("variable", PROFILE_VARIABLES)
def test_a_users_own_profile_always_wins(variable: str, empty_container: Path, tmp_path: Path) -> None:
    if fast_dds_major() < 3 and variable != profile_variable():
        pytest.skip(f"Fast DDS {fast_dds_major()} does not read {variable}")
    profile = tmp_path / "users_own.xml"
    profile.write_text(USER_PROFILE, encoding="utf-8")
    env = _environ(**{variable: str(profile)})
    code = (
        "import os; from container._runtime import use_fast_discovery; use_fast_discovery();"
        " print(sorted(k for k in os.environ if k.endswith('_DEFAULT_PROFILES_FILE')))"
    )
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == str([variable])  # the project's is not set beside it
    lines = _run_until_ready(empty_container, env)
    # Fast DDS read the user's file: its parser names it.
    assert [line for line in lines if f"Error parsing '{profile}'" in line], lines


#: A writer of two topics: a reliable one at 5 Hz, each message its number and
#: when it was sent (CLOCK_MONOTONIC, one clock for every process here); and
#: a best-effort flood of 60 kB at 100 Hz that overfills a stopped reader's buffers.
_WRITER = """
import sys, time, rclpy
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from std_msgs.msg import String
rclpy.init()
node = Node("heartbeat_writer")
flood = node.create_publisher(String, "/heartbeat_probe_flood", qos_profile_sensor_data)
talk = node.create_publisher(String, "/heartbeat_probe", 10)
pad = "x" * 60000
tick = 0
start = time.monotonic()
while True:
    flood.publish(String(data=f"{tick}:{pad}"))
    if tick % 20 == 0:
        talk.publish(String(data=f"{tick // 20} {time.monotonic()}"))
    tick += 1
    time.sleep(max(0.0, start + tick / 100 - time.monotonic()))
"""

#: Its reader: a line per reliable message (number, sent, received), and one
#: for each gap in the flood (what full buffers lost).
_READER = """
import time, rclpy
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from std_msgs.msg import String
rclpy.init()
node = Node("heartbeat_reader")
last = [None]
def on_talk(message):
    number, sent = message.data.split()
    print("talk", number, sent, time.monotonic(), flush=True)
def on_flood(message):
    tick = int(message.data.partition(":")[0])
    if last[0] is not None and tick > last[0] + 1:
        print("flood lost", tick - last[0] - 1, flush=True)
    last[0] = tick
node.create_subscription(String, "/heartbeat_probe", on_talk, 10)
node.create_subscription(String, "/heartbeat_probe_flood", on_flood, qos_profile_sensor_data)
rclpy.spin(node)
"""


# Three 1 s stops of a reader process, about 8 s.
@pytest.mark.slow
def test_a_reliable_reader_that_lost_messages_has_them_again_within_a_heartbeat() -> None:
    """The project's profile has writers send a heartbeat every 100 ms, not Fast DDS's 3 s.

    A reliable reader that lost a message delivers nothing after it until
    the writer's next heartbeat lets it ask for what it misses. The reader
    is stopped for 1 s (as a loaded machine can leave a process unrun) while
    a flood fills the transport's buffers; once it runs again, it must have
    every message sent before within 0.4 s, after each of three stops. It had
    them 0.01 s after; with Fast DDS's default 0.43-0.97 s after a stop, the
    worst of three 0.81 s or more in each of 8 runs, and up to 3 s by the
    heartbeat's phase.
    """
    env = _environ(**{profile_variable(): str(dds_profile())})
    reader = LoggedProcess([sys.executable, "-c", _READER], env=env, name="reader")
    writer = LoggedProcess([sys.executable, "-c", _WRITER], env=env, name="writer")
    try:
        reader.wait_for_line("talk ", timeout=20)
        first = len(reader.lines)
        caught_up: list[float] = []
        for _ in range(3):
            start = len(reader.lines)
            os.killpg(reader.process.pid, signal.SIGSTOP)
            try:
                threading.Event().wait(1.0)  # the fault itself: 1 s without the CPU
            finally:
                os.killpg(reader.process.pid, signal.SIGCONT)
            resumed = time.monotonic()
            before: list[float] = []
            # Until a message sent 1 s after the reader resumed has come:
            # every one sent before has come by then, or is lost for good.
            while True:
                line = reader.wait_for_line("talk ", start=start, timeout=10)
                start = reader.lines.index(line, start) + 1
                _, _, sent, at = line.split()
                if float(sent) < resumed:
                    before.append(float(at))
                elif float(sent) >= resumed + 1.0:
                    break
            caught_up.append(max(before, default=resumed) - resumed)
        # The stops did what they are for: the reader's buffers overflowed.
        reader.wait_for_line("flood lost", start=first, timeout=1)
        assert max(caught_up) < 0.4, f"s after resuming: {caught_up}\n{reader.output()}"
    finally:
        writer.close()
        reader.close()


# -- set-up: the distribution and the Python, one clear line for what is not supported ---------------


def _setup(tmp_path: Path, **env: str) -> subprocess.CompletedProcess[str]:
    environ = {**os.environ, "VENV": str(tmp_path / "venv"), **env}
    return subprocess.run(
        ["bash", str(REPO / ".ci" / "setup")], env=environ, capture_output=True, text=True, timeout=60
    )


def test_setup_refuses_a_distribution_it_has_no_table_for_in_one_line(tmp_path: Path) -> None:
    result = _setup(tmp_path, ROS_DISTRO="humble")
    assert result.returncode != 0
    assert result.stderr.splitlines() == [
        "setup: ROS_DISTRO=humble is not supported (supported: jazzy, kilted)"
    ], result.stderr
    assert not (tmp_path / "venv" / "bin").exists()


# Runs .ci/setup.
@pytest.mark.slow
@pytest.mark.parametrize("python", ["python3.10", "/nonexistent/python3"])
def test_setup_refuses_a_python_it_does_not_support_in_one_line(python: str, tmp_path: Path) -> None:
    result = _setup(tmp_path, PYTHON=python)
    assert result.returncode != 0
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"setup: PYTHON={python} "), result.stderr
    assert "supported are 3.11, 3.12 and 3.13" in lines[0] or "does not run" in lines[0]
    assert not (tmp_path / "venv" / "bin").exists()


def test_the_venvs_activate_sets_the_ros_environment_and_deactivate_restores_it() -> None:
    activate = Path(sys.prefix) / "bin" / "activate"
    if not (Path(sys.prefix) / ".ros-distro").is_file():
        pytest.skip("not a virtualenv made by .ci/setup")
    script = (
        f"source {activate}; echo $ROS_DISTRO $ROS_VERSION $ROS_PYTHON_VERSION;"
        ' case ":$AMENT_PREFIX_PATH:" in *":$VIRTUAL_ENV:"*) echo on-path;; esac;'
        " deactivate; echo ${ROS_DISTRO-unset} ${AMENT_PREFIX_PATH-unset}"
    )
    env = {key: value for key, value in os.environ.items() if not key.startswith(("ROS_", "AMENT_"))}
    env["ROS_DOMAIN_ID"] = os.environ.get("ROS_DOMAIN_ID", "0")
    out = subprocess.run(["bash", "-c", script], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.splitlines() == [f"{_distro()} 2 3", "on-path", "unset unset"], out.stdout
