"""Importing a distribution's modules afresh (``container._reimport``), on real files and real imports."""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from container._errors import LoadError
from container._reimport import DistributionModules, distribution_modules, failure_location, import_afresh


@pytest.fixture
def site(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A directory on ``sys.path``; whatever was imported from it is forgotten afterwards."""
    monkeypatch.setattr(sys, "path", [str(tmp_path), *sys.path])
    monkeypatch.setattr(sys, "dont_write_bytecode", False)
    importlib.invalidate_caches()
    yield tmp_path
    for name, module in list(sys.modules.items()):
        if str(getattr(module, "__file__", None) or "").startswith(str(tmp_path)):
            del sys.modules[name]


def _package(site: Path, name: str, **modules: str) -> None:
    (site / name).mkdir(parents=True, exist_ok=True)
    for module, source in modules.items():
        (site / name / f"{module}.py").write_text(source, encoding="utf-8")


def test_a_file_saved_again_within_its_second_at_the_same_size_is_imported_afresh(site: Path) -> None:
    _package(site, "same_size", __init__="VALUE = 1\n")
    init = site / "same_size" / "__init__.py"
    assert importlib.import_module("same_size").VALUE == 1
    stamp = init.stat().st_mtime_ns
    init.write_text("VALUE = 2\n", encoding="utf-8")
    os.utime(init, ns=(stamp, stamp))  # what a save within the same second looks like to Python's cache
    # Python's own import takes the stale byte code: the trap import_afresh avoids.
    del sys.modules["same_size"]
    assert importlib.import_module("same_size").VALUE == 1

    module, _ = import_afresh(
        DistributionModules("same-size", ("same_size",)), lambda: importlib.import_module("same_size")
    )

    assert module.VALUE == 2


def test_a_failed_import_puts_back_every_old_module_and_undo_does_after_success(site: Path) -> None:
    _package(site, "tree", __init__="from . import leaf\n", leaf="X = 1\n")
    old = {name: sys.modules[name] for name in ("tree", "tree.leaf") if importlib.import_module(name)}
    modules = DistributionModules("tree", ("tree",))
    (site / "tree" / "leaf.py").write_text("X = (\n", encoding="utf-8")

    with pytest.raises(SyntaxError) as caught:
        import_afresh(modules, lambda: importlib.import_module("tree"))

    assert {name: sys.modules[name] for name in old} == old
    assert failure_location(caught.value, modules) == f"{site / 'tree' / 'leaf.py'}:1"
    (site / "tree" / "leaf.py").write_text("X = 2\n", encoding="utf-8")
    _, reimport = import_afresh(modules, lambda: importlib.import_module("tree"))
    assert sys.modules["tree.leaf"].X == 2
    reimport.undo()
    assert {name: sys.modules[name] for name in old} == old


def test_a_runtime_error_is_placed_at_the_distribution_s_own_frame(site: Path) -> None:
    _package(site, "raiser", __init__="import json\n\njson.loads('{')\n")
    modules = DistributionModules("raiser", ("raiser",))

    with pytest.raises(ValueError) as caught:
        import_afresh(modules, lambda: importlib.import_module("raiser"))

    # The innermost frame is json's; the one to edit is the plugin's.
    assert failure_location(caught.value, modules) == f"{site / 'raiser' / '__init__.py'}:3"


def _entry_point(value: str) -> importlib.metadata.EntryPoint:
    return importlib.metadata.EntryPoint(name="nodes", value=value, group="container.plugins")


def test_a_root_below_a_namespace_package_is_the_first_regular_package(site: Path) -> None:
    (site / "acme" / "nodes").mkdir(parents=True)  # acme: a namespace package (no __init__)
    (site / "acme" / "nodes" / "__init__.py").write_text("", encoding="utf-8")
    (site / "acme" / "nodes" / "plugin.py").write_text("", encoding="utf-8")
    importlib.import_module("acme.nodes.plugin")

    modules = distribution_modules("acme-nodes", [_entry_point("acme.nodes.plugin")])

    assert modules.roots == ("acme.nodes",)
    assert modules.owns("acme.nodes.plugin") and not modules.owns("acme") and not modules.owns("acme.nodesx")
    assert modules.sources() == [(site / "acme" / "nodes").resolve()]


def test_the_container_s_own_code_cannot_be_taken_out() -> None:
    with pytest.raises(LoadError, match=r"is the container's own code .*restart the container"):
        distribution_modules("lifecycle-container", [_entry_point("container.demo")])
