"""Spacing a service's answers, so that a burst of them cannot push one out of its caller's history.

DDS delivers every answer of a service to every client of that service,
and each client drops the answers that are not its own (rmw_fastrtps and
rmw_cyclonedds alike: rclcpp#2397). A client keeps what it has not taken
yet in its response history, 10 deep with rclpy's default QoS. So when 20
callers wait at once and the node answers them within a few milliseconds,
each client sees 20 answers arrive, and one that has not taken its own
before ten more came loses it to the history. Measured with 20 callers in
another process on a loaded two-core machine: some of the first ten went
unanswered in about half the bursts (the one whose transition took effect
among them), with this node's keep-all services as with rcl's own. The
service's QoS cannot help: the answer is lost in the client.

:class:`AnswerPacer` lets a few answers go at once (a caller's transitions
in a row, a lifecycle manager's configure and activate, are not held up)
and spaces the rest of a burst one per ``interval``, so a client has at
least ``11 - burst`` intervals (80 ms by default) to take its answer
before ten more can have come. Twenty concurrent callers are all answered
within 170 ms.
"""

from __future__ import annotations

import functools
import math
import threading
import time
from collections.abc import Callable
from typing import TypeVar

__all__ = ["AnswerPacer", "paced"]

#: Answers that go out at once, then one per interval.
BURST = 3
INTERVAL_S = 0.01

Request = TypeVar("Request")
Response = TypeVar("Response")


class AnswerPacer:
    """When each answer of one service may go: ``burst`` at once, then one per ``interval``.

    A generic cell rate algorithm (a token bucket kept as one time): the
    bucket refills at one answer per ``interval`` up to ``burst``.
    Thread-safe: answers of a reentrant group ask from several threads.

    :param clock: seconds, monotonic (a fake one in tests).
    """

    def __init__(
        self, *, burst: int = BURST, interval: float = INTERVAL_S, clock: Callable[[], float] = time.monotonic
    ) -> None:
        if burst < 1 or not interval > 0:
            raise ValueError(f"burst must be at least 1 and interval positive, not {burst} and {interval}")
        self._interval = interval
        self._tolerance = (burst - 1) * interval
        self._clock = clock
        self._lock = threading.Lock()
        #: When the next answer would go if the bucket were empty.
        self._due = -math.inf

    def delay(self) -> float:
        """Reserve the next answer's turn; the seconds to wait before sending it."""
        with self._lock:
            now = self._clock()
            send_at = max(now, self._due - self._tolerance)
            self._due = max(self._due, send_at) + self._interval
            return send_at - now


def paced(
    handler: Callable[[Request, Response], Response], pacer: AnswerPacer
) -> Callable[[Request, Response], Response]:
    """``handler``, returning its answer only when ``pacer`` lets it go.

    For plain service callbacks: the wait is on the callback's own thread
    (a lane's), never on the event loop; the answer is sent when it returns.
    """

    @functools.wraps(handler)
    def answer(request: Request, response: Response) -> Response:
        answered = handler(request, response)
        wait = pacer.delay()
        if wait > 0:
            time.sleep(wait)  # the pacing itself: the thread has nothing else to do meanwhile
        return answered

    return answer
