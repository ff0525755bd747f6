"""One way to run a ROS program: context, executor, signals, exit codes, shutdown.

Every command (``container run``, ``container manager``, ``container load``,
``container lifecycle ...``) runs its work through :func:`run_session`, so all
of them start ROS and end alike:

* DDS security decided before rcl starts, by rcl's own rules
  (:mod:`container._security`): a refusal is one line and exit 1, a
  process that will run without the security its environment seems to ask
  for says so in one warning; what rcl still refuses at start-up is one
  line too, never a traceback;
* a fresh context initialised with only the command line's ROS arguments
  (the ``--ros-args ... [--]`` sections, :func:`container.cli.split_ros_args`),
  which rcl parses with its own semantics; the command's own ``-p
  name:=value`` is never read by rcl as a remap rule;
* rclpy's signal handlers off, and SIGINT/SIGTERM handled by the session
  (rclpy's would shut the context down under the nodes' feet);
* the exit code: what ``main`` returns; for a command cut short by a signal,
  ``128 + signal`` (130 for Ctrl-C), as shells report it. A *server* (a
  container, a manager) treats the first signal as the request to stop and
  exits with what its orderly shutdown returns once it has said it is ready
  (:meth:`Session.mark_ready`); a signal before that stops the start-up and
  the process exits ``128 + signal``, within :data:`START_UP_STOP_S` of the
  signal: what has not stopped by then is left to the process's end (a
  client command cut short likewise);
* repeated signals, as ``ros2 launch`` and rclcpp's container expect: Ctrl-C
  in a terminal reaches every process of the group and launch forwards one
  more SIGINT, so a repetition of the *first* signal is absorbed (one line
  says so); a different signal (launch's SIGTERM after its
  ``sigterm_timeout``) or a third one ends the process at once with ``128 +
  signal``, without a traceback, and so does an event loop still stuck
  ``shutdown_timeout`` after the first signal;
* one line per signal, for a server: said from Python's signal handler
  (:func:`container._roslog.say_now`), when the signal comes, even while the
  loop is busy (constructing a node, importing a plugin); a client command
  stays quiet;
* the executor shut down and the context with it, whatever happened.

Before the session's handlers are installed, and after a session that no
signal stopped, the handlers the caller had apply (the ``container`` command
installs its own first thing: :mod:`container.__main__`).
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import gc
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

from ._compat import RCLError, hand_signal_over
from ._errors import SecurityError
from ._roslog import say_now
from ._runtime import configure_warnings, dump_stacks_on_sigusr1, use_fast_discovery
from ._security import NO_SECURITY_PLUGINS, check_security, clear_rcl_error
from .executor import AsyncioExecutor, Deadline, end_resender, end_spare_threads

__all__ = [
    "EXIT_FAILURE",
    "EXIT_OK",
    "EXIT_USAGE",
    "Session",
    "exit_code_for",
    "exit_now",
    "ros_failure",
    "run_session",
    "tear_down",
]

EXIT_OK = 0
EXIT_FAILURE = 1
#: Bad usage or a bad configuration file, as argparse exits.
EXIT_USAGE = 2

_SIGNALS = (signal.SIGINT, signal.SIGTERM)

#: How often the hard stop looks whether the loop is still stuck.
_HARD_STOP_POLL_S = 0.1

#: Seconds from the first signal to the end of a session that was not a
#: ready server (a start-up, a client command): an orderly stop takes 0.1-0.5 s.
START_UP_STOP_S = 0.8

#: How long each step of the end of a session, rcl's shutdown and then the
#: context's destruction with the DDS participant's (0.1-0.3 s here), may
#: take before the process ends without it. Fast DDS can deadlock in both,
#: with peers' discovery traffic arriving (four containers stopped at once:
#: 4 hangs in about 300 runs of the signals test on Kilted): destroying the
#: participant, the main thread sat in ``DomainParticipant::set_listener``
#: for good, a UDP receive thread waiting on a mutex of the participant's
#: discovery listener; finalising the rosout publisher in rcl's shutdown,
#: it waited on the discovery (PDP) mutex.
TEARDOWN_S = 5.0

_log = logging.getLogger("container")


def _arm_hard_stop(session: Session, signum: int) -> None:
    """Make sure a stuck loop cannot keep the process alive after the first signal.

    The orderly stop goes through the loop (asyncio's own handling of the
    signal). If the loop is stuck in a callback and stays stuck for the
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
        if session.spun.wait(_HARD_STOP_POLL_S):
            return


