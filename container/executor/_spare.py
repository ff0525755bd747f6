"""Threads for calls that may block for good, reused once they are free.

:func:`container.executor.in_thread` gives each call a thread of its own,
so a constructor or transition callback that never returns costs one idle
thread and holds up nobody else. Starting a thread for every call cost the
event loop about 2 ms each: ``Thread.start()`` waits until the new thread
runs, and the new thread runs the call at once, holding the GIL, so the
loop waited out a GIL switch interval. A container file of 100 nodes
started some 300 of them (0.63-0.69 s of a 2-3 s start-up, measured).

Here a thread whose call has returned waits :data:`SPARE_IDLE_S` for the
next call and takes it; handing a call to a spare thread is a queue put,
which never waits. A call still running keeps its thread: nothing is
shared while it runs, and no number of threads is a limit.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from typing import Final

from ._owners import executor_work

__all__ = ["SPARE_IDLE_S", "end_spare_threads", "run_on_spare_thread"]

#: How long a thread whose call returned waits for another before it ends.
SPARE_IDLE_S: Final = 3.0

_Job = tuple[Callable[[], object], Callable[[object, BaseException | None], None], str]
_Inbox = queue.SimpleQueue[_Job | None]
#: Put in an idle thread's inbox: end now.
_END: Final = None


class _SpareThreads:
    """Idle threads, each with its own inbox (the last to idle is reused first)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._idle: list[tuple[_Inbox, threading.Thread]] = []

    def run(
        self,
        call: Callable[[], object],
        deliver: Callable[[object, BaseException | None], None],
        *,
        name: str,
    ) -> None:
        with self._lock:
            spare = self._idle.pop() if self._idle else None
        if spare is None:
            inbox: _Inbox = queue.SimpleQueue()
            inbox.put((call, deliver, name))
            thread = threading.Thread(target=self._serve, args=(inbox,), name=name, daemon=True)
            with executor_work():  # the call it runs is metered apart, as its caller's (``in_thread``)
                thread.start()
        else:
            spare[0].put((call, deliver, name))

    def end_idle(self, *, timeout: float) -> None:
        """End the threads waiting for a call; wait up to ``timeout`` for them to exit."""
        with self._lock:
            idle, self._idle = self._idle, []
        for inbox, _ in idle:
            inbox.put(_END)
        for _, thread in idle:
            thread.join(timeout)

    def _serve(self, inbox: _Inbox) -> None:
        this = threading.current_thread()
        spare = (inbox, this)
        while True:
            try:
                job = inbox.get(timeout=SPARE_IDLE_S)
            except queue.Empty:
                with self._lock:
                    if spare in self._idle:
                        self._idle.remove(spare)
                        return
                # Taken off the idle list just now: its call is on the way.
                continue
            if job is _END:
                return
            call, deliver, name = job
            del job  # what a call returned (a node it made) is not kept while this thread idles
            this.name = name
            value: object = None
            error: BaseException | None = None
            try:
                value = call()
            except BaseException as exc:  # delivered to whoever waits for the call
                error = exc
            del call
            this.name = "spare"
            # Idle before the outcome is told: the caller's next call (a
            # file's next constructor) finds this thread free.
            with self._lock:
                self._idle.append(spare)
            deliver(value, error)
            del deliver, value, error


_spare = _SpareThreads()


def run_on_spare_thread(
    call: Callable[[], object],
    deliver: Callable[[object, BaseException | None], None],
    *,
    name: str,
) -> None:
    """Run ``call`` on a free thread named ``name``; then ``deliver(value, error)`` there.

    ``deliver`` must not block: the thread is already counted free.
    """
    _spare.run(call, deliver, name=name)


def end_spare_threads(*, timeout: float) -> None:
    """End every spare thread that waits for a call (those still running one go on).

    A process about to exit, or to count the threads it left behind, calls it.
    """
    _spare.end_idle(timeout=timeout)
