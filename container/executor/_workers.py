"""The worker threads that run plain callbacks: one pool for every lane of a dispatcher.

A lane (``_lanes``) decides *whether* a plain callback may start (its
group's limit); the pool decides *where*. Each lane used to keep threads of
its own, so a container held a thread for every group that had run a plain
callback in the last :data:`WORKER_IDLE_S`: 69 threads for 100 demo nodes,
119 for the demo mix. Threads here are shared: work goes to an idle worker
when there is one, and a new thread starts only when every worker is busy
(running a callback, or blocked in one), as asyncio's default executor and
Go's scheduler do. So a callback that blocks for good holds one thread and
delays nobody: the next work finds no idle worker and gets a new one. Past
:attr:`WorkerPool.size`, a worker exits as its callback returns (the pool
shrinks back once the blockers are done); below it, one idle for
:data:`WORKER_IDLE_S` exits too, so an idle container keeps no thread here.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import TYPE_CHECKING, Final

from ._engine import Handoff, mark_carrier
from ._owners import executor_work

if TYPE_CHECKING:
    from ._engine import Work
    from ._lanes import Lane

__all__: list[str] = []

#: Seconds a worker waits for more work before it exits.
WORKER_IDLE_S = 3.0
#: How long a worker whose work comes quickly stays awake for more (see
#: ``Handoff.linger``): it lingers only while its last work was handed to
#: it sooner than this after it was free for it.
#:
#: Sooner after it was *free*, from the hand-over's own time: not from how
#: long its wait took, which once the worker sleeps includes its own
#: wake-up (50-200 us on a virtual machine). Measured that way, one late
#: hand-over put it to sleep and its wake-ups then kept every wait above
#: the bound: it never lingered again while the work came as fast as
#: before, and which of the two a run settled in decided plain service
#: calls' rate (0.82x-1.24x between otherwise equal 1.5 s turns; the
#: accounting's few microseconds a call tipped it to sleeping).
#:
#: Measured against, on the project's 2-core shared KVM VM: with the loop's
#: linger (``fastpath/handoff.c``, ``LOOP_LINGER_NS``, commit bc7e731), plain
#: service calls 7,430-7,614/s before and 19,770-20,200/s after, the code
#: before side by side (``bench_executor.py --only services``), the
#: ten-node load's CPU with plain callbacks 1.01x, ping-pong 0.98x; in
#: ``bench_busy.py`` the plain intra-process subscriber then got 3,171
#: frames a second at 177% CPU, where the run before lingering got 2,490 at
#: one core. 250 us itself was not measured against other values. Never
#: used on one CPU: the worker does not linger (``Handoff.spin`` is false),
#: since the loop it waits for needs that CPU to hand work over.
WORKER_LINGER_NS = 250_000
#: Workers kept while idle (up to :data:`WORKER_IDLE_S`); those started past
#: it, while every worker was busy, exit when their callback returns.
POOL_SIZE: Final = 8


class WorkerPool:
    """Threads that run the plain work lanes hand them.

    :param name: the threads' name prefix.
    :param handoff: where the loop's thread counts the workers it wakes
        (``None``: it never waits for them).
    :param carries: whether a worker carries on to the plain callbacks its
        callbacks' publishes reach (see ``_lanes``).
    :param size: workers kept while idle; more start while all are busy.
    """

    def __init__(self, *, name: str, handoff: Handoff | None, carries: bool, size: int = POOL_SIZE) -> None:
        self._name = name
        self._handoff = handoff
        self._carries = carries
        self.size = size
        self._lock = threading.Lock()
        #: Idle workers less work queued for them (negative: work waits for a worker about to idle).
        self._idle = 0
        self._threads: list[threading.Thread] = []
        self._started = 0
        self._closed = False
        #: (lane, work, handed by the loop's thread, when it was handed: monotonic ns); None: exit.
        self._inbox: queue.SimpleQueue[tuple[Lane, Work, bool, int] | None] = queue.SimpleQueue()

    def hand(self, lane: Lane, work: Work, *, from_loop: bool) -> None:
        """Run ``work`` (its slot in ``lane`` taken) on an idle worker, or on a new one when
        every worker is busy. ``from_loop``: handed by the loop's thread, which waits for
        the worker to start (``Handoff``)."""
        thread: threading.Thread | None = None
        with self._lock:
            if self._idle > 0:
                self._idle -= 1
            else:
                self._started += 1
                thread = threading.Thread(target=self._work, name=f"{self._name}-{self._started}", daemon=True)
                self._threads.append(thread)
        handoff = self._handoff
        handed = handoff is not None and from_loop
        if handoff is not None and handed:
            handoff.handed()
        self._inbox.put((lane, work, handed, time.monotonic_ns()))
        if thread is not None:
            with executor_work():  # started in a node's callback maybe, but the executor's thread
                thread.start()

    def _work(self) -> None:
        if self._carries:
            mark_carrier()  # its publishes to plain callbacks need not wake the loop
        inbox = self._inbox
        # Never on one CPU (Handoff's spin: see Dispatcher), where lingering
        # keeps the loop thread it waits for off the CPU.
        lingering = self._handoff if self._handoff is not None and self._handoff.spin else None
        quick = False  # the last work came soon after this thread was free: linger before the next
        while True:
            free_from = time.monotonic_ns()
            if quick and lingering is not None and inbox.empty():
                lingering.linger(WORKER_LINGER_NS)
            try:
                item = inbox.get(timeout=WORKER_IDLE_S)
            except queue.Empty:
                if self._retire(idle=True):
                    return
                continue
            if item is None:
                return
            lane, work, handed, handed_at = item
            del item
            quick = handed_at - free_from < WORKER_LINGER_NS
            handoff = self._handoff if handed else None
            if handoff is not None:
                handoff.started()
            try:
                lane.run_handed(work)
            finally:
                if handoff is not None:
                    handoff.finished()
            # Not kept while this thread waits for other lanes' work: the work holds its
            # callback, and with it its node (an unloaded node would live on).
            del lane, work
            if self._retire(idle=False):
                return

    def _retire(self, *, idle: bool) -> bool:
        """Whether this worker ends now: it waited :data:`WORKER_IDLE_S` for nothing
        (``idle``), or it just finished a callback and the pool is above its size; never
        while work is on its way to it (the count says so under the lock)."""
        with self._lock:
            if self._closed:
                self._drop_current()
                return True
            if idle:
                if self._idle <= 0:
                    return False  # work is on its way to this thread: take it
                self._idle -= 1
            elif self._idle >= 0 and len(self._threads) > self.size:
                pass  # nothing waits for this thread, and the pool is above its size
            else:
                self._idle += 1
                return False
            self._drop_current()
            return True

    def _drop_current(self) -> None:
        current = threading.current_thread()
        if current in self._threads:
            self._threads.remove(current)

    @property
    def threads(self) -> list[threading.Thread]:
        """The workers alive."""
        with self._lock:
            return [thread for thread in self._threads if thread.is_alive()]

    def close(self, *, timeout: float) -> bool:
        """Let every worker end once its callback returns; join them.

        :return: ``False`` if one was still running a callback when ``timeout``
            ran out (a daemon thread, which cannot be killed).
        """
        with self._lock:
            self._closed = True
            threads = list(self._threads)
        for _ in threads:
            self._inbox.put(None)
        deadline = time.monotonic() + timeout
        joined = True
        for thread in threads:
            if thread is threading.current_thread():
                continue  # closing from one of our own callbacks
            thread.join(max(0.0, deadline - time.monotonic()))
            joined = joined and not thread.is_alive()
        return joined
