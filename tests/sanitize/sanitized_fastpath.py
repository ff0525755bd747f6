"""pytest plugin of the sanitizer run (``-p sanitized_fastpath``, loaded by ``.ci/sanitize``).

It refuses to run a single test unless ``container.executor._fastpath`` is
the sanitized build that this directory's ``sitecustomize`` (imported at
start-up) put in its place, and the executor runs on it (the compiled
engine, not a fallback): a run that silently tested the ordinary build
would report nothing, and mean nothing.
"""

from __future__ import annotations

import os
import sys

import pytest

__all__ = ["pytest_configure", "pytest_report_header"]


def _sanitized() -> tuple[str, str]:
    """The module the sanitized build stands in for, and the build's path."""
    # Read from the module itself: the one imported at start-up must be ours.
    site = sys.modules.get("sitecustomize")
    module, variable = getattr(site, "MODULE", None), getattr(site, "VARIABLE", None)
    if not isinstance(module, str) or not isinstance(variable, str):
        raise pytest.UsageError("sanitized_fastpath: tests/sanitize/sitecustomize.py was not imported (PYTHONPATH)")
    path = os.environ.get(variable, "")
    if not path:
        raise pytest.UsageError(f"sanitized_fastpath: {variable} names no sanitized build")
    return module, os.path.realpath(path)


def pytest_configure(config: pytest.Config) -> None:
    from container.executor import _engine, _fastpath

    module, wanted = _sanitized()
    loaded = os.path.realpath(_fastpath.__file__ or "")
    if loaded != wanted:
        raise pytest.UsageError(f"sanitized_fastpath: {module} is {loaded}, not the sanitized build {wanted}")
    if _engine.ENGINE != "compiled":
        raise pytest.UsageError(f"sanitized_fastpath: the executor runs on the {_engine.ENGINE} engine")


def pytest_report_header(config: pytest.Config) -> str:
    module, path = _sanitized()
    return f"{module}: {path} (sanitized)"
