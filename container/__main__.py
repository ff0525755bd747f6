"""``python -m container`` and the ``container`` console script."""

from __future__ import annotations

import sys
import threading

from .cli import main as _main

__all__ = ["main"]


def main() -> int:
    """Run the command; never wait on threads a plugin left running.

    Python's own exit joins every non-daemon thread, so one a plugin started
    and never ended would keep the process alive after the container is
    gone. The session has already named them in the log; here the process
    ends with its exit code regardless.
    """
    code = _main()
    if any(t.is_alive() and not t.daemon for t in threading.enumerate() if t is not threading.main_thread()):
        from ._session import exit_now  # rclpy only loads when a session ran

        exit_now(code or 1)
    return code


if __name__ == "__main__":
    sys.exit(main())
