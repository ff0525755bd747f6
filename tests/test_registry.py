"""Plugin discovery through real distributions on disk.

Each test writes ``<name>-<version>.dist-info`` folders and plugin modules into
its own directories on ``sys.path``, under an entry point group of its own, so
``importlib.metadata`` finds exactly these plugins and nothing installed.
"""

from __future__ import annotations

import importlib
import logging
import re
import shutil
import sys
import textwrap
from collections.abc import Callable, Iterator
from dataclasses import FrozenInstanceError
from pathlib import Path

import pytest
from rclpy.lifecycle import LifecycleNode

from container._errors import LoadError, PluginError
from container._hookspecs import hookimpl
from container._registry import (
    ENTRY_POINT_GROUP,
    NodeType,
    PluginRegistry,
    ros_package_name,
)

GOOD = """
from rclpy.lifecycle import LifecycleNode
from container._hookspecs import hookimpl

class Talker(LifecycleNode):
    pass

class FastListener(LifecycleNode):
    pass

@hookimpl
def register_node_types(register):
    register(Talker)
    register(FastListener, name="Listener")
"""

MakeDist = Callable[..., Path]


@pytest.fixture(autouse=True)
def _clean_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for suffix in ("PLUGINS_BLOCK", "PLUGINS_ALLOW", "TRACE_HOOKS"):
        monkeypatch.delenv(f"CONTAINER_{suffix}", raising=False)


@pytest.fixture
def group(request: pytest.FixtureRequest) -> str:
    """An entry point group nobody else uses, so installed plugins stay out."""
    return "container.test_plugins." + re.sub(r"\W+", "_", request.node.name)


@pytest.fixture
def make_dist(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, group: str
) -> Iterator[MakeDist]:
    """Install a distribution: ``make_dist(name, entry_points, **modules)``.

    Returns its ``.dist-info`` directory.

    ``entry_points`` maps entry point names to ``module`` or ``module:attr``;
    ``modules`` maps module names to their source. Each distribution gets a
    ``sys.path`` entry of its own, after the previous ones, so discovery order
    is creation order (the order inside one directory is the file system's).
    """
    monkeypatch.setattr(sys, "path", list(sys.path))

    def make(
        name: str,
        entry_points: dict[str, str],
        *,
        ep_group: str | None = None,
        **modules: str,
    ) -> Path:
        site = tmp_path / f"site{len(list(tmp_path.iterdir()))}"
        # Named as pip names it (PEP 427): importlib.metadata finds a
        # distribution by name only under that spelling.
        info = site / f"{re.sub(r'[-_.]+', '_', name)}-1.0.dist-info"
        info.mkdir(parents=True)
        (info / "METADATA").write_text(
            f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n"
        )
        lines = [f"[{ep_group or group}]"]
        lines += [f"{ep} = {target}" for ep, target in entry_points.items()]
        (info / "entry_points.txt").write_text("\n".join(lines) + "\n")
        for module, source in modules.items():
            (site / f"{module}.py").write_text(textwrap.dedent(source))
        sys.path.append(str(site))
        importlib.invalidate_caches()
        return info

    yield make
    for module_name, module in list(sys.modules.items()):
        if str(getattr(module, "__file__", None) or "").startswith(str(tmp_path)):
            del sys.modules[module_name]


# -- discovery and naming -----------------------------------------------------


def test_good_plugin_registers_types_named_after_its_package(
    make_dist: MakeDist, group: str
) -> None:
    make_dist("Acme-Sensors.Extra", {"nodes": "acme_nodes"}, acme_nodes=GOOD)

    registry = PluginRegistry(group=group)

    assert registry.failures == []
    assert sorted(registry.types) == [
        "acme_sensors_extra::Listener",
        "acme_sensors_extra::Talker",
    ]
    talker = registry.types["acme_sensors_extra::Talker"]
    assert talker.package == "acme_sensors_extra"
    assert talker.name == "Talker"
    assert talker.distribution == "Acme-Sensors.Extra"
    assert talker.node_class.__name__ == "Talker"
    assert issubclass(talker.node_class, LifecycleNode)
    assert registry.types["acme_sensors_extra::Listener"].node_class.__name__ == (
        "FastListener"
    )


