"""One logging path: Python's ``logging`` records go out as ROS log lines.

The library modules (the executor and its watchdog, the plugin registry, the
session) log through Python's :mod:`logging`, which keeps them free of rclpy
at import and lets tests read them with ``caplog``. A process the
``container`` command runs installs :class:`RosLogHandler` on the root
logger instead of a stream handler, and every record goes through rcutils,
as a node's own lines do: rcutils' console format (time stamp, severity,
logger name), ``--log-level``, and once rcl has started, the log file under
``ROS_LOG_DIR`` (``~/.ros/log``) and, for the lines of a node that publishes
its log, ``/rosout``.

rcl publishes on ``/rosout`` only the lines of a node's logger and its child
loggers, so once the process has its node (the container node, the lifecycle
manager: :func:`route_to`) the records are logged under that node's name:
``container`` becomes the node's logger (``ComponentManager``), and
``container.executor.*`` its child ``ComponentManager.executor``; other
Python loggers (a plugin's library) become children under their full name.
Lines before the node exists (plugin discovery) and after it is gone (the
exit summary) keep the Python names, and reach the console and, while rcl
runs, the log file.

A signal handler says its line with :func:`say_now`, straight to rcutils:
Python's logging takes locks (the handler's, the module's) that the code the
signal interrupted may hold, and a stream it may be writing. rclpy's logging
lock is held only inside its C call, which a Python signal handler never
interrupts, so that path cannot deadlock. Such a line may be the process's
last: :func:`say_now` flushes C's standard I/O buffers after it, where rcl's
log file waits (it writes through by itself only an ERROR line). Once
:func:`install` ran, the ``container`` command's own handler for a signal
before its session (:mod:`container._entry`) says its line this way too.
"""

from __future__ import annotations

import ctypes
import inspect
import logging

import rclpy.logging
from rclpy.impl.logging_severity import LoggingSeverity
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.node import Node

from . import _entry
from ._compat import rcutils_log

__all__ = ["ROOT_NAME", "RosLogHandler", "install", "route_to", "say_now", "severity_of"]

#: The Python logger of the container's own lines, and their ROS name while no node is attached.
ROOT_NAME = "container"

#: The C library, for ``fflush(NULL)`` (:func:`say_now`).
_LIBC = ctypes.CDLL(None)


def severity_of(levelno: int) -> LoggingSeverity:
    """The rcutils severity of a Python log level (``WARNING`` is ``WARN``, ``CRITICAL`` ``FATAL``)."""
    if levelno >= logging.CRITICAL:
        return LoggingSeverity.FATAL
    if levelno >= logging.ERROR:
        return LoggingSeverity.ERROR
    if levelno >= logging.WARNING:
        return LoggingSeverity.WARN
    if levelno >= logging.INFO:
        return LoggingSeverity.INFO
    return LoggingSeverity.DEBUG


class RosLogHandler(logging.Handler):
    """Log each record through rcutils, under its ROS logger name.

    :param verbose: lower rcutils' threshold for the container's loggers to
        DEBUG (rcutils drops what is below its own threshold, INFO by default).
    """

    def __init__(self, level: int = logging.NOTSET, *, verbose: bool = False) -> None:
        super().__init__(level)
        self.setFormatter(logging.Formatter("%(message)s"))
        self.verbose = verbose
        #: The attached node's logger, under which the records are logged.
        self._node: RcutilsLogger | None = None
        #: Its child loggers by suffix: each registers the child with rcl's
        #: ``/rosout`` publisher, and unregisters when dropped.
        self._children: dict[str, RcutilsLogger] = {}
        if verbose:
            rclpy.logging.set_logger_level(ROOT_NAME, LoggingSeverity.DEBUG)

    @property
    def root_name(self) -> str:
        """The ROS logger name of the container's own lines now."""
        node = self._node
        return ROOT_NAME if node is None else node.name

    def attach(self, logger: RcutilsLogger | None) -> None:
        """Log under ``logger`` (a node's) from now on; ``None``: the Python names again.

        Must be called with ``None`` before the node is destroyed: its child
        loggers hold entries in rcl's ``/rosout`` table.
        """
        self.acquire()
        try:
            self._children.clear()
            self._node = logger
            if logger is not None and self.verbose:
                rclpy.logging.set_logger_level(logger.name, LoggingSeverity.DEBUG)
        finally:
            self.release()

    def ros_name(self, name: str) -> str:
        """The ROS logger name of the Python logger ``name`` (under the handler's lock)."""
        node = self._node
        if name in (ROOT_NAME, "root"):
            return self.root_name
        if name.startswith(f"{ROOT_NAME}."):
            # One child per part of the container (executor, plugins, hooks),
            # not per module: a bounded set of names for rqt_console's filters.
            suffix = name.split(".")[1]
            if node is None:
                return f"{ROOT_NAME}.{suffix}"
        elif node is None:
            return name
        else:
            suffix = name
        child = self._children.get(suffix)
        if child is None:
            child = self._children[suffix] = node.get_child(suffix)
        child_name: str = child.name
        return child_name

    def emit(self, record: logging.LogRecord) -> None:
        try:
            rcutils_log(
                severity_of(record.levelno),
                self.ros_name(record.name),
                self.format(record),
                function=record.funcName or "<unknown>",
                file=record.pathname,
                line=record.lineno,
            )
        except Exception:
            self.handleError(record)


#: The handler :func:`install` put on the root logger, if any.
_installed: RosLogHandler | None = None


def install(*, level: int = logging.INFO, verbose: bool = False) -> None:
    """Send the process's Python log records through ROS logging, at ``level`` and above.

    Like :func:`logging.basicConfig`, does nothing where the root logger has
    handlers already (pytest's, an embedding program's): those keep the records.
    """
    global _installed
    root = logging.getLogger()
    if root.handlers:
        return
    handler = RosLogHandler(verbose=verbose)
    root.addHandler(handler)
    root.setLevel(logging.DEBUG if verbose else level)
    _installed = handler
    _entry.use_ros_logging(say_now)


def route_to(node: Node | None) -> None:
    """Log the container's lines under ``node``'s logger (to ``/rosout``); ``None`` before it goes."""
    if _installed is not None:
        _installed.attach(None if node is None else node.get_logger())


def say_now(levelno: int, message: str) -> None:
    """Log ``message`` from a signal handler: straight to rcutils, under the container's name.

    No Python logging lock is taken (see the module's docstring). rcutils
    writes the console line unbuffered; the log file's buffer is flushed here
    (all of C's ``FILE`` streams: rcl's file sink is one), as only an ERROR
    line would flush it by itself: the process may not live long enough to
    do it later.
    """
    handler = _installed
    name = ROOT_NAME if handler is None else handler.root_name
    here = inspect.currentframe()
    caller = here.f_back if here is not None else None
    code = caller.f_code if caller is not None else None
    rcutils_log(
        severity_of(levelno),
        name,
        message,
        function=code.co_name if code is not None else "say_now",
        file=code.co_filename if code is not None else __file__,
        line=caller.f_lineno if caller is not None else 0,
    )
    _LIBC.fflush(None)
