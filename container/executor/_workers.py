"""The worker threads that run plain callbacks: one pool for every lane of a dispatcher.

A lane (``_lanes``) decides *whether* a plain callback may start (its
group's limit); the pool decides *where*. Each lane used to keep threads of
its own, so a container held a thread for every group that had run a plain
callback in the last :data:`WORKER_IDLE_S`: 69 threads for 100 demo nodes,
119 for the demo mix. Threads here are shared: work goes to an idle worker
when there is one, and to a new one while the pool has fewer than
:attr:`WorkerPool.size`. With every worker busy, work waits in the pool's
backlog, which a worker drains before it goes idle; a monitor (as Go's
sysmon) starts one more thread whenever the backlog waited
:data:`STUCK_S` with no worker finishing anything: the workers are blocked,
not busy. So a callback that blocks for good holds one thread and delays
others by :data:`STUCK_S` (:data:`STUCK_MAX_S` at most), while a burst of short callbacks (50
messages at once) is run by the threads there are, not by a thread started
per message: started so, then ending as their callback returned, threads
were started on every burst, each start a stall of the loop, and a
hundred-node container's start-up took 2.58x plain rclpy's (1.69x with a
thread per lane). Past :attr:`WorkerPool.size`, a worker exits once its
callback returned, if the backlog is empty or another worker finished
something meanwhile (the others are not all blocked: the pool shrinks back
once the blockers are done, even under a backlog that never empties);
below it, one idle for :data:`WORKER_IDLE_S` exits too, and so does the
monitor, so an idle container keeps no thread here.
"""

from __future__ import annotations

import collections
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
#: After this many lingers in a row that saw no work handed over, the worker
#: skips its next :data:`WORKER_LINGER_SKIP` lingers, twice as many after
#: each such round up to :data:`WORKER_LINGER_SKIP_MAX`, back to
#: :data:`WORKER_LINGER_SKIP` once a linger sees work: the loop's own
#: backoff (``fastpath/handoff.c``, ``LOOP_MISSES_MAX``), with its values.
#:
#: Shared by every lane, the worker on top of the stack sees the work of
#: all of them, which comes "quickly" far more often than one lane's did:
#: ten nodes' 100 Hz timers (1,000 firings a second at random moments) had
#: it spin 250 us for a fifth of them, for nothing, and the ten-node load
#: cost 1.12x the CPU of a thread per lane (``bench_executor.py --only
#: load``, side by side). A request-answer exchange, where lingering pays,
#: sees the work within the linger and never backs off.
WORKER_LINGER_MISSES = 2
WORKER_LINGER_SKIP = 32
WORKER_LINGER_SKIP_MAX = 4096
#: Workers kept while idle (up to :data:`WORKER_IDLE_S`); those started past
#: it, while every worker was blocked, exit when their callback returns.
POOL_SIZE: Final = 8
#: How long work may wait in the backlog with no worker finishing anything
#: before the monitor starts another thread for it, when the monitor woke on
#: time: what a blocked callback delays another group's, once every worker
#: is blocked.
STUCK_S = 0.005
#: How long work waits in the backlog with no worker finishing, however
#: late the monitor woke (see :meth:`WorkerPool._watch`).
STUCK_MAX_S = 0.05


class _Worker:
    """One thread of the pool and the inbox only it reads."""

    __slots__ = ("inbox", "thread")

    def __init__(self) -> None:
        #: (lane, work, handed by the loop's thread, when it was handed: monotonic ns); None: exit.
        self.inbox: queue.SimpleQueue[tuple[Lane, Work, bool, int] | None] = queue.SimpleQueue()
        self.thread: threading.Thread | None = None