def test_package_name_follows_ros_spelling() -> None:
    assert ros_package_name("My-Plugin.Nodes") == "my_plugin_nodes"
    assert ros_package_name("my_plugin") == "my_plugin"
    assert ros_package_name("a-.b") == "a_b"


def test_packages_lists_full_type_names_sorted(make_dist: MakeDist, group: str) -> None:
    make_dist("zeta", {"nodes": "zeta_nodes"}, zeta_nodes=GOOD)
    make_dist("alpha", {"nodes": "alpha_nodes"}, alpha_nodes=GOOD)

    registry = PluginRegistry(group=group)

    assert registry.packages() == {
        "alpha": ["alpha::Listener", "alpha::Talker"],
        "zeta": ["zeta::Listener", "zeta::Talker"],
    }
    assert list(registry.packages()) == ["alpha", "zeta"]


def test_default_group_is_container_plugins(
    make_dist: MakeDist, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert ENTRY_POINT_GROUP == "container.plugins"
    make_dist(
        "default-group-probe",
        {"nodes": "default_group_probe"},
        ep_group="container.plugins",
        default_group_probe=GOOD,
    )

    registry = PluginRegistry()

    assert "default_group_probe::Talker" in registry.types


def test_types_mapping_and_node_type_are_read_only(
    make_dist: MakeDist, group: str
) -> None:
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)
    registry = PluginRegistry(group=group)
    talker = registry.types["good::Talker"]

    with pytest.raises(TypeError):
        registry.types["good::Other"] = talker  # type: ignore[index]
    with pytest.raises(FrozenInstanceError):
        talker.name = "Other"  # type: ignore[misc]
    assert talker.full_name == "good::Talker"


# -- broken plugins are reported and skipped ----------------------------------


def test_import_error_is_reported_and_good_plugin_still_loads(
    make_dist: MakeDist, group: str, caplog: pytest.LogCaptureFixture
) -> None:
    make_dist(
        "broken-plugin",
        {"nodes": "broken_nodes"},
        broken_nodes="import no_such_module_xyz\n",
    )
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)

    with caplog.at_level(logging.WARNING, logger="container.plugins"):
        registry = PluginRegistry(group=group)

    [failure] = registry.failures
    assert isinstance(failure, PluginError)
    assert failure.distribution == "broken-plugin"
    assert failure.entry_point == "nodes"
    assert "no_such_module_xyz" in str(failure)
    assert isinstance(failure.__cause__, ModuleNotFoundError)
    assert sorted(registry.types) == ["good::Listener", "good::Talker"]
    messages = [record.getMessage() for record in caplog.records]
    assert any("broken-plugin" in m and "no_such_module_xyz" in m for m in messages)


def test_plugin_that_exits_at_import_is_reported_and_skipped(make_dist: MakeDist, group: str) -> None:
    make_dist("exiting-plugin", {"nodes": "exiting_nodes"}, exiting_nodes="import sys\nsys.exit(3)\n")
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)

    registry = PluginRegistry(group=group)

    [failure] = registry.failures
    assert failure.distribution == "exiting-plugin"
    assert "SystemExit: 3" in str(failure)
    assert sorted(registry.types) == ["good::Listener", "good::Talker"]


def test_misspelled_hook_argument_is_reported(make_dist: MakeDist, group: str) -> None:
    make_dist(
        "typo-plugin",
        {"nodes": "typo_nodes"},
        typo_nodes="""
        from container._hookspecs import hookimpl

        @hookimpl
        def register_node_types(registr):
            raise AssertionError("never called")
        """,
    )
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)

    registry = PluginRegistry(group=group)

    [failure] = registry.failures
    assert failure.distribution == "typo-plugin"
    assert "invalid hook implementation" in str(failure)
    assert "registr" in str(failure)
    assert "\n" not in str(failure)
    assert sorted(registry.types) == ["good::Listener", "good::Talker"]


