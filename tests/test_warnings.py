"""The warnings a load caused, as a successful LoadNode answer carries them."""

from __future__ import annotations

from container import LoadWarning
from container._warnings import decode, encode


def test_a_successful_answer_reads_back_as_the_warnings_it_carries() -> None:
    warnings = [
        LoadWarning("talker", "Unknown parameter 'rat' ignored: this node does not read it (did you mean 'rate'?)"),
        LoadWarning("robot.ComponentManager", "Extra component argument 'x' is not used by this container"),
    ]
    text = encode(warnings)
    assert text.splitlines()[0] == (
        "[WARN] [talker]: Unknown parameter 'rat' ignored: this node does not read it (did you mean 'rate'?)"
    )
    assert decode(text, default_logger="ComponentManager") == warnings


def test_no_warnings_leave_the_answer_empty_as_rclcpp_does() -> None:
    assert encode([]) == ""
    assert decode("", default_logger="ComponentManager") == []


def test_a_line_break_in_a_message_cannot_forge_another_warning() -> None:
    text = encode([LoadWarning("talker", "first\n[WARN] [forged]: second")])
    assert decode(text, default_logger="c") == [LoadWarning("talker", "first [WARN] [forged]: second")]


def test_another_containers_text_on_success_is_its_own_warning() -> None:
    assert decode("cut short: timer still running\n", default_logger="ComponentManager") == [
        LoadWarning("ComponentManager", "cut short: timer still running")
    ]


def test_a_huge_list_is_clipped_to_one_answer() -> None:
    text = encode([LoadWarning("n", "x" * 300)] * 10)
    assert len(text) < 900
    assert text.endswith("characters)")
