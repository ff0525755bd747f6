"""The event loop's ``call_soon``, which meters what a node's code schedules (``fastpath/handles.c``).

The executor's own loop (``container/executor/_loop.py``) credits each
handle to the node whose code scheduled it: the node is in the context the
handle is scheduled in (a ``ContextVar``, see ``_owners``), and its
callback is scheduled wrapped in that node's ``Meter.call``. asyncio
schedules every wake-up of every task through ``call_soon``, the loop's
hottest method: the compiled engine overrides it in C, this is the same
override in Python. A loop class takes it as its first base, the loop's
own ``call_soon`` second.

A call goes through unchanged when the context names the executor's own
work, or when the callback is a step or a wake-up of an asyncio task (its
``__self__`` is a task). Otherwise it is scheduled as
``account.call(arrived, callback, *args)``, where ``account`` is
``owner.account("loop_callback")`` of the node's owner (the unattributed
owner when the context names nobody, or is not a ``contextvars.Context``)
and ``arrived`` is now.

Difference: none in what it does; it costs a Python call more per handle.
"""

from __future__ import annotations

import contextvars
import time
from collections.abc import Callable
from typing import Any

__all__ = ["HandleMeter"]

_monotonic_ns = time.monotonic_ns
_USAGE = "HandleMeter(owner, executor, task_type, call_soon, unattributed)"


class HandleMeter:
    """The first base of an event loop whose ``call_soon`` meters each handle a node's code schedules."""

    __slots__ = ()

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        if kwargs:
            raise TypeError(_USAGE)
        if len(args) != 5:
            raise TypeError(f"HandleMeter() takes exactly 5 arguments ({len(args)} given)")
        owner, executor, task_type, call_soon, unattributed = args
        if type(owner) is not contextvars.ContextVar or not isinstance(task_type, type) or not callable(call_soon):
            raise TypeError(
                "HandleMeter(owner: ContextVar, executor, task_type: type, call_soon: callable, unattributed)"
            )
        state = self.__dict__  # the loop's instance dictionary
        state["_handle_meter"] = (owner, executor, task_type, call_soon, unattributed)

    def call_soon(self, *args: Any, **kwargs: Any) -> Any:
        """``call_soon(callback, *args, context=None)``: the loop's own, a node's handle metered as its."""
        state = self.__dict__.get("_handle_meter")
        if state is None:
            raise TypeError("HandleMeter.__init__ was not called")
        owner_var, executor, task_type, call_soon, unattributed = state
        schedule: Callable[..., Any] = call_soon
        if not args:
            return schedule(self, *args, **kwargs)  # the loop's own call_soon says what is missing
        context = kwargs.get("context")
        if context is None:
            owner = owner_var.get()
        elif type(context) is contextvars.Context:
            owner = context.get(owner_var)
        else:
            owner = None
        if owner is executor or isinstance(getattr(args[0], "__self__", None), task_type):
            return schedule(self, *args, **kwargs)
        account = (unattributed if owner is None else owner).account("loop_callback")
        return schedule(self, account.call, _monotonic_ns(), *args, **kwargs)