def test_unknown_hook_is_reported_before_any_hook_runs(
    make_dist: MakeDist, group: str
) -> None:
    make_dist(
        "unknown-hook",
        {"nodes": "unknown_hook_nodes"},
        unknown_hook_nodes="""
        from rclpy.node import Node
        from container._hookspecs import hookimpl

        class Orphan(Node):
            pass

        @hookimpl
        def register_node_type(register):
            pass

        @hookimpl
        def register_node_types(register):
            register(Orphan)
        """,
    )
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)

    registry = PluginRegistry(group=group)

    [failure] = registry.failures
    assert failure.distribution == "unknown-hook"
    assert "register_node_type'" in str(failure)
    assert "unknown_hook::Orphan" not in registry.types
    assert sorted(registry.types) == ["good::Listener", "good::Talker"]


def test_duplicate_type_name_skips_the_later_plugin_entirely(
    make_dist: MakeDist, group: str
) -> None:
    make_dist(
        "dup",
        {"first": "dup_first", "second": "dup_second"},
        dup_first="""
        from rclpy.node import Node
        from container._hookspecs import hookimpl

        class Talker(Node):
            pass

        @hookimpl
        def register_node_types(register):
            register(Talker)
        """,
        dup_second="""
        from rclpy.node import Node
        from container._hookspecs import hookimpl

        class Extra(Node):
            pass

        class Talker(Node):
            pass

        @hookimpl
        def register_node_types(register):
            register(Extra)
            register(Talker)
        """,
    )

    registry = PluginRegistry(group=group)

    [failure] = registry.failures
    assert failure.distribution == "dup"
    assert failure.entry_point == "second"
    assert "'dup::Talker' is already registered by distribution 'dup'" in str(failure)
    assert list(registry.types) == ["dup::Talker"]
    assert registry.types["dup::Talker"].node_class.__module__ == "dup_first"


def test_register_hook_that_raises_is_reported_and_rolled_back(
    make_dist: MakeDist, group: str
) -> None:
    make_dist(
        "raiser",
        {"nodes": "raiser_nodes"},
        raiser_nodes="""
        from rclpy.node import Node
        from container._hookspecs import hookimpl

        class Early(Node):
            pass

        @hookimpl
        def register_node_types(register):
            register(Early)
            raise RuntimeError("hardware library missing")
        """,
    )
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)

    registry = PluginRegistry(group=group)

    [failure] = registry.failures
    assert failure.distribution == "raiser"
    assert failure.entry_point == "nodes"
    assert "RuntimeError: hardware library missing" in str(failure)
    assert isinstance(failure.__cause__, RuntimeError)
    assert sorted(registry.types) == ["good::Listener", "good::Talker"]


@pytest.mark.parametrize(
    ("registration", "reason"),
    [
        ("register(42)", "not a class"),
        ("register(dict)", "not a subclass of rclpy.node.Node"),
        ("register(Fine, name='not-valid')", "must be a Python identifier"),
        ("register(Fine, name='')", "must be a Python identifier"),
        ("register(Fine); register(Fine)", "registered twice"),
    ],
)
def test_invalid_registration_skips_the_plugin(
    make_dist: MakeDist, group: str, registration: str, reason: str
) -> None:
    make_dist(
        "invalid",
        {"nodes": "invalid_nodes"},
        invalid_nodes=f"""
        from rclpy.node import Node
        from container._hookspecs import hookimpl

        class Fine(Node):
            pass

        class Other(Node):
            pass

        @hookimpl
        def register_node_types(register):
            register(Other)
            {registration}
        """,
    )

    registry = PluginRegistry(group=group)

    [failure] = registry.failures
    assert failure.distribution == "invalid"
    assert reason in str(failure)
    assert registry.types == {}


