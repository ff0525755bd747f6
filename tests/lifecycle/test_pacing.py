"""The answer pacer: a few answers at once, then one per interval; idle time refills it."""

from __future__ import annotations

import itertools

import pytest

from container.lifecycle._pacing import AnswerPacer, paced


class Clock:
    """A clock the test moves."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_burst_goes_at_once_up_to_its_size_then_one_per_interval() -> None:
    clock = Clock()
    pacer = AnswerPacer(burst=3, interval=0.01, clock=clock)

    delays = [pacer.delay() for _ in range(6)]

    assert delays == pytest.approx([0.0, 0.0, 0.0, 0.01, 0.02, 0.03])


def test_a_caller_s_transitions_in_a_row_are_held_to_one_per_interval_only_past_the_burst() -> None:
    clock = Clock()
    pacer = AnswerPacer(burst=3, interval=0.01, clock=clock)

    sent = []
    for _ in range(8):
        clock.now += pacer.delay()  # answered after the delay
        sent.append(clock.now)
        clock.now += 0.004  # the caller's round trip to its next request

    # configure, activate, deactivate, cleanup as fast as the caller goes:
    # never held up; past that, one answer per 10 ms.
    gaps = [b - a for a, b in itertools.pairwise(sent)]
    assert gaps[:3] == pytest.approx([0.004] * 3)
    assert gaps[-3:] == pytest.approx([0.01] * 3)


def test_idle_time_refills_the_burst() -> None:
    clock = Clock()
    pacer = AnswerPacer(burst=3, interval=0.01, clock=clock)
    for _ in range(5):
        pacer.delay()

    clock.now += 1.0

    assert [pacer.delay() for _ in range(4)] == pytest.approx([0.0, 0.0, 0.0, 0.01])


def test_a_pacer_refuses_an_empty_burst_or_no_interval() -> None:
    with pytest.raises(ValueError, match="burst must be at least 1"):
        AnswerPacer(burst=0)
    with pytest.raises(ValueError, match="interval positive"):
        AnswerPacer(interval=float("nan"))


def test_paced_returns_the_handler_s_answer_and_keeps_its_name() -> None:
    def handler(request: int, response: list[int]) -> list[int]:
        response.append(request)
        return response

    answer = paced(handler, AnswerPacer())

    assert answer(7, []) == [7]
    assert answer.__name__ == "handler"
