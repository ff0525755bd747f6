"""``python -m container`` and the ``container`` console script.

A signal before the command's session handles signals itself (while Python
imports the command line, rclpy and the plugins, while rcl starts) ends the
process quietly with ``128 + signal``, as a shell reports a process a signal
killed: Ctrl-C in the first half second must not print a
``KeyboardInterrupt`` traceback from the middle of an import. This module
imports nothing but the standard library until that is in place; what
``container/__init__.py`` imports runs before it, and stays small.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

__all__ = ["main"]


def _exit_quietly(signum: int, frame: object) -> None:
    # Runs between any two bytecodes: only what is safe there.
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(128 + signum)


def main() -> int:
    """Run the command; never wait on threads a plugin left running.

    Python's own exit joins every non-daemon thread, so one a plugin started
    and never ended would keep the process alive after the container is
    gone. The session has already named them in the log; here the process
    ends with its exit code regardless.

    SIGINT and SIGTERM end the process at once until the session installs
    its own handlers, and again after a session that no signal stopped (the
    session restores them), to the end of the process.

    Standard output closed by its reader (``container list | head -1``)
    ends the command quietly with status 0 (:mod:`container._output` says
    why SIGPIPE stays ignored); the last flush happens here, inside that
    rule, not in the interpreter's exit.
    """
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _exit_quietly)
    from ._output import closed_early, guard_output

    guard_output()
    from .cli import main as run_command

    try:
        code = run_command()
    except BrokenPipeError:
        if not closed_early():
            raise  # not our standard output's: a real failure
        code = 0  # a command that only reads, stopped at a line nobody reads
    try:
        sys.stdout.flush()  # buffered output: a failure found only now keeps the command's own status
    except BrokenPipeError:
        if not closed_early():
            raise
    if any(t.is_alive() and not t.daemon for t in threading.enumerate() if t is not threading.main_thread()):
        from ._session import exit_now  # rclpy only loads when a session ran

        exit_now(code or 1)
    return code


if __name__ == "__main__":
    sys.exit(main())
