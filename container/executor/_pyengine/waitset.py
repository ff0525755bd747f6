"""An rcl wait set over entities given once, their handles held (``fastpath/waitset.c``).

The compiled ``WaitSet`` fills, waits on and reads an rcl wait set in one
call, where rclpy's takes a call per entity to fill and one per kind to
read, on every wait. Here it is rclpy's own wait set
(``container._compat.WaitSet``), filled from the handles held since
construction and read into the same answer: ``()`` when nothing was ready
(rcl's timeout), else the six lists of ready addresses (subscriptions,
guard conditions, timers, clients, services, events), each in the order
the entities were given.

Differences: a poll (``poll=True``: a wait whose guard condition is
already triggered, so ``rcl_wait`` returns at once) lets go of the GIL,
as rclpy's ``wait`` always does; the compiled one keeps it, because a
release once a millisecond while a chain of callbacks runs woke a waiting
thread each time, too late to take the GIL, and restarted its wait for
CPython's forced switch (a plain 20 Hz timer beside a busy chain ran 0-12
times in 4 s instead of 80; see the design notes). Both bound a poll to
:data:`POLL_HOLD_MAX_NS`. The ``notifier`` and ``handoff`` it is given are
only checked: the compiled one tells the notifier when each wait ends at
the latest (so that a carrier's publish need not wake it) and stays awake,
before blocking, for the answer of plain work it handed over; neither
happens here (see ``notifier`` and ``handoff``). And every timer is in
every wait, as in rclpy's wait set: the compiled one gives ``rcl_wait``
only those due next and keeps the others in a heap of their deadlines
(``rcl_wait`` reads every timer's clock, and Fast DDS attaches every
timer's guard condition, on each wait: at 500 nodes, over half of a
process's CPU). The same timers fire at the same times; here what a wait
costs grows with the count of timers (``timers_waited`` tells either way).
"""

from __future__ import annotations

import operator
from collections.abc import Sequence
from typing import Any

from ..._compat import WaitSet as RclpyWaitSet
from .handoff import Handoff
from .held import Held, enter_all, exit_all
from .notifier import Notifier

__all__ = ["POLL_HOLD_MAX_NS", "WaitSet", "poll"]

#: The longest a poll may wait in ``rcl_wait``, should its guard condition
#: not be in the wait set after all (destroyed at shutdown).
POLL_HOLD_MAX_NS = 1_000_000

#: The kinds of entity, in the order of the wait set's slots and of its answer.
_KINDS = ("subscription", "guard_condition", "timer", "client", "service", "event")


def poll_timeout(timeout: int) -> int:
    """The timeout of a poll: at most :data:`POLL_HOLD_MAX_NS`, whatever it was asked."""
    return POLL_HOLD_MAX_NS if timeout < 0 or timeout > POLL_HOLD_MAX_NS else timeout


def poll(wait_set: Any, timeout_ns: int, /) -> None:
    """``rcl_wait`` on rclpy's wait set (its handle, held and entered for the call): for a
    wait whose guard condition is already triggered. It lets go of the GIL here (see the module)."""
    timeout = operator.index(timeout_ns)
    held = Held(wait_set)
    try:
        held.handle.wait(poll_timeout(timeout))
    finally:
        held.exit()


class WaitSet:
    """An rcl wait set over entities given once (their handles held until :meth:`close`)."""

    __slots__ = ("_context", "_entities", "_wait_set", "_waiting", "timers_waited")

    def __init__(
        self,
        context: Any,
        *,
        subscriptions: Sequence[Any] = (),
        guard_conditions: Sequence[Any] = (),
        timers: Sequence[Any] = (),
        clients: Sequence[Any] = (),
        services: Sequence[Any] = (),
        events: Sequence[Any] = (),
        notifier: Notifier | None = None,
        handoff: Handoff | None = None,
    ) -> None:
        if getattr(self, "_context", None) is not None:
            raise RuntimeError("WaitSet is initialised once")
        self._context: Held | None = None
        self._entities: list[list[Held]] = []
        self._wait_set: Any = None
        #: How many timers the last wait gave ``rcl_wait``: all of them, here.
        self.timers_waited = 0
        #: A thread is in ``rcl_wait`` without the GIL: :meth:`close` must not free under it.
        self._waiting = False
        if notifier is not None and not isinstance(notifier, Notifier):
            raise TypeError("notifier must be a Notifier or None")
        if handoff is not None and not isinstance(handoff, Handoff):
            raise TypeError("handoff must be a Handoff or None")
        held_context = Held(context)
        entities: list[list[Held]] = []
        try:
            for given in (subscriptions, guard_conditions, timers, clients, services, events):
                entities.append(enter_all(given))
            wait_set = RclpyWaitSet(*(len(held) for held in entities), held_context.handle)
        except BaseException:
            for held in reversed(entities):
                exit_all(held)
            held_context.exit()
            raise
        self._context = held_context
        self._entities = entities
        self._wait_set = wait_set

    def wait(self, timeout_ns: int, poll: bool = False, /) -> tuple[list[int], ...]:
        """Wait at most ``timeout_ns`` (negative: no limit; a poll: at most
        :data:`POLL_HOLD_MAX_NS`): ``()`` when nothing was ready, else the ready
        addresses of each kind."""
        timeout = operator.index(timeout_ns)
        wait_set = self._wait_set
        if wait_set is None:
            raise RuntimeError("WaitSet not initialised, or closed")
        subscriptions, guards, timers, clients, services, events = self._entities
        wait_set.clear_entities()
        for add, entities in (
            (wait_set.add_subscription, subscriptions),
            (wait_set.add_guard_condition, guards),
            (wait_set.add_timer, timers),
            (wait_set.add_client, clients),
            (wait_set.add_service, services),
        ):
            for held in entities:
                add(held.handle)
        indices = [wait_set.add_event(held.handle) for held in events]
        self.timers_waited = len(timers)
        if poll:
            wait_set.wait(poll_timeout(timeout))
        else:
            self._waiting = True
            try:
                wait_set.wait(timeout)
            finally:
                self._waiting = False
        ready = (
            *(
                wait_set.get_ready_entities(kind) if entities else []
                for kind, entities in zip(_KINDS, (subscriptions, guards, timers, clients, services), strict=False)
            ),
            [held.pointer for held, index in zip(events, indices, strict=True) if wait_set.is_ready("event", index)],
        )
        # rcl's timeout is "nothing ready": rclpy's wait does not tell it apart.
        return ready if any(ready) else ()

    def close(self) -> None:
        """Let every handle go; a wait after this raises ``RuntimeError``."""
        if self._waiting:
            raise RuntimeError("WaitSet.close() while a thread waits in it: wake it first")
        self._close()

    def _close(self) -> None:
        """The rcl wait set goes (it points at the entities), then the handles, the context last."""
        wait_set, self._wait_set = self._wait_set, None
        if wait_set is not None:
            wait_set.destroy_when_not_in_use()
        for held in reversed(self._entities):
            exit_all(held)
        context, self._context = self._context, None
        if context is not None:
            context.exit()

    def __del__(self) -> None:
        self._close()
