"""Waitables whose own code raises: left out, tried again a few times, then set aside.

A waitable is user code run inside the wait itself. One that keeps raising
(rclpy 9's ``Waitable.__enter__`` raises ``NotImplementedError`` unless a
subclass defines it: a waitable written for Jazzy) would flood the log and
starve its node's other entities if it were tried on every wait; it is
reported once and left out from then on. rclpy's own executors raise out of
``spin`` instead.

But a waitable may also be seen half built: Kilted's ``ActionClient`` adds
itself to its node (which wakes the executor) before it makes the lock its
``get_num_entities`` takes, so a wait set rebuilt on another thread in that
window gets an ``AttributeError`` from a client that works a moment later.
So a failure only leaves the waitable out for a while (:data:`_RETRY_AFTER_NS`);
it is set aside when it fails again on every retry.
"""

from __future__ import annotations

import threading
import time
import weakref
from dataclasses import dataclass

__all__ = ["WaitableFaults"]

#: After a waitable's first, second and third failure in a row, how long it is
#: left out before it is tried again (ns); a fourth failure sets it aside,
#: about 0.56 s after the first. A half-built waitable is whole within
#: microseconds, or within a GIL switch interval (5 ms) on a busy machine.
_RETRY_AFTER_NS = (5_000_000, 50_000_000, 500_000_000)
#: A failure this long (ns) after the first of a run of failures starts a new
#: run: a waitable that fails now and then is tried again each time, one that
#: keeps failing is set aside.
_RUN_NS = 2_000_000_000


@dataclass(slots=True)
class _Failures:
    """A waitable's run of failures."""

    #: The waitable (weakly where it can be), to tell it from another object at the same address.
    held: weakref.ref[object] | object
    first_ns: int
    count: int = 0
    #: Left out until then (monotonic ns); 0 once that time came (tried again at the next rebuild).
    retry_at_ns: int = 0

    def holds(self, waitable: object) -> bool:
        return _is(self.held, waitable)


def _hold(waitable: object) -> weakref.ref[object] | object:
    try:
        return weakref.ref(waitable)
    except TypeError:  # not weakly referenceable: kept alive here
        return waitable


def _is(held: weakref.ref[object] | object, waitable: object) -> bool:
    """Whether what :func:`_hold` made of a waitable is ``waitable`` (not another object at its address)."""
    return (held() if isinstance(held, weakref.ref) else held) is waitable


class WaitableFaults:
    """Which waitables are left out of the wait sets, for now or for good (any thread)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        #: Waitables in a run of failures, by identity.
        self._failing: dict[int, _Failures] = {}
        #: Waitables set aside for good, by identity.
        self._set_aside: dict[int, weakref.ref[object] | object] = {}
        #: The earliest retry still to come (monotonic ns; 0: none). Read by the
        #: wait sets before each wait, without the lock.
        self.retry_at_ns = 0

    def failed(self, waitable: object) -> tuple[int, float] | None:
        """Record that ``waitable``'s own code raised.

        :return: ``None`` while it is only left out for a while; once it is
            set aside, how many times it failed in a row and over how many seconds.
        """
        key = id(waitable)
        now = time.monotonic_ns()
        with self._lock:
            failures = self._failing.get(key)
            if failures is None or not failures.holds(waitable) or now - failures.first_ns > _RUN_NS:
                failures = self._failing[key] = _Failures(_hold(waitable), now)
            failures.count += 1
            if failures.count > len(_RETRY_AFTER_NS):
                del self._failing[key]
                self._set_aside[key] = failures.held
                self._next_retry()
                return failures.count, (now - failures.first_ns) / 1e9
            failures.retry_at_ns = now + _RETRY_AFTER_NS[failures.count - 1]
            self._next_retry()
            return None

    def left_out(self, waitable: object) -> bool:
        """Whether ``waitable`` stays out of the wait set being built (set aside, or its retry not yet due)."""
        if not self._failing and not self._set_aside:
            return False
        key = id(waitable)
        with self._lock:
            kept = self._set_aside.get(key)
            if kept is not None:
                if _is(kept, waitable):
                    return True
                del self._set_aside[key]  # another object at a reused address
            failures = self._failing.get(key)
            if failures is None:
                return False
            if not failures.holds(waitable) or (
                failures.retry_at_ns == 0 and time.monotonic_ns() - failures.first_ns > _RUN_NS
            ):
                del self._failing[key]  # another object, or a run long over
                return False
            return failures.retry_at_ns != 0

    def retries_due(self) -> bool:
        """Whether a retry's time came (its waitable is taken back at the next rebuild)."""
        now = time.monotonic_ns()
        with self._lock:
            due = False
            for failures in self._failing.values():
                if failures.retry_at_ns and failures.retry_at_ns <= now:
                    failures.retry_at_ns = 0
                    due = True
            self._next_retry()
        return due

    def _next_retry(self) -> None:
        self.retry_at_ns = min((f.retry_at_ns for f in self._failing.values() if f.retry_at_ns), default=0)
