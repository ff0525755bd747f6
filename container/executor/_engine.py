"""Which engine runs the executor's hot path: the compiled one, or its pure-Python twin.

Both provide the same names with the same behaviour (``_fastpath.pyi``
describes them): the compiled ``_fastpath`` (``fastpath/*.c``, built at
set-up) and ``_pyengine``, the executable specification of it, in Python
over rclpy's own calls. The compiled one is used unless
``CONTAINER_EXECUTOR_ENGINE=python`` asks for the other, or it cannot be
imported (a platform where the extension did not build): the Python one
then runs, slower, and the first executor made says why in one warning
line (:func:`announce`). Every module of the executor imports the engine's
names from here, never from either engine directly.
"""

from __future__ import annotations

import importlib
import logging
import os
from types import ModuleType
from typing import TYPE_CHECKING, Final

__all__ = [
    "CLIENT",
    "DRAIN",
    "ENGINE",
    "EVENT",
    "SERVICE",
    "SUBSCRIPTION",
    "VARIABLE",
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
    "announce",
    "first_step",
    "mark_carrier",
    "poll",
    "publisher_gid",
    "stuck_after",
]

#: The environment variable that chooses: ``compiled`` (the default) or ``python``.
VARIABLE: Final = "CONTAINER_EXECUTOR_ENGINE"
#: Each engine's module.
_ENGINES: Final = {"compiled": "._fastpath", "python": "._pyengine"}

_log = logging.getLogger("container.executor")


def _choose() -> tuple[ModuleType, str, str | None]:
    """The engine module, its name, and why it is not the one asked for (``None``: it is)."""
    wanted = os.environ.get(VARIABLE, "").strip().lower() or "compiled"
    why: str | None = None
    if wanted not in _ENGINES:
        why = f"{VARIABLE}={wanted!r} is not one of {', '.join(sorted(_ENGINES))}"
        wanted = "compiled"
    if wanted == "compiled":
        try:
            return importlib.import_module(_ENGINES["compiled"], __package__), "compiled", why
        except ImportError as error:
            why = f"the compiled engine could not be imported ({error})"
    return importlib.import_module(_ENGINES["python"], __package__), "python", why


_module, ENGINE, _why = _choose()
_announced = False


def announce() -> None:
    """Say, once per process, that the engine is not the one asked for, and why."""
    global _announced
    if _why is None or _announced:
        return
    _announced = True
    _log.warning("%s: the executor runs on the %s engine", _why, ENGINE)


if TYPE_CHECKING:
    # One description of both engines: the stub of the compiled one.
    from ._fastpath import (
        CLIENT,
        DRAIN,
        EVENT,
        SERVICE,
        SUBSCRIPTION,
        Caller,
        Deadline,
        Express,
        FdWatcher,
        HandleMeter,
        Handoff,
        KeepLast,
        Lock,
        Meter,
        Notifier,
        Route,
        Routes,
        Runner,
        Server,
        Slots,
        Taker,
        Token,
        WaitSet,
        Work,
        first_step,
        mark_carrier,
        poll,
        publisher_gid,
        stuck_after,
    )
else:
    _missing = [name for name in __all__ if name not in globals() and not hasattr(_module, name)]
    if _missing:
        raise ImportError(f"the {ENGINE} engine lacks {', '.join(_missing)}")
    globals().update({name: getattr(_module, name) for name in __all__ if name not in globals()})
