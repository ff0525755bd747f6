"""``container.build_backend``: the ament index entries it adds to a plugin's wheel."""

from __future__ import annotations

import base64
import csv
import hashlib
import io
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from container.build_backend import add_index_entries
from tests.container_support import REPO

INDEX = "demo_plugin-1.0.data/data/share/ament_index/resource_index"

PLUGIN = """
from rclpy.lifecycle import LifecycleNode
from container import hookimpl

class Beeper(LifecycleNode):
    pass

@hookimpl
def register_node_types(register):
    register(Beeper)
    register(Beeper, name="Alias")
"""


def make_wheel(path: Path, module: str, *, entry_points: bool = True) -> Path:
    info = "demo_plugin-1.0.dist-info"
    files = {
        "demo_plugin_nodes.py": module.encode(),
        f"{info}/METADATA": b"Metadata-Version: 2.1\nName: demo-plugin\nVersion: 1.0\n",
        f"{info}/WHEEL": b"Wheel-Version: 1.0\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
    }
    if entry_points:
        files[f"{info}/entry_points.txt"] = b"[container.plugins]\ndemo = demo_plugin_nodes\n"
    rows = [[name, "sha256=x", str(len(content))] for name, content in files.items()] + [[f"{info}/RECORD", "", ""]]
    record = io.StringIO()
    csv.writer(record, lineterminator="\n").writerows(rows)
    wheel = path / "demo_plugin-1.0-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as archive:
        for name, content in files.items():
            archive.writestr(name, content)
        archive.writestr(f"{info}/RECORD", record.getvalue())
    return wheel


def record_of(wheel: Path) -> dict[str, tuple[str, str]]:
    with zipfile.ZipFile(wheel) as archive:
        text = archive.read("demo_plugin-1.0.dist-info/RECORD").decode()
    return {row[0]: (row[1], row[2]) for row in csv.reader(io.StringIO(text)) if row}


def test_a_plugin_wheel_gets_its_package_and_component_types(tmp_path: Path) -> None:
    wheel = make_wheel(tmp_path, PLUGIN)

    add_index_entries(wheel, source=tmp_path)

    with zipfile.ZipFile(wheel) as archive:
        assert archive.read(f"{INDEX}/packages/demo_plugin") == b""
        assert archive.read(f"{INDEX}/rclcpp_components/demo_plugin").decode() == (
            "demo_plugin::Alias;demo_plugin_nodes:Beeper\ndemo_plugin::Beeper;demo_plugin_nodes:Beeper\n"
        )
        content = archive.read(f"{INDEX}/rclcpp_components/demo_plugin")
    digest = base64.urlsafe_b64encode(hashlib.sha256(content).digest()).rstrip(b"=").decode()
    record = record_of(wheel)
    assert record[f"{INDEX}/rclcpp_components/demo_plugin"] == (f"sha256={digest}", str(len(content)))
    assert record["demo_plugin-1.0.dist-info/RECORD"] == ("", "")
    assert list(record)[-1] == "demo_plugin-1.0.dist-info/RECORD"


def test_a_plugin_that_fails_to_import_gets_its_package_only_and_says_why(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    wheel = make_wheel(tmp_path, "import not_installed_anywhere\n")

    add_index_entries(wheel, source=tmp_path)

    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
    assert f"{INDEX}/packages/demo_plugin" in names
    assert f"{INDEX}/rclcpp_components/demo_plugin" not in names
    assert "No module named 'not_installed_anywhere'" in capsys.readouterr().err


def test_a_wheel_without_plugins_is_left_as_it_is(tmp_path: Path) -> None:
    wheel = make_wheel(tmp_path, PLUGIN, entry_points=False)
    before = wheel.read_bytes()

    add_index_entries(wheel, source=tmp_path)

    assert wheel.read_bytes() == before


# A build: pip, then CMake's configure (about 5 s).
@pytest.mark.slow
def test_a_plugin_built_by_scikit_build_cores_own_backend_is_refused_with_the_fix(tmp_path: Path) -> None:
    # Its wheel would load but carry no ament index entries: ros2 pkg list and
    # ros2 component types would not see the plugin (issue 45).
    source = tmp_path / "beacon"
    shutil.copytree(REPO / "examples" / "beacon_plugin", source, ignore=shutil.ignore_patterns("tests", "build"))
    pyproject = source / "pyproject.toml"
    text = pyproject.read_text(encoding="utf-8")
    assert 'build-backend = "container.build_backend"' in text
    pyproject.write_text(
        text.replace('build-backend = "container.build_backend"', 'build-backend = "scikit_build_core.build"'),
        encoding="utf-8",
    )
    result = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-build-isolation", "--no-deps", "--wheel-dir", tmp_path / "dist",
         source],
        capture_output=True, text=True, timeout=300,
    )
    said = " ".join((result.stdout + result.stderr).split())  # CMake wraps its messages
    assert result.returncode != 0, said
    assert (
        "lifecycle_container: beacon-nodes is a plugin (container.plugins entry points) built by scikit-build-core's "
        "own backend, so its wheel would carry no ament index entries"
    ) in said
    assert 'in pyproject.toml, [build-system] build-backend = "container.build_backend".' in said
    assert not list((tmp_path / "dist").glob("*.whl"))
