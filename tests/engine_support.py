"""The executor's two engines in the tests: which one runs, and what only the compiled one has.

The suite runs on the engine ``CONTAINER_EXECUTOR_ENGINE`` chooses (see
``container/executor/_engine.py``). A test of a mechanism that only the
compiled engine has is marked :func:`compiled_only`, naming the mechanism
(its one reason text, :func:`lacks`); the unit tests of the engines'
objects run against both modules (:func:`engines`) where the behaviour is
the same.
"""

from __future__ import annotations

import pytest

from container.executor import _engine, _fastpath, _pyengine

__all__ = ["ENGINE", "compiled_only", "engines", "lacks"]

#: The engine this test run's executors run on: ``compiled`` or ``python``.
ENGINE: str = _engine.ENGINE


def lacks(mechanism: str) -> str:
    """Why a test of ``mechanism`` is skipped under the Python engine."""
    return f"the Python engine has no {mechanism} (docs/executor/engines.md)"


def compiled_only(mechanism: str) -> pytest.MarkDecorator:
    """Skip the test when the executor runs on the Python engine: it tests ``mechanism``,
    which only the compiled engine has."""
    return pytest.mark.skipif(ENGINE != "compiled", reason=lacks(mechanism))


def engines(*, python_lacks: str | None = None) -> list[object]:
    """Both engine modules as parameters (ids ``compiled``, ``python``), for tests of
    their objects; ``python_lacks``: the mechanism the test needs that the Python
    engine does not have (its case is skipped, whichever engine the executor runs on)."""
    marks = [] if python_lacks is None else [pytest.mark.skip(reason=lacks(python_lacks))]
    return [pytest.param(_fastpath, id="compiled"), pytest.param(_pyengine, id="python", marks=marks)]
