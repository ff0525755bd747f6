"""``python -m container`` and the ``container`` command (Python on ``bin/container``, a sh launcher).

The entry point's first act is to take SIGINT and SIGTERM
(:func:`container._entry.take`): a signal before the command's session
handles signals itself (while Python imports the command line, rclpy and
the plugins, while rcl starts), or one held since the interpreter started,
ends the process with ``128 + signal``, as a shell reports a process a
signal killed, and one line, never a ``KeyboardInterrupt`` traceback from
the middle of an import. This module imports nothing but the standard
library until that is in place, and the package's ``__init__`` imports
nothing at all.
"""

from __future__ import annotations

import sys

from ._entry import SIGNALS, take

__all__ = ["main"]

#: The exit codes of a command a signal cut short (SIGINT, SIGTERM).
_CUT_SHORT = frozenset(128 + signum for signum in SIGNALS)
#: How long the interpreter's own exit may take once the command is over (s).
#: The session has destroyed rcl's context and the DDS participant by then
#: (``_session.tear_down``, bounded itself); what is left is Python's.
_EXIT_GRACE_S = 20.0


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
    take(sys.argv[1:])
    import threading

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
    if code in _CUT_SHORT:
        # A signal cut the command short, its session is over: Python's own
        # exit would take 0.2-0.3 s more (the interpreter's teardown, and
        # Fast DDS's factory sleeps 100 ms in its destructor), past the
        # second a stopped start-up may take.
        from ._session import exit_now

        exit_now(code)
    if any(t.is_alive() and not t.daemon for t in threading.enumerate() if t is not threading.main_thread()):
        from ._session import exit_now  # rclpy only loads when a session ran

        exit_now(code or 1)
    # Bounded: past the grace, faulthandler's own thread writes every
    # thread's stack to stderr and ends the process with status 1.
    import faulthandler

    faulthandler.dump_traceback_later(_EXIT_GRACE_S, exit=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
