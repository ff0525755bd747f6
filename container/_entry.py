"""SIGINT and SIGTERM from a ``container`` process's first instruction until its session takes them.

A ``container`` process starts as two interpreters, one pid: the ROS
wheels' bootstrapper (``ros_wheels_bootstrapper.pth``) re-executes Python
with ``LD_LIBRARY_PATH`` set while the first one is still processing its
site-packages, and the second imports the command. Until code of ours
handles them, Python's own rules apply: SIGINT raises ``KeyboardInterrupt``
wherever the interpreter is (a traceback from ``site``, "Fatal Python
error" and status 1, or from the middle of an import), and where Python
ignores exceptions (a weakref callback) it is printed as "Exception
ignored" and the process carries on as if no signal had come; SIGTERM
kills. So, for the ``container`` command only (:func:`is_container_command`):

* ``lifecycle_container.pth``, which site processes before the
  bootstrapper's file, calls :func:`hold`: both signals are *blocked*. A
  blocked signal waits, pending; the mask and what is pending survive the
  bootstrapper's ``execve``, so the second interpreter starts, and imports,
  with both held;
* the entry point's first act (:mod:`container.__main__`) is :func:`take`:
  the handler :func:`_exit_at_once` is installed, then the signals
  unblocked, and one that came meanwhile is delivered there and then;
* that handler never raises into the code it interrupts (an exception in a
  weakref callback or a ``__del__`` is what gets swallowed): it says one
  line and ends the process, ``128 + signal`` (130 for Ctrl-C). It stays
  until the command's session installs its own, and comes back after a
  session that no signal stopped.

Left to Python and the kernel: the first interpreter's own start, before
site reaches this project's file (the default action kills the process;
shells report that as ``128 + signal`` too), a few milliseconds.

The line: through ROS logging once the process has it
(:func:`use_ros_logging`, by :func:`container._roslog.install`), a plain one
on stderr before; only a server command (``run``, ``manager``) says it: a
client command cut short is quiet, as in its session. This module imports
only the standard library: it runs at interpreter start.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys

TYPE_CHECKING = False
if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

__all__ = ["SIGNALS", "hold", "is_container_command", "take", "use_ros_logging"]

SIGNALS = (signal.SIGINT, signal.SIGTERM)

#: The module ``python -m`` runs for the command, and the console script's name.
_COMMAND = "container"
#: The commands that are servers: they say the line.
_SERVERS = ("run", "manager")
#: Python's options that take a value (``-X dev``, ``-W error``), and those that end its options.
_VALUE_OPTIONS = frozenset("XW")
_END_OPTIONS = frozenset("cm")

#: How the handler says its line: ``(severity, message)`` through ROS logging, once there.
_say: Callable[[int, str], None] | None = None
#: The server command's name, for the plain line (``container run``); ``None``: quiet.
_server: str | None = None


def is_container_command(argv: Sequence[str], executable: str) -> bool:
    """Whether the interpreter ``argv`` (``sys.orig_argv``) runs the ``container`` command.

    Either ``python [options] -m container ...``, or the console script
    ``container`` beside ``executable`` (the environment's ``bin``), which
    ``ros2 run`` and launch_ros reach through ``lib/lifecycle_container``.
    Nothing else: a process that blocked these signals and never took them
    could not be interrupted.
    """
    args = iter(argv[1:])
    for arg in args:
        if arg == "--check-hash-based-pycs":
            next(args, None)
            continue
        if arg.startswith("--") or arg == "-":
            return False  # --help, --version, or a script on stdin
        if arg.startswith("-"):
            for at, option in enumerate(arg[1:], start=2):
                if option in _VALUE_OPTIONS or option in _END_OPTIONS:
                    value = arg[at:] or next(args, "")
                    if option == "c":
                        return False
                    if option == "m":
                        return value == _COMMAND
                    break
            continue
        # The script itself, reached through any symbolic link, against the
        # directory of the interpreter (not the interpreter's own target).
        script = os.path.realpath(arg)
        return os.path.basename(script) == _COMMAND and os.path.dirname(script) == os.path.realpath(
            os.path.dirname(os.path.abspath(executable))
        )
    return False


def hold() -> None:
    """Block SIGINT and SIGTERM in a ``container`` process (``lifecycle_container.pth``); else nothing."""
    if is_container_command(sys.orig_argv, sys.executable):
        signal.pthread_sigmask(signal.SIG_BLOCK, SIGNALS)


def take(argv: Sequence[str]) -> None:
    """Handle SIGINT and SIGTERM by ending the process; deliver one that was held.

    :param argv: the command's arguments (``sys.argv[1:]``): a server
        command says a line when a signal ends it.
    """
    global _server
    command = _command_word(argv)
    _server = f"{_COMMAND} {command}" if command in _SERVERS else None
    for signum in SIGNALS:
        signal.signal(signum, _exit_at_once)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, SIGNALS)


def use_ros_logging(say: Callable[[int, str], None]) -> None:
    """Say the line through ``say(severity, message)`` from now on: ROS logging exists.

    ``say`` must be safe in a signal handler (:func:`container._roslog.say_now`).
    """
    global _say
    _say = say


def _exit_at_once(signum: int, frame: object) -> None:
    # Runs between any two bytecodes of the main thread: no lock the
    # interrupted code may hold (Python's logging's) is taken.
    with contextlib.suppress(Exception):
        if _server is not None:
            message = f"{signal.Signals(signum).name} received: exiting"
            if _say is not None:
                _say(20, message)  # logging.INFO, without importing logging
            else:
                sys.stderr.write(f"{_server}: {message}\n")
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(128 + signum)


def _command_word(argv: Sequence[str]) -> str | None:
    """The sub-command in ``argv``: its first word outside ``--ros-args ... --`` sections and options."""
    inside = False
    for arg in argv:
        if arg == "--ros-args":
            inside = True
        elif inside:
            inside = arg != "--"
        elif not arg.startswith("-"):
            return arg
    return None