def test_invalid_registration_fails_the_plugin_even_if_caught(
    make_dist: MakeDist, group: str
) -> None:
    make_dist(
        "sloppy",
        {"nodes": "sloppy_nodes"},
        sloppy_nodes="""
        from rclpy.node import Node
        from container._hookspecs import hookimpl

        class Fine(Node):
            pass

        @hookimpl
        def register_node_types(register):
            try:
                register(object)
            except Exception:
                pass
            register(Fine)
        """,
    )

    registry = PluginRegistry(group=group)

    [failure] = registry.failures
    assert "not a subclass of rclpy.node.Node" in str(failure)
    assert registry.types == {}


def test_register_after_the_hook_returned_is_refused(
    make_dist: MakeDist, group: str
) -> None:
    make_dist(
        "late",
        {"nodes": "late_nodes"},
        late_nodes="""
        from rclpy.node import Node
        from container._hookspecs import hookimpl

        class Late(Node):
            pass

        kept = []

        @hookimpl
        def register_node_types(register):
            kept.append(register)
        """,
    )
    registry = PluginRegistry(group=group)
    late_nodes = sys.modules["late_nodes"]

    with pytest.raises(PluginError, match="after register_node_types returned"):
        late_nodes.kept[0](late_nodes.Late)
    assert registry.types == {}


# -- block-list and allow-list ------------------------------------------------

EXPLODES_ON_IMPORT = "raise RuntimeError('must not be imported')\n"


def test_block_list_keyword_skips_without_importing(
    make_dist: MakeDist, group: str
) -> None:
    make_dist(
        "Blocked.Plugin", {"nodes": "blocked_nodes"}, blocked_nodes=EXPLODES_ON_IMPORT
    )
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)

    registry = PluginRegistry(group=group, block=["blocked-plugin"])

    assert registry.failures == []
    assert sorted(registry.types) == ["good::Listener", "good::Talker"]


def test_block_list_from_environment(
    make_dist: MakeDist, group: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    make_dist("blocked", {"nodes": "blocked_nodes"}, blocked_nodes=EXPLODES_ON_IMPORT)
    make_dist("also-blocked", {"nodes": "also_nodes"}, also_nodes=EXPLODES_ON_IMPORT)
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)
    monkeypatch.setenv("CONTAINER_PLUGINS_BLOCK", " blocked , also_blocked,")

    registry = PluginRegistry(group=group)

    assert registry.failures == []
    assert sorted(registry.types) == ["good::Listener", "good::Talker"]


def test_allow_list_keyword_loads_only_listed(make_dist: MakeDist, group: str) -> None:
    make_dist("other", {"nodes": "other_nodes"}, other_nodes=EXPLODES_ON_IMPORT)
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)

    registry = PluginRegistry(group=group, allow=["GOOD"])

    assert registry.failures == []
    assert sorted(registry.types) == ["good::Listener", "good::Talker"]


def test_allow_list_from_environment(
    make_dist: MakeDist, group: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    make_dist("other", {"nodes": "other_nodes"}, other_nodes=EXPLODES_ON_IMPORT)
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)
    monkeypatch.setenv("CONTAINER_PLUGINS_ALLOW", "good")

    registry = PluginRegistry(group=group)

    assert registry.failures == []
    assert sorted(registry.types) == ["good::Listener", "good::Talker"]


def test_empty_allow_list_loads_nothing(
    make_dist: MakeDist, group: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)

    assert PluginRegistry(group=group, allow=()).types == {}
    monkeypatch.setenv("CONTAINER_PLUGINS_ALLOW", "")
    assert PluginRegistry(group=group).types == {}


def test_environment_only_narrows_the_configuration(
    make_dist: MakeDist, group: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in ("one", "two", "three", "four", "five"):
        make_dist(name, {"nodes": f"{name}_nodes"}, **{f"{name}_nodes": GOOD})
    monkeypatch.setenv("CONTAINER_PLUGINS_ALLOW", "one,two,three,four")
    monkeypatch.setenv("CONTAINER_PLUGINS_BLOCK", "three")

    registry = PluginRegistry(
        group=group, allow=["two", "three", "four", "five"], block=["four"]
    )

    assert list(registry.packages()) == ["two"]


# -- tracing --------------------------------------------------------------------


def trace_lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "container.hooks"]