def _arm_deadline(session: Session, signum: int, *, say: bool) -> None:
    """End the process if the session is not over :data:`START_UP_STOP_S` after ``signum``.

    For a start-up or a client command a signal cut short: what stops in
    order does so well within it; a node's constructor or transition that
    holds on, a plugin's import, a teardown slowed by a loaded machine does
    not hold the process past it.
    """
    if session.deadline is None:
        session.deadline = threading.Thread(
            target=_deadline, args=(session, signum, say), name="start-up-deadline", daemon=True
        )
        session.deadline.start()


def _deadline(session: Session, signum: int, say: bool) -> None:
    if session.over.wait(START_UP_STOP_S):
        return
    if say:
        name = signal.Signals(signum).name
        say_now(
            logging.WARNING,
            f"start-up still stopping {START_UP_STOP_S:g} s after {name}: exiting without a clean shutdown",
        )
    exit_now(exit_code_for(signum))


def exit_now(code: int) -> NoReturn:
    """End the process at once with ``code``, whatever threads still run.

    For what an orderly exit cannot do: a stuck loop, a signal that
    escalates, threads a plugin left behind (Python's exit would join them),
    a start-up a signal cut short. Logs and standard streams are flushed
    first.
    """
    with contextlib.suppress(Exception):
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(code)


def ros_failure(error: BaseException) -> str:
    """One line for an error rcl raised, naming the cause a user can act on."""
    text = str(error)
    # Said before rcl starts (check_security) where it can be known; these
    # are for what only the middleware finds out.
    if "doesn't have the security libraries" in text:
        return NO_SECURITY_PLUGINS
    if "couldn't find all security files" in text:
        return "DDS security: Fast DDS could not find all the enclave's security files (ROS_SECURITY_STRATEGY=Enforce)"
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
    #: Started by the first signal to a session that is not a ready server.
    deadline: threading.Thread | None = None
    #: Set once the executor stopped spinning (the hard stop ends).
    spun: threading.Event = field(default_factory=threading.Event)
    #: Set once the session is over, all shut down (the deadline ends).
    over: threading.Event = field(default_factory=threading.Event)
    #: Set by :meth:`mark_ready`.
    ready: bool = False

    def stop_asked(self) -> bool:
        """Whether a signal asked the session to stop, if the loop has not handled it yet.

        Python's handler records the signal when it comes; :attr:`stopping`
        is set on the loop, once the loop has control again.
        """
        return self.signal is not None

    def mark_ready(self) -> None:
        """Say the server has started: a signal from now on is the ordinary way to stop it.

        A server a signal stopped that never got here (its start-up cut
        short) exits ``128 + signal``, whatever ``main`` returns; one that
        did, with what ``main`` returns.
        """
        self.ready = True

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
    configure_warnings()
    if server:
        dump_stacks_on_sigusr1()
    # Security requested is security, or said in one line, before rcl
    # starts: rcl would run without it unsaid, or fail with no reason.
    try:
        security = check_security(ros_args)
    except SecurityError as exc:
        _log.error(str(exc))
        return EXIT_FAILURE
    if security.warning is not None:
        _log.warning(security.warning)
    # rclpy warns about the half-made node it cleans up after a failed
    # creation; the failure itself is reported (ros_failure), once.
    warnings.filterwarnings("ignore", message="Failed to fini rosout publisher", category=RuntimeWarning)
    before = set(threading.enumerate())
    previous = {signum: signal.getsignal(signum) for signum in _SIGNALS}
    context = Context()
    try:
        # Only the ROS sections: rcl would read the command's own arguments
        # (-p x:=y) as deprecated ROS arguments.
        rclpy.init(args=["container", *ros_args], context=context, signal_handler_options=SignalHandlerOptions.NO)
    except KeyboardInterrupt:
        return exit_code_for(signal.SIGINT)
    except RCLError as exc:
        # What rcl refuses that nothing checked before (an invalid --enclave
        # name, a security failure check_security could not foresee).
        _log.error(ros_failure(exc))
        return EXIT_FAILURE
    if security.stale_rcl_error:
        clear_rcl_error()
    code = EXIT_FAILURE
    clean = False
    session: Session | None = None
    try:
        # A client command's output is read by scripts: its own loop
        # stalls (an import, the first log call) are never reported there.
        options = {"watchdog_reports": server, **(executor_options or {})}
        executor = AsyncioExecutor(context=context, **options)
        session = Session(context, executor)
        try:
            codes: list[int] = []
            signals = _Signals(session, server=server)
            executor.spin_until_future_complete(_guarded(main, session, signals, codes=codes))
            if codes:
                code = codes[0]
            elif session.signal is not None:
                code = exit_code_for(session.signal)
        finally:
            clean = executor.shutdown()
            session.spun.set()
            # The container's own thread, not a plugin's: ended before the
            # context, its answers to clients that never matched dropped.
            end_resender(timeout=1.0)
            if session.hard_stop is not None:
                session.hard_stop.join(1.0)
            if session.signal is None:
                # A session no signal stopped leaves the caller's handlers;
                # one a signal stopped keeps its own: the process is on its
                # way out, and a repetition is still absorbed until it is gone.
                for signum, handler in previous.items():
                    if handler is not None:
                        signal.signal(signum, handler)
            else:
                atexit.register(signals.hand_over)
    except KeyboardInterrupt:
        code = exit_code_for(signal.SIGINT)
    finally:
        # rcl's shutdown finalises the rosout publishers: Fast DDS deadlocked
        # there too (a PDP mutex, peers' discovery arriving), the GIL held.
        with _teardown_bound(code, "rcl's shutdown"):
            try_shutdown(context=context)
    end_spare_threads(timeout=1.0)  # idle, not left behind
    if session is not None:
        session.over.set()
        if session.deadline is not None:
            session.deadline.join(1.0)
    leftover = [t.name for t in threading.enumerate() if t not in before]
    if leftover or not clean:
        # Daemon threads would die silently with the process; say so instead.
        _log.error(f"threads left behind: {', '.join(leftover) or 'callbacks still running'}")
        code = code or EXIT_FAILURE
    tear_down(context, code=code)
    return code


