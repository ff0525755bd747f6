"""Repeated warnings: the first at once, then one line per period with the count held back."""

from __future__ import annotations

from container import Throttle


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_burst_of_one_kind_is_one_line_then_one_per_period_with_its_count() -> None:
    lines: list[str] = []
    clock = _Clock()
    throttle = Throttle(lines.append, period=10.0, clock=clock)
    for _ in range(25):  # ten a second for 2.5 s
        throttle("clock_jump", "device clock jumped")
        clock.now += 0.1
    assert lines == ["device clock jumped"]
    assert throttle.held("clock_jump") == 24
    clock.now = 110.0
    assert throttle("clock_jump", "device clock jumped")
    assert lines[1] == "device clock jumped (24 more like this in the last 10 s)"
    assert throttle.held("clock_jump") == 0


def test_kinds_are_throttled_apart_and_flush_says_what_was_held() -> None:
    lines: list[str] = []
    clock = _Clock()
    throttle = Throttle(lines.append, period=5.0, clock=clock)
    throttle("a", "A")
    throttle("b", "B")
    throttle("a", "A")
    throttle("a", "A")
    assert lines == ["A", "B"]
    throttle.flush()
    assert lines[2:] == ["2 more 'a' warning(s) were not logged"]
    throttle.flush()
    assert len(lines) == 3
