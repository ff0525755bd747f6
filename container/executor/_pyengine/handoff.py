"""The busy loop thread lets go of the GIL until the workers it woke have started (``fastpath/handoff.c``).

A plain callback runs on its lane's worker thread, which needs the GIL.
While the loop's thread is busy (an asyncio task publishing in a loop) it
never sleeps, so the worker gets the GIL only when CPython forces a switch
(``sys.getswitchinterval()``, 5 ms). So the loop thread, before its next
asyncio iteration, waits (without the GIL: a ``threading.Condition``) until
each worker it handed work to since has started, bounded by a timeout
(:meth:`Handoff.give`). It waits for the start, not the end: a callback
that blocks lets the GIL go, and the loop runs on at once.

Differences: the compiled one then stays awake, spinning on
``sched_yield`` without the GIL, for those workers to finish (``spin_ns``),
a worker lingers awake for the next hand-over (:meth:`Handoff.linger`),
and the loop stays awake in ``WaitSet.wait`` for an answer: on a virtual
machine an idle core costs 50-200 us to wake. A Python loop cannot spin
without the GIL (spinning with it starves the very thread it waits for),
so here nothing spins: ``give`` returns once the workers started,
``linger`` returns ``False`` at once, and :attr:`Handoff.lingered` stays 0.
"""

from __future__ import annotations

import threading
import time

__all__ = ["Handoff"]


class Handoff:
    """The busy loop thread lets go of the GIL until the workers it woke have started.

    ``spin``: whether a thread may stay awake for another's hand-over (kept
    and told, as the compiled one's; nothing spins here).
    """

    __slots__ = ("_given", "_outstanding", "_spin", "_started", "_waiting")

    def __init__(self, *, spin: bool = True) -> None:
        self._spin = bool(spin)
        #: Guards ``_outstanding`` and ``_waiting``; the loop waits on it in :meth:`give`.
        self._started = threading.Condition(threading.Lock())
        #: Handed and not yet started.
        self._outstanding = 0
        #: The loop thread waits in :meth:`give`.
        self._waiting = False
        #: Gives that waited (for tests and benchmarks).
        self._given = 0

    @property
    def spin(self) -> bool:
        """Whether a thread may stay awake (spinning) for another's hand-over."""
        return self._spin

    def handed(self) -> None:
        """The loop thread just woke a worker with plain work."""
        with self._started:
            self._outstanding += 1

    def started(self) -> None:
        """A worker woken by :meth:`handed` holds the GIL and its work."""
        with self._started:
            if self._outstanding > 0:
                self._outstanding -= 1
            if self._outstanding == 0 and self._waiting:
                self._started.notify()

    def finished(self) -> None:
        """A worker that :meth:`started` is done and about to wait for work again
        (what the compiled one's spinning waits for; nothing does here)."""

    def give(self, timeout_ns: int, spin_ns: int = 0, /) -> bool:
        """Wait, without the GIL, until every handed worker started (at most ``timeout_ns``);
        ``False`` at once when none is outstanding. ``spin_ns``: how long the compiled one
        then stays awake for them to finish (not here: see the module)."""
        # A negative timeout is none: the executor gives a positive one (HANDOFF_WAIT_NS).
        deadline = time.monotonic() + max(timeout_ns, 0) / 1e9
        with self._started:
            if self._outstanding == 0:
                return False
            self._waiting = True
            waited = False
            while self._outstanding > 0:
                waited = True
                left = deadline - time.monotonic()
                if left <= 0 or not self._started.wait(left):
                    break
            # Not started in time (a worker starting up, a starved core): forget
            # them, or the next give would wait for them again.
            self._outstanding = 0
            self._waiting = False
        if waited:
            self._given += 1
        return waited

    def linger(self, spin_ns: int, /) -> bool:
        """On a worker: stay awake for the next hand-over; ``False`` at once here (no spinning)."""
        return False

    @property
    def outstanding(self) -> int:
        """Workers handed work and not started yet."""
        with self._started:
            return self._outstanding

    @property
    def given(self) -> int:
        """How often :meth:`give` let the GIL go."""
        return self._given

    @property
    def lingered(self) -> int:
        """The loop's waits that stayed awake and saw the answer (none here)."""
        return 0
