"""``container.clip``: a value from outside, fit for a log line or an answer."""

from __future__ import annotations

import pytest

from container import ConfigError, DeviceError, checks, clip
from container.devices import DevicePolicy, PortRefused

MEGABYTE = 1024 * 1024
HUGE_PORT = "/dev/" + "a" * (MEGABYTE - 5)


def test_a_short_value_is_itself() -> None:
    assert clip("/dev/ttyUSB0") == "/dev/ttyUSB0"
    assert clip("/dev/ttyUSB0", quote=True) == "'/dev/ttyUSB0'"
    assert clip("x" * 200) == "x" * 200


def test_a_long_value_keeps_its_start_and_says_its_length() -> None:
    shown = clip(HUGE_PORT, quote=True)
    assert shown == f"'/dev/{'a' * 195}…' (1048576 characters)"
    assert clip("x" * 201) == f"{'x' * 200}… (201 characters)"
    assert clip("x" * 1000, limit=10) == "xxxxxxxxxx… (1000 characters)"


def test_quoting_escapes_what_could_forge_a_line_or_drive_a_terminal() -> None:
    assert clip("a\nERROR forged\x1b[2J", quote=True) == r"'a\nERROR forged\x1b[2J'"
    shown = clip("\n" * 300, quote=True)
    assert "\n" not in shown and shown.endswith("…' (300 characters)")


def test_other_values_are_shown_as_python_writes_them() -> None:
    assert clip(5, quote=True) == "5"
    assert clip([1, 2], quote=True) == "[1, 2]"
    assert clip(list(range(100_000)), quote=True).endswith(" (688890 characters)")
    assert clip(ValueError("bad")) == "bad"


def test_errors_echo_a_peers_value_clipped_and_keep_it_whole() -> None:
    refused = PortRefused("not allowed", port=HUGE_PORT)
    assert refused.port == HUGE_PORT
    assert len(str(refused)) < 300 and "(1048576 characters)" in str(refused)
    with pytest.raises(PortRefused, match=r"^port '/dev/a+…' \(1048576 characters\): a path of 1048576 bytes"):
        DevicePolicy().check_port(HUGE_PORT)
    device = DeviceError("port closed", device=HUGE_PORT)
    assert device.device == HUGE_PORT and len(str(device)) < 300


@pytest.mark.parametrize(
    "check", [checks.boolean, checks.integer, checks.number, checks.strings], ids=lambda c: c.__name__
)
def test_a_refused_parameter_value_is_echoed_clipped(check: object) -> None:
    with pytest.raises(ConfigError) as refused:
        check("x" * MEGABYTE, where="parameter 'p'")  # type: ignore[operator]
    assert len(str(refused.value)) < 300 and "(1048576 characters)" in str(refused.value)