def test_tracing_off_by_default(
    make_dist: MakeDist, group: str, caplog: pytest.LogCaptureFixture
) -> None:
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)

    with caplog.at_level(logging.DEBUG):
        PluginRegistry(group=group)

    assert trace_lines(caplog) == []


def test_tracing_keyword_logs_each_plugins_hook_call(
    make_dist: MakeDist, group: str, caplog: pytest.LogCaptureFixture
) -> None:
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)
    make_dist("second", {"nodes": "second_nodes"}, second_nodes=GOOD)

    with caplog.at_level(logging.DEBUG):
        PluginRegistry(group=group, trace=True)

    lines = trace_lines(caplog)
    calls = [line for line in lines if "register_node_types [hook]" in line]
    assert len(calls) == 2
    assert "distribution 'good' entry point 'nodes'" in calls[0]
    assert "distribution 'second' entry point 'nodes'" in calls[1]
    assert any(line.strip().startswith("finish register_node_types") for line in lines)


def test_tracing_from_environment(
    make_dist: MakeDist,
    group: str,
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    make_dist("good", {"nodes": "good_nodes"}, good_nodes=GOOD)
    monkeypatch.setenv("CONTAINER_TRACE_HOOKS", "1")

    with caplog.at_level(logging.DEBUG):
        PluginRegistry(group=group)

    assert any("register_node_types" in line for line in trace_lines(caplog))


# -- resolve ------------------------------------------------------------------


@pytest.fixture
def registry(make_dist: MakeDist, group: str) -> PluginRegistry:
    make_dist("demo-nodes", {"nodes": "demo_nodes"}, demo_nodes=GOOD)
    make_dist("other", {"nodes": "other_nodes"}, other_nodes=GOOD)
    return PluginRegistry(group=group)


@pytest.mark.parametrize("plugin_name", ["demo_nodes::Talker", "Talker"])
def test_resolve_accepts_full_and_bare_type_names(
    registry: PluginRegistry, plugin_name: str
) -> None:
    node_type = registry.resolve("demo_nodes", plugin_name)

    assert isinstance(node_type, NodeType)
    assert node_type is registry.types["demo_nodes::Talker"]


@pytest.mark.parametrize(
    ("package", "plugin_name"),
    [
        ("demo_nodes_cpp", "demo_nodes_cpp::Talker"),
        ("demo-nodes", "demo_nodes::Talker"),
        ("json", "json::JSONDecoder"),
        ("", ""),
    ],
)
def test_resolve_unknown_package_uses_rclcpp_wording(
    registry: PluginRegistry, package: str, plugin_name: str
) -> None:
    with pytest.raises(LoadError) as caught:
        registry.resolve(package, plugin_name)

    assert str(caught.value) == "Could not find requested resource in ament index"


@pytest.mark.parametrize(
    "plugin_name",
    ["demo_nodes::Talkr", "Talkr", "other::Talker", "demo_nodes::FastListener", ""],
)
def test_resolve_unknown_type_uses_rclcpp_wording(
    registry: PluginRegistry, plugin_name: str
) -> None:
    with pytest.raises(LoadError) as caught:
        registry.resolve("demo_nodes", plugin_name)

    assert str(caught.value) == "Failed to find class with the requested plugin name."


# -- following what is installed ----------------------------------------------


def test_a_plugin_installed_after_start_loads_on_request(registry: PluginRegistry, make_dist: MakeDist) -> None:
    make_dist("late-nodes", {"nodes": "late_nodes"}, late_nodes=GOOD)

    node_type = registry.resolve("late_nodes", "Talker")

    assert node_type.full_name == "late_nodes::Talker"
    assert node_type.distribution == "late-nodes"
    assert "late_nodes::Listener" in registry.types


def test_a_plugin_uninstalled_after_start_is_refused(registry: PluginRegistry) -> None:
    site = Path(sys.modules["demo_nodes"].__file__ or "").parent
    shutil.rmtree(site / "demo_nodes-1.0.dist-info")

    for _ in range(2):  # the first refusal forgets the types; the second still says why
        with pytest.raises(LoadError) as caught:
            registry.resolve("demo_nodes", "Talker")
        assert str(caught.value) == (
            "Cannot load demo_nodes::Talker: distribution 'demo-nodes' is no longer installed"
        )
    assert not any(name.startswith("demo_nodes::") for name in registry.types)
    assert registry.resolve("other", "Talker").full_name == "other::Talker"


def test_a_plugin_installed_after_start_then_uninstalled_is_no_longer_installed(
    registry: PluginRegistry, make_dist: MakeDist
) -> None:
    info = make_dist("late-nodes", {"nodes": "late_nodes"}, late_nodes=GOOD)
    assert registry.resolve("late_nodes", "Talker").distribution == "late-nodes"
    # What pip uninstall removes: the metadata (the module stays imported).
    moved = info.rename(info.with_name("gone"))

    with pytest.raises(LoadError) as caught:
        registry.resolve("late_nodes", "Talker")
    # Not "since the container started": it was installed after that.
    assert str(caught.value) == "Cannot load late_nodes::Talker: distribution 'late-nodes' is no longer installed"

    moved.rename(info)  # installed again: Python still holds the first import
    importlib.invalidate_caches()
    with pytest.raises(LoadError) as caught:
        registry.resolve("late_nodes", "Listener")
    assert str(caught.value) == (
        "Cannot load late_nodes::Listener: distribution 'late-nodes' was uninstalled after the container "
        "imported it, and installed again since: restart the container to load it"
    )


def test_a_plugin_replaced_after_start_asks_for_a_restart(registry: PluginRegistry) -> None:
    site = Path(sys.modules["demo_nodes"].__file__ or "").parent
    old = site / "demo_nodes-1.0.dist-info"
    new = old.rename(site / "demo_nodes-2.0.dist-info")
    (new / "METADATA").write_text("Metadata-Version: 2.1\nName: demo-nodes\nVersion: 2.0\n")

    with pytest.raises(LoadError, match=r"replaced .*version 1\.0 was imported, 2\.0 is installed.*restart"):
        registry.resolve("demo_nodes", "Talker")
    # Not imported again under the new version: Python would hand back the old modules.
    with pytest.raises(LoadError, match="replaced"):
        registry.resolve("demo_nodes", "Listener")
    assert not any(name.startswith("demo_nodes::") for name in registry.types)


def test_a_load_of_a_plugin_that_failed_answers_with_its_failure(make_dist: MakeDist, group: str) -> None:
    make_dist("broken-plugin", {"nodes": "broken_nodes"}, broken_nodes="import no_such_module_xyz\n")
    registry = PluginRegistry(group=group)

    with pytest.raises(LoadError) as caught:
        registry.resolve("broken_plugin", "Anything")

    assert str(caught.value) == (
        "Plugin failed to load: distribution 'broken-plugin' entry point 'nodes': cannot import "
        "'broken_nodes': ModuleNotFoundError: No module named 'no_such_module_xyz'"
    )


def test_a_rescan_tries_each_entry_point_once(make_dist: MakeDist, group: str, tmp_path: Path) -> None:
    imports = tmp_path / "imports"
    imports.mkdir()
    make_dist(
        "broken-plugin",
        {"nodes": "counted_nodes"},
        counted_nodes=f"""
        import tempfile
        tempfile.mkstemp(dir={str(imports)!r})  # one file per import
        raise RuntimeError('broken')
        """,
    )
    registry = PluginRegistry(group=group)

    for _ in range(3):
        with pytest.raises(LoadError, match="RuntimeError: broken"):
            registry.resolve("broken_plugin", "Talker")
        with pytest.raises(LoadError, match="Could not find requested resource"):
            registry.resolve("nothing_here", "Talker")

    assert len(list(imports.iterdir())) == 1
    assert len(registry.failures) == 1


# -- in-process plugins -------------------------------------------------------


class Builtin(LifecycleNode):
    pass


class BuiltinPlugin:
    @hookimpl
    def register_node_types(self, register: Callable[..., None]) -> None:
        register(Builtin)


class BrokenBuiltinPlugin:
    @hookimpl
    def register_node_types(self, register: Callable[..., None]) -> None:
        register(Builtin)
        register(Builtin, name="no good")


def test_add_plugin_registers_in_process_types(group: str) -> None:
    registry = PluginRegistry(group=group)

    registry.add_plugin(BuiltinPlugin(), distribution="lifecycle-container")

    assert registry.resolve("lifecycle_container", "Builtin").node_class is Builtin


def test_add_plugin_raises_and_keeps_nothing_when_broken(group: str) -> None:
    registry = PluginRegistry(group=group)

    with pytest.raises(PluginError, match="Python identifier") as caught:
        registry.add_plugin(BrokenBuiltinPlugin(), distribution="lifecycle-container")

    assert caught.value.distribution == "lifecycle-container"
    assert registry.types == {}
    assert registry.failures == []
    registry.add_plugin(BuiltinPlugin(), distribution="lifecycle-container")
    assert list(registry.types) == ["lifecycle_container::Builtin"]


# -- importing a distribution afresh (container reload) ------------------------


def test_a_reimport_registers_the_new_code_and_undo_puts_the_old_back(
    registry: PluginRegistry,
) -> None:
    old_class = registry.types["demo_nodes::Talker"].node_class
    old_module = sys.modules["demo_nodes"]
    source = Path(old_module.__file__ or "")
    new = textwrap.dedent(GOOD).replace("class Talker(LifecycleNode):", "class Talker(LifecycleNode):\n    NEW = 1")
    source.write_text(new)

    swap = registry.reimport("demo-nodes")

    new_class = registry.types["demo_nodes::Talker"].node_class
    assert new_class is not old_class and getattr(new_class, "NEW", None) == 1
    assert set(swap.types) == {"demo_nodes::Talker", "demo_nodes::Listener"}
    assert sys.modules["demo_nodes"] is not old_module
    assert registry.types["other::Talker"].distribution == "other"  # the others' untouched
    swap.undo()
    assert registry.types["demo_nodes::Talker"].node_class is old_class
    assert sys.modules["demo_nodes"] is old_module
    assert registry.resolve("demo_nodes", "Listener").node_class.__module__ == "demo_nodes"


@pytest.mark.parametrize(
    ("new_source", "words"),
    [
        ("def broken(:\n", r"demo_nodes\.py:1: cannot import 'demo_nodes': SyntaxError"),
        (GOOD + "\nraise RuntimeError('at import')\n", r"demo_nodes\.py:\d+: cannot import .*RuntimeError: at import"),
        (
            GOOD.replace('register(FastListener, name="Listener")', "register(FastListener, name='not valid')"),
            r"demo_nodes\.py:\d+: cannot register FastListener as 'not valid'",
        ),
    ],
    ids=["syntax error", "raises at import", "invalid registration"],
)
def test_a_reimport_that_fails_names_the_file_and_line_and_changes_nothing(
    registry: PluginRegistry, new_source: str, words: str
) -> None:
    before = dict(registry.types)
    old_module = sys.modules["demo_nodes"]
    Path(old_module.__file__ or "").write_text(textwrap.dedent(new_source))

    with pytest.raises(LoadError, match=words):
        registry.reimport("demo-nodes")

    assert dict(registry.types) == before
    assert sys.modules["demo_nodes"] is old_module
    # The old code's hook is registered again: a rescan or another reimport still works.
    Path(old_module.__file__ or "").write_text(textwrap.dedent(GOOD))
    assert set(registry.reimport("demo-nodes").types) == {"demo_nodes::Talker", "demo_nodes::Listener"}


def test_what_was_not_loaded_from_an_entry_point_cannot_be_reimported(registry: PluginRegistry) -> None:
    class Plugin:
        @hookimpl
        def register_node_types(self, register: Callable[..., None]) -> None:
            register(LifecycleNode, name="Inline")

    registry.add_plugin(Plugin(), distribution="inline")
    with pytest.raises(LoadError, match="'inline' was not loaded from an installed entry point"):
        registry.reimport("inline")
