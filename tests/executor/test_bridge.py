"""The bridge between rclpy's coroutines and asyncio's tasks (``container/executor/_bridge.py``)."""

from __future__ import annotations

import asyncio
import inspect
from collections.abc import Generator

from container.executor._bridge import adapt


class _Suspend:
    """An awaitable that suspends once, yielding what a task would wait on."""

    def __await__(self) -> Generator[str, None, None]:
        yield "waiting"


async def _suspends() -> None:
    await _Suspend()


def _never_progress() -> asyncio.Future[None]:
    raise AssertionError("the coroutine yielded a value: it waits on that, not on progress")


def test_an_adapted_coroutine_closed_after_the_one_it_drives_closes_quietly() -> None:
    """A task destroyed while pending (its loop shut down, a node's task waiting on a reader) is
    garbage with the coroutine it drives: the collector closes both, in either order. Closed
    second, the driver forwarded its ``GeneratorExit`` into the closed coroutine, which raised
    "cannot reuse already awaited coroutine", printed as an exception ignored."""
    inner = _suspends()
    outer = adapt(inner, _never_progress)
    assert outer.send(None) == "waiting"
    inner.close()
    outer.close()  # nothing raised


def test_an_adapted_coroutine_closed_first_closes_the_one_it_drives() -> None:
    inner = _suspends()
    outer = adapt(inner, _never_progress)
    assert outer.send(None) == "waiting"
    outer.close()
    assert inspect.getcoroutinestate(inner) == inspect.CORO_CLOSED
