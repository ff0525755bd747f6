"""The process ends with a given status at a given moment, unless cancelled first (``fastpath/deadline.c``).

For a wait that the waiting code cannot bound itself (a destructor deep in
rcl and Fast DDS that never returns).

Difference: the compiled thread never touches Python, so it ends the
process even while another thread holds the GIL for good (a pybind11
destructor that deadlocked, the case it exists for); this one needs the
GIL to wake up, and ends the process only where the code it bounds lets
go of it. Its line goes through rclpy's logging (all of its sinks); the
compiled one's through rcutils' console sink only (rclpy's output handler
takes the GIL).
"""

from __future__ import annotations

import os
import sys
import threading

from rclpy.logging import get_logger

__all__ = ["Deadline"]


class Deadline:
    """Unless :meth:`cancel` comes within ``seconds``, say ``message`` (WARN, under
    ``logger``) and end the process with status ``code``."""

    def __init__(self, seconds: float, *, code: int, logger: str, message: str) -> None:
        seconds = float(seconds)
        if not 0.0 <= seconds <= 1e9:
            raise ValueError("Deadline: seconds from 0 to 1e9")
        self._cancelled = threading.Event()
        self._thread = threading.Thread(
            target=self._wait_then_end, args=(seconds, int(code), str(logger), str(message)),
            name="deadline", daemon=True,
        )  # fmt: skip
        self._thread.start()

    def _wait_then_end(self, seconds: float, code: int, logger: str, message: str) -> None:
        if self._cancelled.wait(seconds):
            return
        get_logger(logger).warning(message)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)

    def cancel(self) -> None:
        """The process does not end (the thread is joined); again, nothing."""
        self._cancelled.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()
