"""One way to run a ROS program: context, executor, signals, exit codes, shutdown.

Every command (``container run``, ``container manager``, ``container load``,
``container lifecycle ...``) runs its work through :func:`run_session`, so all
of them start ROS and end alike:

* a fresh context initialised with only the command line's ROS arguments
  (the ``--ros-args ... [--]`` sections, :func:`container.cli.split_ros_args`),
  which rcl parses with its own semantics; the command's own ``-p
  name:=value`` is never read by rcl as a remap rule;
* rclpy's signal handlers off, and SIGINT/SIGTERM handled on the event loop
  (rclpy's would shut the context down under the nodes' feet);
* the exit code: what ``main`` returns; for a command cut short by a signal,
  ``128 + signal`` (130 for Ctrl-C), as shells report it; a *server* (a
  container, a manager) treats the first signal as the request to stop and
  exits with what its orderly shutdown returns; a second signal while it
  shuts down exits at once (``128 + signal``), without a traceback;
* the executor shut down and the context with it, whatever happened.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Awaitable, Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, NoReturn

import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import try_shutdown

from ._compat import RCLError
from ._runtime import use_fast_discovery
from .executor import AsyncioExecutor

__all__ = [
    "EXIT_FAILURE",
    "EXIT_OK",
    "EXIT_USAGE",
    "Session",
    "exit_code_for",
    "exit_now",
    "ros_failure",
    "run_session",
]

EXIT_OK = 0
EXIT_FAILURE = 1
#: Bad usage or a bad configuration file, as argparse exits.
EXIT_USAGE = 2

_SIGNALS = (signal.SIGINT, signal.SIGTERM)

#: How often the hard stop looks whether the loop is still stuck.
_HARD_STOP_POLL_S = 0.1

_log = logging.getLogger("container")


def _arm_hard_stop(session: Session, signum: int, frame: object) -> None:
    """Python-level signal handler: make sure a stuck loop cannot keep the process alive.

    The orderly stop goes through the loop (asyncio's own handling of the
    same signal). If the loop is stuck in a callback and stays stuck for the
    executor's shutdown timeout, this ends the process anyway, naming what
    was stuck.
    """
    if session.hard_stop is None:
        session.hard_stop = threading.Thread(
            target=_hard_stop, args=(session, signum), name="hard-stop", daemon=True
        )
        session.hard_stop.start()


def _hard_stop(session: Session, signum: int) -> None:
    watchdog = session.executor.watchdog
    if watchdog is None:
        return
    limit = session.executor.shutdown_timeout
    while session.executor.watchdog is watchdog:  # ends when the spin does
        stall = watchdog.stall
        if stall is not None and time.monotonic() - stall.since >= limit:
            name = signal.Signals(signum).name
            _log.error(
                f"{name}: the event loop has been stuck for {time.monotonic() - stall.since:.1f} s "
                f"in {stall.what}; exiting without a clean shutdown"
            )
            exit_now(exit_code_for(signum))
        time.sleep(_HARD_STOP_POLL_S)


def exit_now(code: int) -> NoReturn:
    """End the process at once with ``code``, whatever threads still run.

    For what an orderly exit cannot do: a stuck loop, a second signal,
    threads a plugin left behind (Python's exit would join them). Logs and
    standard streams are flushed first.
    """
    with contextlib.suppress(Exception):
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(code)


def ros_failure(error: BaseException) -> str:
    """One line for an error rcl raised, naming the cause a user can act on."""
    text = str(error)
    if "doesn't have the security libraries" in text:
        return (
            "ROS_SECURITY_ENABLE is true, but this Fast DDS is built without its security plugins "
            "(the PyPI wheels' Fast DDS is): use a ROS 2 whose Fast DDS was built with -DSECURITY=ON, "
            "or unset ROS_SECURITY_ENABLE"
        )
    first = text.strip().splitlines()[0] if text.strip() else type(error).__name__
    # rcl appends ", at <file>:<line>" locations of its own sources.
    return f"ROS error: {first.split(', at /')[0]}"


def exit_code_for(signum: int) -> int:
    """The exit code shells report for a process ended by ``signum`` (130 for SIGINT)."""
    return 128 + signum


@dataclass
class Session:
    """What :func:`run_session` hands to the program it runs.

    :ivar stopping: set by the first SIGINT or SIGTERM of a server session.
    :ivar signal: the signal that stopped the session, if one did.
    """

    context: Context
    executor: AsyncioExecutor
    stopping: asyncio.Event = field(default_factory=asyncio.Event)
    signal: int | None = None
    #: Started by the first signal: ends the process if the loop stays stuck.
    hard_stop: threading.Thread | None = None

    @contextlib.contextmanager
    def client_node(self, name: str) -> Iterator[Node]:
        """A short-lived node for a command to talk through; gone afterwards.

        A leading underscore in ``name`` hides it from ``list`` and lifecycle
        tools; it serves no parameters and logs nothing to ``/rosout``.
        """
        node = Node(name, context=self.context, start_parameter_services=False, enable_rosout=False)
        self.executor.add_node(node)
        try:
            yield node
        finally:
            self.executor.remove_node(node)
            node.destroy_node()


def run_session(
    main: Callable[[Session], Awaitable[int]],
    *,
    server: bool = False,
    executor_options: dict[str, Any] | None = None,
    ros_args: Sequence[str] = (),
) -> int:
    """Run ``main`` on a fresh context and executor; return the process exit code.

    :param server: ``True`` for a long-running process that stops on the
        first signal by itself (``main`` awaits ``session.stopping``); for any
        other command a signal cancels ``main``.
    :param executor_options: keyword arguments for :class:`AsyncioExecutor`.
    :param ros_args: ROS arguments (``--ros-args`` sections) for the context:
        rcl applies them to the nodes created with global arguments and
        configures logging (``--log-level``) from them.
    """
    use_fast_discovery()
    # rclpy warns about the half-made node it cleans up after a failed
    # creation; the failure itself is reported (ros_failure), once.
    warnings.filterwarnings("ignore", message="Failed to fini rosout publisher", category=RuntimeWarning)
    before = set(threading.enumerate())
    context = Context()
    try:
        # Only the ROS sections: rcl would read the command's own arguments
        # (-p x:=y) as deprecated ROS arguments.
        rclpy.init(args=["container", *ros_args], context=context, signal_handler_options=SignalHandlerOptions.NO)
    except KeyboardInterrupt:
        return exit_code_for(signal.SIGINT)
    code = EXIT_FAILURE
    clean = False
    try:
        executor = AsyncioExecutor(context=context, **(executor_options or {}))
        session = Session(context, executor)
        try:
            codes: list[int] = []
            executor.spin_until_future_complete(_guarded(main, session, server=server, codes=codes))
            if codes:
                code = codes[0]
            elif session.signal is not None:
                code = exit_code_for(session.signal)
        finally:
            clean = executor.shutdown()
            if session.hard_stop is not None:
                session.hard_stop.join(1.0)
    except KeyboardInterrupt:
        code = exit_code_for(signal.SIGINT)
    finally:
        try_shutdown(context=context)
    leftover = [t.name for t in threading.enumerate() if t not in before]
    if leftover or not clean:
        # Daemon threads would die silently with the process; say so instead.
        _log.error(f"threads left behind: {', '.join(leftover) or 'callbacks still running'}")
        return code or EXIT_FAILURE
    return code


async def _guarded(
    main: Callable[[Session], Awaitable[int]], session: Session, *, server: bool, codes: list[int]
) -> None:
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    assert task is not None

    def on_signal(signum: int) -> None:
        if session.signal is not None:
            # A second signal: the user wants out now, whatever is still running.
            name = signal.Signals(signum).name
            print(f"{name} again: exiting at once", file=sys.stderr, flush=True)
            exit_now(exit_code_for(signum))
        session.signal = signum
        if server:
            _log.info(f"{signal.Signals(signum).name} received: shutting down")
            session.stopping.set()
        else:
            task.cancel()

    for signum in _SIGNALS:
        loop.add_signal_handler(signum, on_signal, signum)
        # asyncio runs on_signal on the loop, which an async def callback may
        # hold for good; this runs in the main thread whatever it executes.
        signal.signal(signum, functools.partial(_arm_hard_stop, session))
    try:
        codes.append(await main(session))
    except asyncio.CancelledError:
        if session.signal is None:
            raise
        task.uncancel()
    except RCLError as exc:
        # ROS itself refused (a node could not be created, most often): a
        # user's environment problem, said in one line, not a traceback.
        print(f"container: {ros_failure(exc)}", file=sys.stderr, flush=True)
        codes.append(EXIT_FAILURE)
    finally:
        if not server or session.signal is None:
            for signum in _SIGNALS:
                loop.remove_signal_handler(signum)
