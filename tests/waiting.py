"""Waiting for a condition: the suite's one poll-until helper, in a thread and on a loop.

Both forms take the condition, a description of what is awaited, and a
timeout; both fail with an ``AssertionError`` that names what was awaited.
Poll only what offers no event to wait on (graph discovery: rclpy#929;
state another thread or process changes): where a future, an event or a
message marks the outcome, wait on that instead.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Protocol

__all__ = ["Spinner", "wait_until", "wait_until_async"]

#: What was awaited: a text, or a function making one when the wait fails
#: (to report the state at that moment).
What = str | Callable[[], str]

_POLL_S = 0.01
_SPIN_S = 0.05


class Spinner(Protocol):
    """An executor to serve callbacks of while waiting (rclpy's or ours)."""

    def spin_once(self, timeout_sec: float | None = None) -> None: ...


def wait_until(
    condition: Callable[[], object], what: What, *, timeout: float = 10.0, executor: Spinner | None = None
) -> None:
    """Block until ``condition()`` is true.

    :param executor: spun meanwhile (the condition is checked each time a
        callback completes, or every 50 ms); without one, this thread sleeps
        10 ms between checks.
    :raises AssertionError: naming ``what``, after ``timeout`` seconds.
    """
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() >= deadline:
            raise AssertionError(_failed(what, timeout))
        if executor is not None:
            executor.spin_once(timeout_sec=_SPIN_S)
        else:
            time.sleep(_POLL_S)


async def wait_until_async(condition: Callable[[], object], what: What, *, timeout: float = 10.0) -> None:
    """:func:`wait_until` on the running loop, which goes on running meanwhile (checks every 10 ms).

    :raises AssertionError: naming ``what``, after ``timeout`` seconds.
    """
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not condition():
        if loop.time() >= deadline:
            raise AssertionError(_failed(what, timeout))
        await asyncio.sleep(_POLL_S)


def _failed(what: What, timeout: float) -> str:
    return f"timed out after {timeout:g} s waiting for {what if isinstance(what, str) else what()}"
