"""Which engine runs the hot path (``_engine``): the first executor says why it is not the one asked for."""

from __future__ import annotations

import logging

import pytest
from rclpy.context import Context

from container import AsyncioExecutor
from container.executor import _engine


def test_the_first_executor_says_once_why_the_engine_is_not_the_one_asked_for(
    context: Context, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    why = f"{_engine.VARIABLE}='rust' is not one of compiled, python"
    monkeypatch.setattr(_engine, "_why", why)
    monkeypatch.setattr(_engine, "_announced", False)
    with caplog.at_level(logging.WARNING, logger="container.executor"):
        for _ in range(2):
            AsyncioExecutor(context=context).shutdown(timeout_sec=1.0)
    said = [record.getMessage() for record in caplog.records if record.name == "container.executor"]
    assert said == [f"{why}: the executor runs on the {_engine.ENGINE} engine"]


def test_the_engine_asked_for_is_not_announced(
    context: Context, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(_engine, "_why", None)
    monkeypatch.setattr(_engine, "_announced", False)
    with caplog.at_level(logging.WARNING, logger="container.executor"):
        AsyncioExecutor(context=context).shutdown(timeout_sec=1.0)
    assert [record for record in caplog.records if record.name == "container.executor"] == []
