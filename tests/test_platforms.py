"""The platform choices: ROS distribution and Python at set-up, the Fast DDS profile variable.

Each runs on whatever leg of CI's matrix runs it (``.ci/run``): the same
assertions hold on Jazzy and Kilted, Python 3.11 to 3.13.
"""

from __future__ import annotations

import importlib.metadata
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from container._runtime import DDS_PROFILE, PROFILE_VARIABLES, fast_dds_major, profile_variable
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
    assert out.stdout.strip() == str([(profile_variable(), str(DDS_PROFILE))])
    lines = _run_until_ready(empty_container, _environ())
    # Kilted warned on every start while the project set FASTRTPS_... there.
    assert not [line for line in lines if "deprecated" in line or "PROFILES_FILE" in line], lines


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
