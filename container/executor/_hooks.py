"""What the executor's parts ask of each other: one protocol per edge.

The executor owns a dispatcher, which owns lanes. Each part calls back
into its owner through one object implementing the protocol below, rather
than through a handful of loose callables, so that who depends on whom is
written down in one place: :class:`ExecutorHooks` (the dispatcher's view
of the executor) and :class:`LaneHooks` (a lane's view of its dispatcher).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterable, Sized
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from rclpy.guard_condition import GuardCondition
    from rclpy.node import Node

    from ._engine import Handoff, Work
    from ._lanes import Lane
    from ._workers import WorkerPool

__all__: list[str] = []


class ExecutorHooks(Protocol):
    """The dispatcher's view of the executor that owns it."""

    @property
    def done_waiters(self) -> Sized:
        """Futures waiting for any callback to complete (``spin_once``); the
        compiled path calls :meth:`callback_completed` only while it is non-empty."""

    def nodes(self) -> Iterable[Node]:
        """The nodes whose entities are waited on."""

    def own_guards(self) -> Iterable[tuple[GuardCondition, int]]:
        """The executor's own guard conditions, each with the flag it raises."""

    def post(self, callback: Callable[..., object], *args: Any) -> None:
        """Run ``callback(*args)`` on the dispatching loop's thread soon (any thread)."""

    @property
    def posted(self) -> Sized:
        """What :meth:`post` queued for the loop's thread and has not run yet."""

    def run_posted(self) -> None:
        """Run it now (on the loop's thread, dispatching)."""

    def report_error(self, node: Node, entity: object, error: BaseException) -> None:
        """A callback of ``node``'s ``entity`` raised ``error``."""

    def callback_completed(self) -> None:
        """A callback finished (or, async, suspended for the first time)."""

    def response_arrived(self) -> None:
        """A client's response was taken: whoever awaits an rclpy future may go on."""

    def progress(self) -> asyncio.Future[None]:
        """A future completed at the executor's next progress (what parked coroutines wait on)."""

    def wake(self) -> None:
        """Wake the loop's thread out of ``rcl_wait``."""


class LaneHooks(Protocol):
    """A lane's view of its dispatcher."""

    #: Whether worker threads carry on to the plain callbacks their callbacks' publishes reach.
    carries: bool
    #: The threads plain callbacks run on (every lane of the dispatcher shares them).
    workers: WorkerPool

    @property
    def handoff(self) -> Handoff | None:
        """Where the loop's thread counts the workers it wakes (``None``: it never waits for them)."""

    def on_loop_thread(self) -> bool:
        """Whether the caller runs on the dispatching loop's thread."""

    def post(self, callback: Callable[..., object], *args: Any) -> None:
        """Run ``callback(*args)`` on the loop's thread soon (any thread)."""

    def progress(self) -> asyncio.Future[None]:
        """See :meth:`ExecutorHooks.progress`."""

    def defer(self, lane: Lane, work: Work) -> bool:
        """Take async ``work`` to start eagerly after the current wait; ``False``: none is dispatched here."""

    def carry(self) -> None:
        """Take what plain callbacks are reported ready for (on a worker thread that just ran one)."""

    def suspended(self) -> None:
        """An async callback's first step suspended (rclpy's ``spin_once`` counts it as run)."""
