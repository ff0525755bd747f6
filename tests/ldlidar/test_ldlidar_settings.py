"""The node's parameters, checked without a node: what each value becomes, and what is refused."""

from __future__ import annotations

from typing import Any

import pytest

from container import ConfigError
from ldlidar import MODELS
from ldlidar._settings import PARAMETERS, Settings, read_settings
from ldlidar.plugin import DIAGNOSTICS_PERIOD

DEFAULTS = {name: default for name, default, _ in PARAMETERS}


def settings_with(**changes: Any) -> Settings:
    """Settings from the defaults with *changes*; keyword names use ``__`` for ``.``."""
    values = {**DEFAULTS, **{k.replace("__", "."): v for k, v in changes.items()}}
    return read_settings(values.__getitem__)


def test_defaults_are_an_upright_ld06_found_automatically() -> None:
    settings = settings_with()
    assert settings.port == "auto" and settings.model is MODELS["LD06"]
    assert settings.baudrate is None  # the model's own
    assert (settings.timeout, settings.poll_interval) == pytest.approx((1.0, 0.02))
    assert settings.direction == "ccw" and settings.frame_id == "ldlidar_link"
    assert (settings.bins, settings.range_min, settings.range_max) == (455, 0.03, 15.0)
    assert settings.crop is None
    # A report a second, as ROS's diagnostic_updater; an outage worth a log line after 5 s.
    assert (settings.diagnostics_period, settings.outage) == (DIAGNOSTICS_PERIOD, 5.0)


def test_values_are_converted_to_what_the_device_takes() -> None:
    settings = settings_with(
        comm__serial_port=" /dev/ttyUSB0 ",
        comm__baudrate=921600.0,
        comm__poll_msec=5,
        lidar__model="stl-27l",
        lidar__rot_verse="cw",
        lidar__range_max=12,
        lidar__enable_angle_crop=True,
        lidar__angle_crop_min=300,
        lidar__angle_crop_max=60,
    )
    assert settings.port == "/dev/ttyUSB0" and settings.baudrate == 921600
    assert settings.poll_interval == pytest.approx(0.005)
    assert settings.model is MODELS["STL27L"] and settings.direction == "cw"
    assert settings.range_max == 12.0
    assert settings.crop == (300.0, 60.0)  # a sector through the front


@pytest.mark.parametrize(
    ("parameter", "value", "reason"),
    [
        ("comm.serial_port", 5, "must be a non-empty string, not 5"),
        ("comm.baudrate", -1, "must be >= 0, not -1"),
        ("comm.baudrate", True, "must be an integer, not True"),
        ("comm.timeout_msec", -5, "must be positive, not -5"),
        ("comm.poll_msec", 31, "must be within [0, 30], not 31"),
        (
            "comm.poll_msec",
            0,
            "0 (read whenever bytes arrive) is not offered: it cost twice the CPU of polling for no lower "
            "latency, since a revolution is read as soon as its last bytes arrive anyway; use 1-30",
        ),
        ("lidar.model", "LD99", "unknown LiDAR model 'LD99'; known: LD06, LD19, STL27L"),
        ("lidar.rot_verse", "up", "must be 'CW' or 'CCW', not 'UP'"),
        ("lidar.frame_id", "  ", "must be a non-empty string, not '  '"),
        ("lidar.bins", 1.5, "must be an integer, not 1.5"),
        ("lidar.range_min", -0.1, "must be >= 0, not -0.1"),
        ("lidar.range_min", float("nan"), "must be a finite number, not nan"),
        ("lidar.range_max", 0.03, "must be above lidar.range_min (0.03), not 0.03"),
        ("lidar.enable_angle_crop", "yes", "must be true or false, not 'yes'"),
        ("diagnostics.period_msec", 50, "must be within [100, 60000], not 50"),
        ("diagnostics.outage_msec", 0, "must be positive, not 0"),
        ("lidar.model", "L" * 300, f"unknown LiDAR model '{'L' * 200}…' (300 characters); known: LD06, LD19, STL27L"),
    ],
)
def test_a_bad_value_is_refused_naming_its_parameter(parameter: str, value: Any, reason: str) -> None:
    with pytest.raises(ConfigError) as caught:
        settings_with(**{parameter.replace(".", "__"): value})
    assert caught.value.source == f"parameter {parameter!r}"
    assert caught.value.reason == reason
    assert str(caught.value) == f"parameter {parameter!r}: {reason}"


@pytest.mark.parametrize("parameter", ["lidar.angle_crop_min", "lidar.angle_crop_max"])
def test_crop_angles_are_checked_only_when_cropping(parameter: str) -> None:
    key = parameter.replace(".", "__")
    assert settings_with(**{key: 400}).crop is None
    with pytest.raises(ConfigError, match=r"must be within \[0, 360\], not 400") as caught:
        settings_with(lidar__enable_angle_crop=True, **{key: 400})
    assert caught.value.source == f"parameter {parameter!r}"