def tear_down(context: Context, *, code: int) -> None:
    """Destroy ``context`` and the DDS participant now, within :data:`TEARDOWN_S`; past
    that, end the process with ``code``.

    After a session the participant is still there: what holds the last of
    its nodes' rcl handles is garbage in reference cycles (rclpy's nodes and
    entities refer to each other), which Python's own exit collected at a
    moment nobody bounded, with no Python frame left to report. Here they
    are collected and the context destroyed now, and a deadlock in the
    middleware costs :data:`TEARDOWN_S` and one line, not the process's
    exit. The bound is the executor's :class:`~container.executor.Deadline`,
    a thread that needs no GIL: the deadlock happens inside rclpy's
    destructors, which keep it.
    """
    with _teardown_bound(code, "the DDS participant's destruction"):
        context.destroy()  # when nothing uses it any more: the collection below, or now
        gc.collect()


@contextlib.contextmanager
def _teardown_bound(code: int, what: str) -> Iterator[None]:
    """The process ends with ``code`` if the block still runs :data:`TEARDOWN_S` from now."""
    deadline = Deadline(
        TEARDOWN_S,
        code=code,
        logger=_log.name,
        message=(
            f"ROS teardown ({what}) still running {TEARDOWN_S:g} s after the session ended: "
            f"exiting without it (status {code})"
        ),
    )
    try:
        yield
    finally:
        deadline.cancel()


