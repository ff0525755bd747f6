"""The event loop's ``call_soon`` and ``call_at``, which meter what a node's code schedules
(``fastpath/handles.c``).

The executor's own loop (``container/executor/_loop.py``) credits each
handle to the node whose code scheduled it: the node is in the context the
handle is scheduled in (a ``ContextVar``, see ``_owners``), and its
callback is scheduled wrapped in that node's ``Meter.call``. asyncio
schedules every wake-up of every task through ``call_soon``, the loop's
hottest method, and every sleep and timeout through ``call_at``: the
compiled engine overrides both in C, these are the same overrides in
Python. A loop class takes this class as its first base, the loop's own
class second.

A call goes through unchanged when the context names the executor's own
work, or (``call_soon``) when the callback is a step or a wake-up of an
asyncio task (its ``__self__`` is a task). Otherwise it is scheduled as
``account.call(arrived, callback, *args)``, where ``account`` is the
owner's account of ``loop_callback`` (``call_soon``; ``arrived`` now) or
``loop_timer`` (``call_at``; ``arrived`` its due time in ns, 0 when it is
no finite number), of the node's owner, or of the unattributed owner when
the context names nobody or is not a ``contextvars.Context``. The accounts
of the last :data:`KEPT` owners seen are kept per kind, the oldest let go
first.

Difference: none in what it does; it costs a Python call more per handle.
"""

from __future__ import annotations

import contextvars
import math
import time
from collections.abc import Callable
from typing import Any

__all__ = ["HandleMeter"]

_monotonic_ns = time.monotonic_ns
#: Owners whose account's call is kept, per kind (the compiled engine's ``KEPT_SLOTS``).
KEPT = 16
_USAGE = (
    "HandleMeter(owner: ContextVar, executor, task_type: type, call_soon: callable, call_at: callable, unattributed)"
)


class _State:
    """What ``__init__`` was given, and the owners' accounts' calls kept per kind."""

    __slots__ = ("at", "call_at", "call_soon", "executor", "owner", "soon", "task_type", "unattributed")

    def __init__(self, *args: Any) -> None:
        (self.owner, self.executor, self.task_type, self.call_soon, self.call_at, self.unattributed) = args
        #: Owner -> its account's call, per kind, oldest first (held: the call stays its owner's).
        self.soon: dict[object, Callable[..., Any]] = {}
        self.at: dict[object, Callable[..., Any]] = {}


def _owner_in(state: _State, context: object) -> Any:
    if context is None:
        return state.owner.get()
    if type(context) is contextvars.Context:
        return context.get(state.owner)
    return None


class HandleMeter:
    """The first base of an event loop whose ``call_soon`` and ``call_at`` meter each handle a
    node's code schedules as that node's."""

    __slots__ = ()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        if kwargs:
            raise TypeError(_USAGE)
        if len(args) != 6:
            raise TypeError(f"HandleMeter() takes exactly 6 arguments ({len(args)} given)")
        owner, _, task_type, call_soon, call_at, _ = args
        if (
            type(owner) is not contextvars.ContextVar
            or not isinstance(task_type, type)
            or not callable(call_soon)
            or not callable(call_at)
        ):
            raise TypeError(_USAGE)
        self.__dict__["_handle_meter"] = _State(*args)  # the loop's instance dictionary

    def _state(self) -> _State:
        state: _State | None = self.__dict__.get("_handle_meter")
        if state is None:
            raise TypeError("HandleMeter.__init__ was not called")
        return state

    @staticmethod
    def _call(state: _State, kind: str, owner: object) -> Callable[..., Any]:
        """``owner``'s account of ``kind``: its call, kept for next time."""
        if owner is None:
            owner = state.unattributed
        kept = state.soon if kind == "loop_callback" else state.at
        found = kept.get(owner)
        if found is not None:
            return found
        call: Callable[..., Any] = owner.account(kind).call  # type: ignore[attr-defined]
        if len(kept) >= KEPT:
            del kept[next(iter(kept))]  # the oldest
        kept[owner] = call
        return call

    def call_soon(self, *args: Any, **kwargs: Any) -> Any:
        """``call_soon(callback, *args, context=None)``: the loop's own, a node's handle metered as its."""
        state = self._state()
        schedule: Callable[..., Any] = state.call_soon
        if not args:
            return schedule(self, *args, **kwargs)  # the loop's own call_soon says what is missing
        if isinstance(getattr(args[0], "__self__", None), state.task_type):
            return schedule(self, *args, **kwargs)  # a task's step: the commonest, told first
        owner = _owner_in(state, kwargs.get("context"))
        if owner is state.executor:
            return schedule(self, *args, **kwargs)
        return schedule(self, self._call(state, "loop_callback", owner), _monotonic_ns(), *args, **kwargs)

    def call_at(self, *args: Any, **kwargs: Any) -> Any:
        """``call_at(when, callback, *args, context=None)``: the loop's own, a node's timer metered
        as its, late from ``when``."""
        state = self._state()
        schedule: Callable[..., Any] = state.call_at
        if len(args) < 2:
            return schedule(self, *args, **kwargs)  # the loop's own call_at says what is missing
        owner = _owner_in(state, kwargs.get("context"))
        if owner is state.executor:
            return schedule(self, *args, **kwargs)
        call = self._call(state, "loop_timer", owner)
        try:
            when = float(args[0])
        except (TypeError, ValueError):
            when = 0.0  # no number: the loop's own call_at has its say
        arrived = int(when * 1e9) if math.isfinite(when) and abs(when) < 9e9 else 0
        return schedule(self, args[0], call, arrived, *args[1:], **kwargs)
