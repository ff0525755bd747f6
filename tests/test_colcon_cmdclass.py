"""``container.colcon``: an ament_python plugin's ``rclcpp_components`` entry, written with its data files.

colcon's own builds of such a plugin are tests/test_colcon.py's (slow); here
the commands run on a setuptools distribution as colcon's ``setup.py`` calls
describe it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from setuptools.dist import Distribution  # type: ignore[import-untyped]

from container import PluginError
from container.colcon import cmdclass, write_components

PLUGIN = """
from rclpy.lifecycle import LifecycleNode
from container import hookimpl

class Sonar(LifecycleNode):
    pass

@hookimpl
def register_node_types(register):
    register(Sonar)
"""

COMPONENTS = Path("share") / "ament_index" / "resource_index" / "rclcpp_components"


def distribution(**attrs: Any) -> Any:
    settings: dict[str, Any] = {
        "name": "sonar_nodes",
        "entry_points": {"container.plugins": ["sonar_nodes = sonar_nodes"]},
        "data_files": [("share/ament_index/resource_index/packages", ["resource/sonar_nodes"])],
    }
    return Distribution({**settings, **attrs})


@pytest.fixture
def sources(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The plugin's source directory, the working directory as under colcon."""
    (tmp_path / "src" / "sonar_nodes").mkdir(parents=True)
    (tmp_path / "src" / "sonar_nodes" / "__init__.py").write_text(PLUGIN, encoding="utf-8")
    monkeypatch.chdir(tmp_path / "src")
    return tmp_path / "src"


def test_the_commands_are_colcons_data_commands() -> None:
    commands = cmdclass()
    assert sorted(commands) in (["install_data"], ["install_data", "symlink_data"])
    assert all(command.__name__ == name for name, command in commands.items())


def test_the_entry_lists_the_node_types_the_plugin_registers(sources: Path, tmp_path: Path) -> None:
    path = write_components(distribution(), tmp_path / "install", build=None)

    assert path == tmp_path / "install" / COMPONENTS / "sonar_nodes"
    assert path.read_text() == "sonar_nodes::Sonar;sonar_nodes:Sonar\n"


def test_entry_points_as_setup_cfg_gives_them_are_read(sources: Path, tmp_path: Path) -> None:
    text = "[container.plugins]\nsonar_nodes = sonar_nodes\n"
    path = write_components(distribution(entry_points=text), tmp_path / "install", build=None)
    assert path.read_text().startswith("sonar_nodes::Sonar;")


def test_a_plugin_without_the_marker_of_its_package_is_refused_with_the_name(sources: Path, tmp_path: Path) -> None:
    with pytest.raises(PluginError, match=r"no package marker share/ament_index/resource_index/packages/sonar_nodes"):
        write_components(distribution(data_files=[("share/sonar_nodes", ["package.xml"])]), tmp_path, build=None)
    assert not (tmp_path / "share").exists()


def test_a_plugin_that_fails_to_import_fails_the_build_saying_why(sources: Path, tmp_path: Path) -> None:
    (sources / "sonar_nodes" / "__init__.py").write_text("import not_installed_anywhere\n", encoding="utf-8")
    with pytest.raises(PluginError, match=r"No module named 'not_installed_anywhere'") as caught:
        write_components(distribution(), tmp_path, build=None)
    assert caught.value.distribution == "sonar_nodes"


def test_a_distribution_without_plugins_is_refused(sources: Path, tmp_path: Path) -> None:
    with pytest.raises(PluginError, match=r"no 'container\.plugins' entry points"):
        write_components(distribution(entry_points={}), tmp_path, build=None)
