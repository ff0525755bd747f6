"""Sending a service's answer, and sending it again when its client is not matched yet.

A client that has just discovered a service (``wait_for_service`` returned)
may call before the service has matched the client's response reader: Fast
DDS's rmw then blocks up to the writer's blocking time (100 ms) and gives up
with "client will not receive response", and the caller waits forever
(``ros2 component load`` right after a container starts; seen in this
project's tests about once in a few thousand calls, more on a loaded
machine). The compiled send (``_fastpath.Server``) says so by returning
``False``; rclpy's ``send_response``, used for a service the compiled path
cannot serve, reports it as a ``RuntimeWarning`` from C++, which a caller
cannot catch, so exactly that warning is made an error for the whole
process (``_compat.raise_client_not_matched``; ``_compat.client_not_matched``
recognises it, and the Python engine's ``Server`` with it). Either way the
answer is sent again, for a few seconds, from one thread of its own: never
on the event loop, and bounded, so a peer whose response reader can never
match (an incompatible QoS, on purpose or not) costs at most that one thread.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Any

from rclpy.exceptions import InvalidHandle

from .._compat import client_not_matched, raise_client_not_matched
from ._engine import Server

__all__ = ["respond"]

_log = logging.getLogger(__name__)

#: How long an unmatched answer is tried again, and how often.
RETRY_S = 3.0
RETRY_EVERY_S = 0.05
#: Answers waiting for their clients at most; more are dropped, with a log line.
MAX_WAITING = 64


def respond(srv: Any, response: Any, header: Any, *, server: Server | None = None) -> None:
    """Send ``response``; if its client is not matched yet, again from the resender thread.

    ``server``: the service's compiled answers, which ``header`` came from
    (``None``: rclpy's ``send_response``, with rclpy's header).
    """
    if not _sent(srv, server, response, header):
        _resender.add(srv, server, response, header)


def _sent(srv: Any, server: Server | None, response: Any, header: Any, *, let_go: bool = False) -> bool:
    """Send once; ``False`` when the client's response reader is not matched (yet).

    ``let_go``: the compiled send lets go of the GIL while rmw waits for
    the client (the resender thread: every other thread runs meanwhile).
    """
    if server is not None:
        # Entered: a service destroyed meanwhile raises InvalidHandle here (the
        # server's own hold only defers its destruction).
        with srv.handle:
            return server.send(response, header, let_go)
    try:
        srv.send_response(response, header)
    except Exception as error:
        if client_not_matched(error):
            return False
        raise
    return True


class _Resender:
    """One thread that sends waiting answers again until their clients match or time runs out."""

    def __init__(self) -> None:
        self._waiting: collections.deque[tuple[float, Any, Server | None, Any, Any]] = collections.deque()
        self._wake = threading.Condition()
        self._thread: threading.Thread | None = None
        self.dropped = 0

    def add(self, srv: Any, server: Server | None, response: Any, header: Any) -> None:
        with self._wake:
            if len(self._waiting) >= MAX_WAITING:
                self.dropped += 1
                _log.warning(
                    "service %s: %d answers already wait for their clients to match; this one is dropped",
                    _name(srv), len(self._waiting),
                )
                return
            self._waiting.append((time.monotonic() + RETRY_S, srv, server, response, header))
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="respond-again", daemon=True)
                self._thread.start()
            self._wake.notify()

    def _run(self) -> None:
        while True:
            with self._wake:
                while not self._waiting:
                    self._wake.wait()
                batch = list(self._waiting)
                self._waiting.clear()
            time.sleep(RETRY_EVERY_S)
            still = [entry for entry in batch if not self._retry(*entry)]
            with self._wake:
                self._waiting.extendleft(reversed(still))

    @staticmethod
    def _retry(deadline: float, srv: Any, server: Server | None, response: Any, header: Any) -> bool:
        """Try once more; ``True`` when done with the answer (sent, or given up)."""
        try:
            if _sent(srv, server, response, header, let_go=True):
                return True
        except InvalidHandle:
            return True  # the service is gone, and its client's wait with it
        except Exception as error:
            _log.warning("service %s: an answer was not sent (%s)", _name(srv), error)
            return True
        if time.monotonic() >= deadline:
            _log.warning(
                "service %s: an answer was not sent: its client's response reader did not match in %.1f s",
                _name(srv), RETRY_S,
            )
            return True
        return False


def _name(srv: Any) -> str:
    return str(getattr(srv, "srv_name", srv))


# rclpy reports an unmatched client as a warning, which only an error lets _sent see.
raise_client_not_matched()
_resender = _Resender()
