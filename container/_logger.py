"""A node's logger whose lines cost microseconds, not milliseconds.

rclpy's :class:`~rclpy.impl.rcutils_logger.RcutilsLogger` finds the place
of every call again: ``inspect.getframeinfo`` reads the caller's source
lines and works out the column, and ``os.path.realpath`` resolves each
frame's file, every time. Measured on this project's 2-core VM, one line
took 0.43 ms from a small script and 1-4 ms from the container's own
modules (large files, long functions), which is what a hundred nodes'
``Loaded ...`` lines cost the loop's thread during start-up, and what the
demo's listeners spent most of their CPU on (one line per message).

:class:`FastLogger` keeps rclpy's logger for everything but that: the
same name, level and threshold (rcutils'), the same ``/rosout`` sub-logger
registration, and the same filters (``once``, ``throttle_duration_sec``,
``skip_first``), which go to rclpy's own ``log`` since they key their state
on rclpy's record of the call site. A line without a filter goes straight
to the rcutils call rclpy's ends in (:func:`container._compat.rcutils_log`),
with the caller's function, file (made absolute, as rclpy makes it, once
per file) and line. What it does not do is refuse a call site that logs at
two severities, which rclpy does only to keep its filters' state apart.
"""

from __future__ import annotations

import os
from typing import Any, cast

import rclpy.logging
from rclpy.impl import rcutils_logger
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.node import Node

from ._compat import caller_frame, rcutils_log, skip_in_log_calls

__all__ = ["FastLogger", "FastLogging"]

#: Files whose frames are the logging machinery's, not the caller's (as rclpy's ``_find_caller`` skips).
_INTERNAL = frozenset({rcutils_logger.__file__, rclpy.logging.__file__, __file__})

#: ``os.path.abspath`` of each caller's file, as rclpy reports it (``CallerId``).
_ABSOLUTE: dict[str, str] = {}


class FastLogger(RcutilsLogger):
    """An :class:`~rclpy.impl.rcutils_logger.RcutilsLogger` that logs a line without a filter cheaply."""

    def log(self, message: Any, severity: Any, name: str | None = None, **kwargs: Any) -> bool:
        if kwargs:
            if name is not None:
                kwargs["name"] = name
            return bool(super().log(message, severity, **kwargs))  # type: ignore[no-untyped-call, unused-ignore]
        if not self.is_enabled_for(severity):  # type: ignore[no-untyped-call, unused-ignore]
            return False
        frame = caller_frame(1)
        while frame.f_code.co_filename in _INTERNAL and frame.f_back is not None:
            frame = frame.f_back
        code = frame.f_code
        path = code.co_filename
        file = _ABSOLUTE.get(path)
        if file is None:
            file = _ABSOLUTE[path] = os.path.abspath(path)
        rcutils_log(
            int(severity),
            self.name if name is None else name,
            message,
            function=code.co_name,
            file=file,
            line=frame.f_lineno,
        )
        return True

    def get_child(self, name: str) -> FastLogger:
        """The child logger ``name``, itself a :class:`FastLogger`, registered for ``/rosout`` as rclpy's is."""
        child = super().get_child(name)  # type: ignore[no-untyped-call, unused-ignore]
        fast = FastLogger(name=child.name)
        # The registration is let go by whichever logger holds the pair, when it is dropped.
        fast.logger_sublogger_namepair, child.logger_sublogger_namepair = child.logger_sublogger_namepair, None
        return fast


class FastLogging:
    """Makes a node class's :meth:`get_logger` a :class:`FastLogger` (listed before ``Node`` in its bases)."""

    #: :meth:`get_logger`'s logger, made at its first call.
    _fast_logger: FastLogger | None = None

    def get_logger(self) -> FastLogger:
        """The node's logger: rclpy's, but a line costs microseconds (:mod:`container._logger`)."""
        logger = self._fast_logger
        if logger is None:
            rclpys = Node.get_logger(cast(Node, self))  # type: ignore[no-untyped-call, unused-ignore]
            logger = self._fast_logger = FastLogger(name=rclpys.name)
        return logger


# rclpy's own search, which lines with a filter take, looks past this module's frames too.
skip_in_log_calls(__file__)
