"""A pytest plugin for the test command (``.ci/test``): progress to a file, and tests to skip.

``.ci/test`` loads it with ``-p tests.ci_progress``; without its two
environment variables it does nothing.

``CI_PROGRESS_FILE``
    Each test appends ``start TIMEOUT NODEID`` as it starts and
    ``done OUTCOME NODEID`` once its report is in (``passed``, ``failed``
    or ``skipped``; the worst of its phases). A hang that holds the GIL ends
    no test and lets no Python thread run, pytest-timeout's included: the
    test command's guard, a shell loop outside the process, sees the last
    line stay ``start`` longer than that test's timeout allows.
``CI_SKIP_FILE``
    Node ids, one a line, deselected: after such a hang (in Fast DDS, never
    in this project's code; see ``.ci/test``), the rerun skips what had
    finished.
"""

from __future__ import annotations

import os
from collections.abc import Generator
from pathlib import Path

import pytest

__all__: list[str] = []

_PROGRESS = os.environ.get("CI_PROGRESS_FILE")
_SKIP = os.environ.get("CI_SKIP_FILE")
_RANK = {"passed": 0, "skipped": 1, "failed": 2}


def _append(line: str) -> None:
    assert _PROGRESS is not None
    with open(_PROGRESS, "a", encoding="utf-8") as progress:
        progress.write(line + "\n")


def _timeout_of(item: pytest.Item) -> float:
    marker = item.get_closest_marker("timeout")
    if marker is not None and marker.args:
        return float(marker.args[0])
    return float(item.config.getini("timeout") or 0)


_outcome = pytest.StashKey[str]()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Generator[None, object, object]:
    if _PROGRESS is None:
        return (yield)
    item.stash[_outcome] = "passed"
    _append(f"start {_timeout_of(item):g} {item.nodeid}")
    try:
        return (yield)
    finally:
        _append(f"done {item.stash[_outcome]} {item.nodeid}")


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    report = yield
    if _PROGRESS is not None:
        item.stash[_outcome] = max(item.stash.get(_outcome, "passed"), report.outcome, key=_RANK.__getitem__)
    return report


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if _SKIP is None:
        return
    skip = set(Path(_SKIP).read_text(encoding="utf-8").split("\n")) - {""}
    kept = [item for item in items if item.nodeid not in skip]
    deselected = [item for item in items if item.nodeid in skip]
    if deselected:
        config.hook.pytest_deselected(items=deselected)
        items[:] = kept