class _Signals:
    """What SIGINT and SIGTERM mean to one session, from its loop's start to the process's end.

    Two handlers see each signal. Python's (:meth:`on_signal_now`) runs in
    the main thread between two bytecodes, even while the event loop is
    stuck in a callback, so it does only what is safe at any point of any
    code: it records the signal, starts the hard stop, says its line
    straight to rcutils (:func:`container._roslog.say_now`: no Python
    logging lock, which the interrupted code may hold) and ends the process.
    asyncio's (:meth:`on_signal`, while the loop's handlers are installed)
    runs on the loop, after it, as ordinary code: it starts the orderly stop
    and logs through Python's logging like any other line.
    """

    def __init__(self, session: Session, *, server: bool) -> None:
        self.session = session
        self.server = server
        #: The loop's handlers are installed (they log the repetition).
        self.on_loop = False
        #: The first signal came again, and was absorbed.
        self.repeated = False
        self._stop_started = False
        self._repeat_logged = False
        self._task: asyncio.Task[None] | None = None

    def install(self, loop: asyncio.AbstractEventLoop, task: asyncio.Task[None]) -> None:
        """Handle the signals on ``loop``, a client's first cancelling ``task``."""
        self._task = task
        for signum in _SIGNALS:
            # asyncio's handler wakes the loop through its wake-up descriptor
            # and runs on it; the Python-level one replaces asyncio's no-op.
            loop.add_signal_handler(signum, self.on_signal, signum)
            signal.signal(signum, self.on_signal_now)
        self.on_loop = True

    def uninstall(self, loop: asyncio.AbstractEventLoop) -> None:
        """Leave the loop; the Python-level handler goes on to the end of the session."""
        self.on_loop = False
        for signum in _SIGNALS:
            # Not remove_signal_handler then signal.signal: a signal between
            # the two would meet Python's default, which raises or kills.
            hand_signal_over(loop, signum, self.on_signal_now)

    def hand_over(self) -> None:
        """Leave the signals' meaning to the kernel for the process's last moments.

        Python runs no signal handler once it finalizes (it puts back the
        default dispositions), and the teardown of rcl and the DDS
        participant takes a while then (0.1-0.2 s). So from the last
        ``atexit`` callback on: the first signal's repetition is ignored
        until it has come, any other signal ends the process at once (killed
        by it, which shells report as ``128 + signal`` too).
        """
        for signum in _SIGNALS:
            absorb = signum == self.session.signal and not self.repeated
            signal.signal(signum, signal.SIG_IGN if absorb else signal.SIG_DFL)

    def on_signal_now(self, signum: int, frame: object) -> None:
        """Python's handler: record and announce the first signal; absorb its repetition; escalate."""
        if self._record(signum):
            if self.server:
                say_now(logging.INFO, f"{signal.Signals(signum).name} received: shutting down")
            return
        first = self.session.signal
        assert first is not None
        name = signal.Signals(signum).name
        if signum == first and not self.repeated:
            self.repeated = True
            if not self.on_loop:
                say_now(logging.WARNING, _absorbed(name))
            return
        again = "a third time" if signum == first else f"after {signal.Signals(first).name}"
        # WARN: what the operator asked for, if not how it ends (the nodes are
        # not taken down); say_now writes it through to rcl's log file.
        say_now(logging.WARNING, f"{name} {again}: exiting at once")
        exit_now(exit_code_for(signum))

    def on_signal(self, signum: int) -> None:
        """asyncio's handler, on the loop: start the orderly stop, or log the repetition."""
        if self._record(signum) and self.server:  # normally done: Python's handler runs first
            _log.info(f"{signal.Signals(signum).name} received: shutting down")
        first = self.session.signal
        assert first is not None
        name = signal.Signals(first).name
        if not self._stop_started:
            self._stop_started = True
            if self.server:
                self.session.stopping.set()
            elif self._task is not None:
                self._task.cancel()
        elif self.repeated and not self._repeat_logged:
            self._repeat_logged = True
            _log.warning(_absorbed(name))

    def _record(self, signum: int) -> bool:
        """Take ``signum`` as the session's signal if it has none yet; whether it did."""
        session = self.session
        if session.signal is not None:
            return False
        session.signal = signum
        if self.on_loop:
            _arm_hard_stop(session, signum)
        if not (self.server and session.ready):
            _arm_deadline(session, signum, say=self.server)
        return True


def _absorbed(name: str) -> str:
    return f"{name} again: already shutting down; a third signal exits at once"


async def _guarded(
    main: Callable[[Session], Awaitable[int]], session: Session, signals: _Signals, *, codes: list[int]
) -> None:
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    assert task is not None
    signals.install(loop, task)
    try:
        code = await main(session)
    except asyncio.CancelledError:
        if session.signal is None:
            raise
        task.uncancel()
        code = exit_code_for(session.signal)
    except RCLError as exc:
        # ROS itself refused (a node could not be created, most often): a
        # user's environment problem, said in one line, not a traceback.
        _log.error(ros_failure(exc))
        code = EXIT_FAILURE
    else:
        if signals.server and session.signal is not None and not session.ready:
            code = exit_code_for(session.signal)
    finally:
        signals.uninstall(loop)
    codes.append(code)
