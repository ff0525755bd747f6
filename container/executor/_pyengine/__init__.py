"""The executor's engine in pure Python: the executable specification of the compiled one.

Each module here mirrors one source of ``container/executor/fastpath/``
(``held.py`` and ``held.c``, ``lanes.py`` and ``lanes.c``, ...) with the same
names and the same behaviour, read from the C, over rclpy's own calls where
C calls rcl; ``_fastpath.pyi`` describes both engines, and
``container.executor._engine`` chooses one (``CONTAINER_EXECUTOR_ENGINE``).
Put a C source beside its module to compare them; where Python cannot do
what C does (rmw's new-data callbacks, keeping the GIL through a poll,
spinning without it), the module's docstring says what is left out and
why, and ``docs/executor/engines.md`` lists it.
"""

from __future__ import annotations

from .deadline import Deadline
from .express import Express, first_step
from .handles import HandleMeter
from .handoff import Handoff
from .lanes import KeepLast, Route, Routes, Runner, Slots, Token, Work
from .lock import Lock
from .meter import Meter, stuck_after
from .notifier import CLIENT, DRAIN, EVENT, SERVICE, SUBSCRIPTION, Notifier, mark_carrier
from .service import Caller, Server
from .taker import Taker, publisher_gid
from .waitset import WaitSet, poll
from .watcher import FdWatcher

__all__ = [
    "CLIENT",
    "DRAIN",
    "EVENT",
    "SERVICE",
    "SUBSCRIPTION",
    "Caller",
    "Deadline",
    "Express",
    "FdWatcher",
    "HandleMeter",
    "Handoff",
    "KeepLast",
    "Lock",
    "Meter",
    "Notifier",
    "Route",
    "Routes",
    "Runner",
    "Server",
    "Slots",
    "Taker",
    "Token",
    "WaitSet",
    "Work",
    "first_step",
    "mark_carrier",
    "poll",
    "publisher_gid",
    "stuck_after",
]

