"""The one way work reaches an event loop's thread from elsewhere.

The executor's own loop sleeps in ``rcl_wait``, not in its selector: a
hand-over to it is a deque and one guard-condition trigger (one wake-up,
where ``call_soon_threadsafe`` costs three: self-pipe, fd watcher, guard
condition), run after the wait returns. Any other loop (a user's, under
``spin_async``) gets asyncio's own ``call_soon`` or ``call_soon_threadsafe``.
"""

from __future__ import annotations

import asyncio
import collections
import threading
from collections.abc import Callable
from typing import Any

__all__: list[str] = []

#: Runs ``callback(*args)`` on a loop's thread soon; callable from any thread.
Post = Callable[..., None]


class Inbox:
    """Hand-overs to the executor's own loop, and to any other loop.

    :param loop: the executor's own loop.
    :param wake: wakes that loop's thread out of ``rcl_wait``.
    """

    def __init__(self, *, loop: asyncio.AbstractEventLoop, wake: Callable[[], None]) -> None:
        self._loop = loop
        self._wake = wake
        self._queue: collections.deque[tuple[Callable[..., object], tuple[Any, ...]]] = collections.deque()
        #: The thread between a wait and the :meth:`run` after it (see :meth:`draining`).
        self._drainer: int | None = None

    def post(self, callback: Callable[..., object], *args: Any) -> None:
        """Run ``callback(*args)`` on the own loop's thread after its next wait (any thread)."""
        self._queue.append((callback, args))
        if self._drainer is None or self._drainer != threading.get_ident():
            self._wake()

    def draining(self, thread: int | None) -> None:
        """``thread`` (``None``: nobody) dispatches a wait and then calls :meth:`run`:
        what it posts meanwhile runs then, without a wake-up (a guard
        condition's trigger, and the next wait returning at once for it)."""
        self._drainer = thread

    def call_soon(self, loop: asyncio.AbstractEventLoop, callback: Callable[..., object], *args: Any) -> None:
        """Run ``callback(*args)`` in ``loop``'s next iteration (any thread; nothing once it is closed)."""
        if loop.is_closed():
            return
        try:
            here = asyncio.get_running_loop() is loop
        except RuntimeError:
            here = False
        if here:
            loop.call_soon(callback, *args)
        else:
            loop.call_soon_threadsafe(callback, *args)

    def post_to(self, loop: asyncio.AbstractEventLoop, callback: Callable[..., object], *args: Any) -> None:
        """:meth:`post` for the own loop, :meth:`call_soon` for any other."""
        if loop is self._loop:
            self.post(callback, *args)
        else:
            self.call_soon(loop, callback, *args)

    def poster(self, loop: asyncio.AbstractEventLoop) -> Post:
        """What posts to ``loop`` from any thread: :meth:`post` for the own loop."""
        if loop is self._loop:
            return self.post

        def post(callback: Callable[..., object], *args: Any) -> None:
            loop.call_soon_threadsafe(callback, *args)

        return post

    def run(self) -> None:
        """Run what was posted (on the own loop's thread, after a wait)."""
        queue = self._queue
        while queue:
            callback, args = queue.popleft()
            callback(*args)

    def clear(self) -> None:
        self._queue.clear()

    def __bool__(self) -> bool:
        return bool(self._queue)

    def __len__(self) -> int:
        return len(self._queue)