class WorkerPool:
    """Threads that run the plain work lanes hand them.

    Idle workers wait on a stack: work goes to the one that went idle last,
    the only one that lingers awake (``Handoff.linger``) and the likeliest
    to be still on a CPU. With one queue shared by every worker, work went
    to the one idle longest, asleep, while the last one lingered for nothing:
    plain service calls ran at 0.71x and ping-pong at 0.78x of a thread per
    lane (``bench_executor.py``, side by side).

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
        #: The monitor waits on it for a backlog.
        self._backlogged = threading.Condition(self._lock)
        #: Idle workers, the one idle last on top.
        self._idle: list[_Worker] = []
        #: Every worker alive or starting.
        self._workers: list[_Worker] = []
        #: Work every worker was too busy for, oldest first: the next to finish takes it.
        self._backlog: collections.deque[tuple[Lane, Work]] = collections.deque()
        #: Works finished, in all: the monitor's sign that the workers are not all blocked.
        self._finished = 0
        self._monitor: threading.Thread | None = None
        self._started = 0
        self._closed = False

    def hand(self, lane: Lane, work: Work, *, from_loop: bool) -> None:
        """Run ``work`` (its slot in ``lane`` taken) on the worker idle last, or on a new one
        below the pool's size, or after the work the backlog holds (the monitor adds a
        thread should the workers be blocked). ``from_loop``: handed by the loop's thread,
        which waits for the worker to start (``Handoff``); never for backlog work."""
        monitor = None
        with self._lock:
            if self._idle:
                worker = self._idle.pop()
            elif len(self._workers) < self.size:
                worker = self._new_worker()
            else:
                self._backlog.append((lane, work))
                if self._monitor is None:
                    monitor = self._monitor = threading.Thread(
                        target=self._watch, name=f"{self._name}-monitor", daemon=True
                    )
                elif len(self._backlog) == 1:
                    self._backlogged.notify()
                worker = None
        if worker is None:
            if monitor is not None:
                with executor_work():
                    monitor.start()
            return
        handoff = self._handoff
        handed = handoff is not None and from_loop
        if handoff is not None and handed:
            handoff.handed()
        worker.inbox.put((lane, work, handed, time.monotonic_ns()))
        self._start(worker)

    def _new_worker(self) -> _Worker:
        """A worker counted in the pool (the caller holds the lock); :meth:`_start` starts it."""
        worker = _Worker()
        self._started += 1
        worker.thread = threading.Thread(
            target=self._work, args=(worker,), name=f"{self._name}-{self._started}", daemon=True
        )
        self._workers.append(worker)
        return worker

    @staticmethod
    def _start(worker: _Worker) -> None:
        thread = worker.thread
        if thread is not None and thread.ident is None:
            with executor_work():  # started in a node's callback maybe, but the executor's thread
                thread.start()

    def _watch(self) -> None:
        """The monitor: while work waits in the backlog and no worker finishes anything, one
        more thread (the workers are blocked); ends idle, or closed.

        No worker finishing in :data:`STUCK_S` means blocked only if this thread woke on
        time: one that wakes late was waiting for the GIL, and so were the workers,
        running (the loop creating a hundred nodes). Taken for blocked, that started a
        thread a burst, as before the backlog. :data:`STUCK_MAX_S` without a finish
        starts one however late: workers blocked beside a loop that never lets go.
        """
        with self._lock:
            while not self._closed:
                if not self._backlog:
                    if not self._backlogged.wait(WORKER_IDLE_S) and not self._backlog:
                        self._monitor = None
                        return
                    continue
                finished = self._finished
                since = time.monotonic()
                while True:
                    before = time.monotonic()
                    self._backlogged.wait(STUCK_S)  # only close notifies it meanwhile
                    now = time.monotonic()
                    if self._closed or not self._backlog or self._finished != finished:
                        break
                    if now - before < STUCK_S * 1.5 or now - since >= STUCK_MAX_S:
                        self._add_for_backlog()
                        break
            self._monitor = None

    def _add_for_backlog(self) -> None:
        """One more worker, for the backlog's oldest work (the caller holds the lock)."""
        worker = self._new_worker()
        worker.inbox.put((*self._backlog.popleft(), False, time.monotonic_ns()))
        self._lock.release()
        try:
            self._start(worker)
        finally:
            self._lock.acquire()

    def _work(self, me: _Worker) -> None:
        if self._carries:
            mark_carrier()  # its publishes to plain callbacks need not wake the loop
        inbox = me.inbox
        idle = self._idle
        # Never on one CPU (Handoff's spin: see Dispatcher), where lingering
        # keeps the loop thread it waits for off the CPU.
        lingering = self._handoff if self._handoff is not None and self._handoff.spin else None
        quick = False  # the last work came soon after this thread was free: linger before the next
        misses, skip, backoff = 0, 0, WORKER_LINGER_SKIP
        free_from = time.monotonic_ns()
        #: Work from the backlog, taken as the last finished: run next, no wait.
        item: tuple[Lane, Work, bool, int] | None = None
        while True:
            if item is None:
                # Only the worker on top of the stack (the next to be handed work) stays awake.
                if quick and lingering is not None and idle and idle[-1] is me and inbox.empty():
                    if skip > 0:
                        skip -= 1
                    elif lingering.linger(WORKER_LINGER_NS):
                        misses, backoff = 0, WORKER_LINGER_SKIP
                    else:
                        misses += 1
                        if misses >= WORKER_LINGER_MISSES:
                            misses, skip = 0, backoff
                            backoff = min(backoff * 2, WORKER_LINGER_SKIP_MAX)
                try:
                    item = inbox.get(timeout=WORKER_IDLE_S)
                except queue.Empty:
                    if self._retire_idle(me):
                        return
                    continue
                if item is None:
                    return
            lane, work, handed, handed_at = item
            item = None
            # Read without the lock (an int): what the others finish meanwhile is judged against it.
            finished_before = self._finished
            quick = handed_at - free_from < WORKER_LINGER_NS
            handoff = self._handoff if handed else None
            if handoff is not None:
                handoff.started()
            try:
                lane.run_handed(work)
            finally:
                # Not kept while this thread waits for other lanes' work: the work holds its
                # callback, and with it its node (an unloaded node would live on).
                del lane, work
                # Idle (or gone) before the loop hears it finished: the loop holds the GIL
                # from then until it hands the next work, which would otherwise find no
                # idle worker and start a thread for almost every request.
                after = self._idle_again(me, finished_before)
                free_from = time.monotonic_ns()
                if handoff is not None:
                    handoff.finished()
            if after is True:
                return
            if after is not False:
                item = (*after, False, free_from)

    def _idle_again(self, me: _Worker, finished_before: int) -> tuple[Lane, Work] | bool:
        """``me`` finished its work: the backlog's oldest work for it to run next, else
        ``False`` (it is back on the idle stack) or ``True``: it ends now (the pool is
        closed, or above its size: it was started while every worker was blocked).

        Above the pool's size, a worker leaves the backlog to the others once any of them
        finished something while it ran: they are not all blocked, so it is not needed.
        Kept on while the backlog lasted, every thread the monitor started in a slow
        moment of an overloaded container (a hundred listeners logging every message,
        each worker waiting for the GIL) stayed for as long as the overload: 67 threads
        for the demo mix, each one more for the GIL to go round.

        :param finished_before: :attr:`_finished` when ``me`` started its work.
        """
        with self._lock:
            others_finished = self._finished != finished_before
            self._finished += 1
            above_size = len(self._workers) > self.size
            if self._backlog and not (above_size and others_finished and not self._closed):
                return self._backlog.popleft()
            if self._closed or above_size:
                self._workers.remove(me)
                return True
            self._idle.append(me)
            return False

    def _retire_idle(self, me: _Worker) -> bool:
        """``me`` waited :data:`WORKER_IDLE_S` for nothing: whether it ends, which it does
        unless work was handed to it meanwhile (it is then off the idle stack)."""
        with self._lock:
            if me not in self._idle:
                return False  # work is on its way to this thread: take it
            self._idle.remove(me)
            self._workers.remove(me)
            return True

    @property
    def threads(self) -> list[threading.Thread]:
        """The workers alive, and the monitor."""
        with self._lock:
            threads = [w.thread for w in self._workers if w.thread is not None]
            if self._monitor is not None:
                threads.append(self._monitor)
        return [thread for thread in threads if thread.is_alive()]

    def close(self, *, timeout: float) -> bool:
        """Let every worker end once its callback returns; join them.

        :return: ``False`` if one was still running a callback when ``timeout``
            ran out (a daemon thread, which cannot be killed).
        """
        with self._lock:
            self._closed = True
            workers = list(self._workers)
            self._idle.clear()
            self._backlogged.notify_all()
            monitor = self._monitor
        # Workers busy take the backlog before they see this.
        for worker in workers:
            worker.inbox.put(None)
        if monitor is not None and monitor is not threading.current_thread():
            monitor.join(timeout)
        deadline = time.monotonic() + timeout
        joined = True
        for worker in workers:
            thread = worker.thread
            if thread is None or thread is threading.current_thread() or thread.ident is None:
                continue  # closing from one of our own callbacks, or never started
            thread.join(max(0.0, deadline - time.monotonic()))
            joined = joined and not thread.is_alive()
        return joined
