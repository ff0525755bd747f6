"""The check tools are pinned exactly, and one documented command updates the pins (no network here)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from tests.container_support import REPO

PYPROJECT = REPO / "pyproject.toml"


def update_pins() -> ModuleType:
    """``.ci/update_pins.py``, the logic behind ``bash .ci/update-pins``, as a module."""
    spec = importlib.util.spec_from_file_location("update_pins", REPO / ".ci" / "update_pins.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_check_tool_is_pinned_exactly() -> None:
    pins = update_pins().read_pins(PYPROJECT.read_text(encoding="utf-8"))
    assert sorted(pins) == sorted(update_pins().CHECK_TOOLS)
    assert all(version[0].isdigit() for version in pins.values()), pins


def test_an_unpinned_tool_is_refused() -> None:
    module = update_pins()
    text = PYPROJECT.read_text(encoding="utf-8").replace('"ruff==', '"ruff>=')
    with pytest.raises(module.PinError, match=r"ruff>=.* is not pinned exactly"):
        module.read_pins(text)


def test_rewriting_changes_only_the_named_pins(tmp_path: Path) -> None:
    copy = tmp_path / "pyproject.toml"
    before = PYPROJECT.read_text(encoding="utf-8")
    copy.write_text(before, encoding="utf-8")
    result = subprocess.run(
        [sys.executable, ".ci/update_pins.py", "--pyproject", str(copy), "--set", "ruff==99.1.0", "types_pyyaml==7.0"],
        cwd=REPO, capture_output=True, text=True, timeout=30,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    after = copy.read_text(encoding="utf-8")
    pins = update_pins().read_pins(after)
    assert (pins["ruff"], pins["types-PyYAML"]) == ("99.1.0", "7.0")
    changed = [line for line in result.stdout.splitlines() if line[:1] in "+-" and line[:3] not in ("+++", "---")]
    assert sorted(changed) == sorted([
        '-    "ruff==' + update_pins().read_pins(before)["ruff"] + '",',
        '+    "ruff==99.1.0",',
        '-    "types-PyYAML==' + update_pins().read_pins(before)["types-PyYAML"] + '",',
        '+    "types-PyYAML==7.0",',
    ])
    assert PYPROJECT.read_text(encoding="utf-8") == before


def test_a_name_that_is_no_check_tool_changes_nothing(tmp_path: Path) -> None:
    copy = tmp_path / "pyproject.toml"
    copy.write_text(PYPROJECT.read_text(encoding="utf-8"), encoding="utf-8")
    result = subprocess.run(
        [sys.executable, ".ci/update_pins.py", "--pyproject", str(copy), "--set", "black==1.0"],
        cwd=REPO, capture_output=True, text=True, timeout=30,
    )
    assert result.returncode == 1
    assert "black is not a pinned check tool" in result.stdout
    assert copy.read_text(encoding="utf-8") == PYPROJECT.read_text(encoding="utf-8")


def test_the_update_command_exists_and_is_documented() -> None:
    script = REPO / ".ci" / "update-pins"
    assert script.is_file() and "update_pins.py" in script.read_text(encoding="utf-8")
    contributing = (REPO / "CONTRIBUTING.md").read_text(encoding="utf-8")
    checks = contributing.split("## The checks", 1)[1].split("\n## ", 1)[0]
    assert "bash .ci/update-pins" in checks
    assert "green CI red" in checks  # why the pins exist


# Makes a virtualenv (pip bootstrapped: seconds).
@pytest.mark.slow
def test_without_the_package_index_the_update_says_so_and_changes_nothing(tmp_path: Path) -> None:
    copy = tmp_path / "pyproject.toml"
    copy.write_text(PYPROJECT.read_text(encoding="utf-8"), encoding="utf-8")
    empty = tmp_path / "no-wheels"
    empty.mkdir()
    env = {**os.environ, "PIP_NO_INDEX": "1", "PIP_FIND_LINKS": str(empty)}
    result = subprocess.run(
        [sys.executable, ".ci/update_pins.py", "--pyproject", str(copy)],
        cwd=REPO, capture_output=True, text=True, timeout=120, env=env,
    )
    assert result.returncode == 2, result.stdout + result.stderr
    assert "is the package index reachable?" in result.stdout
    assert "pins unchanged" in result.stdout
    assert copy.read_text(encoding="utf-8") == PYPROJECT.read_text(encoding="utf-8")
