"""SIGINT and SIGTERM from a ``container`` process's first instruction until its session takes them.

A ``container`` process starts as a shell and two interpreters, one pid:
the ``container`` command (``bin/container``) is a POSIX sh script that is
also Python, and execs Python on its own file; the ROS wheels' bootstrapper
(``ros_wheels_bootstrapper.pth``) re-executes Python with
``LD_LIBRARY_PATH`` set while the first interpreter is still processing
its site-packages, and the second imports the command. Until code of ours
handles them, Python's own rules apply: SIGINT raises ``KeyboardInterrupt``
wherever the interpreter is (a traceback from ``site``, "Fatal Python
error" and status 1, even in CPython's own start before any ``.pth`` file,
or from the middle of an import), and where Python ignores exceptions (a
weakref callback) it is printed as "Exception ignored" and the process
carries on as if no signal had come; SIGTERM kills. So:

* the launchers start Python with both signals *blocked*, through
  ``env --block-signal=INT,TERM`` (coreutils 8.31 or later: Debian 11,
  Ubuntu 22.04 and later; probed, else a plain ``exec``): ``bin/container``
  (``container/interfaces/container.in``; its interpreter is the
  virtualenv's, beside it, or the one a colcon install wrote in), the
  ``lib/lifecycle_container`` executables ``ros2 run`` and launch_ros start
  (``container/interfaces/ament/executable.in``: Python straight on
  ``bin/container``, since dash, Debian's sh, clears the signal mask it
  inherits; a colcon install's, written by ``container index``, Python on
  themselves, :mod:`container._ament`). A blocked signal waits, pending;
  the mask and what is pending survive every ``execve`` after it, the
  bootstrapper's too, so both interpreters start, and import, with both
  held;
* ``00_lifecycle_container.pth``, which site reads before any other
  ``.pth`` file with code (the bootstrapper's among them), blocks both
  signals in a ``container`` process started some other way: ``python -m
  container``, or Python on the command's file beside the interpreter (the
  launcher, where env cannot block signals). The file does
  it in its one line, with builtin modules only, and for no other process
  (one that blocked them and never took them could not be interrupted);
* the entry point's first act (:mod:`container.__main__`) is :func:`take`:
  the handler :func:`_exit_at_once` is installed, then the signals
  unblocked, and one that came meanwhile is delivered there and then;
* that handler never raises into the code it interrupts (an exception in a
  weakref callback or a ``__del__`` is what gets swallowed): it says one
  line and ends the process, ``128 + signal`` (130 for Ctrl-C). It stays
  until the command's session installs its own, and comes back after a
  session that no signal stopped.

Left to the kernel: the launcher's shell, before its ``exec``. A signal
there ends it by the default action, silently (shells report that as
``128 + signal`` too, launch as ``-2``/``-15``), and so does one its
parent left blocked and pending (dash unblocks it). Where env cannot block
signals, the first interpreter's own start, before site reads the ``.pth``
file, is Python's: until CPython installs its SIGINT handler the default
action kills the process, silently; in the few milliseconds from then to
the file, SIGINT is CPython's ``KeyboardInterrupt`` ("Fatal Python error:
init_import_site", status 1). Where site does not read the file either (a
colcon install, which puts the package on ``PYTHONPATH``), the signals are
Python's until :func:`take`.

The line: through ROS logging once the process has it
(:func:`use_ros_logging`, by :func:`container._roslog.install`), a plain one
on stderr before; only a server command (``run``, ``manager``) says it: a
client command cut short is quiet, as in its session. This module imports
only the standard library.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys

TYPE_CHECKING = False
if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

__all__ = ["SIGNALS", "take", "use_ros_logging"]

SIGNALS = (signal.SIGINT, signal.SIGTERM)

#: The command's name (its launcher's, ``bin/container``).
_COMMAND = "container"
#: The commands that are servers: they say the line.
_SERVERS = ("run", "manager")
#: ``logging.INFO``, without importing logging.
_INFO = 20

#: How the handler says its line: ``(severity, message)`` through ROS logging, once there.
_say: Callable[[int, str], None] | None = None
#: The server command's name, for the plain line (``container run``); ``None``: quiet.
_server: str | None = None


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
    # Runs between any two bytecodes of the main thread: nothing the
    # interrupted code may hold is needed (Python's logging's locks, a
    # stream's buffer: the plain line goes to the descriptor).
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    with contextlib.suppress(Exception):
        if _server is not None:
            message = f"{signal.Signals(signum).name} received: exiting"
            if _say is not None:
                _say(_INFO, message)
            else:
                os.write(2, f"{_server}: {message}\n".encode())
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
