"""The node's parameters: their table, and their values checked as one configure sees them.

The checks are the container's (:mod:`container.checks`), so a bad LiDAR
parameter is reported in the same words as a bad container setting; only
what is particular to a LiDAR (its models, its turning sense, range and crop
limits) is checked here, raising the same :class:`~container.ConfigError`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

from container import ConfigError, checks

from ._protocol import Model, get_model
from ._scan import Direction

__all__ = ["PARAMETERS", "Settings", "read_settings"]

#: Largest ``comm.poll_msec``: 30 ms of an STL-27L at 921600 baud is 2.8 kB,
#: within the 4 KiB the kernel's line discipline buffers between two reads.
_MAX_POLL_MS: Final = 30

#: (name, default, description) of every parameter, in declaration order.
PARAMETERS: Final[tuple[tuple[str, Any, str], ...]] = (
    (
        "comm.serial_port",
        "auto",
        "Device path, pyserial URL or file://capture; 'auto' finds a USB serial device "
        "or starts the built-in emulator.",
    ),
    ("comm.baudrate", 0, "Line speed in baud; 0 uses the model's."),
    ("comm.timeout_msec", 1000, "Milliseconds without a valid packet before the port counts as failed."),
    (
        "comm.poll_msec",
        20,
        "Read the port every so many milliseconds and when a revolution is due (less CPU); "
        "0 reads whenever bytes arrive.",
    ),
    ("lidar.model", "LD06", "LD06, LD19 or STL27L."),
    ("lidar.rot_verse", "CCW", "CCW for a sensor mounted upright, CW for one mounted upside down."),
    ("lidar.frame_id", "ldlidar_link", "Frame of the published scans."),
    ("lidar.bins", 455, "Rays per scan; 0 publishes every measured point (variable length)."),
    ("lidar.range_min", 0.03, "Metres; closer readings are published as -inf."),
    ("lidar.range_max", 15.0, "Metres; farther readings are published as +inf."),
    ("lidar.enable_angle_crop", False, "Blank out the sector angle_crop_min..angle_crop_max."),
    ("lidar.angle_crop_min", 90.0, "Start of the cropped sector, degrees clockwise from the front."),
    ("lidar.angle_crop_max", 270.0, "End of the cropped sector, degrees clockwise from the front."),
)


@dataclass(frozen=True, slots=True)
class Settings:
    """The parameters, checked and converted, as one configure saw them."""

    port: str
    baudrate: int | None
    timeout: float
    poll_interval: float | None
    model: Model
    direction: Direction
    frame_id: str
    bins: int
    range_min: float
    range_max: float
    crop: tuple[float, float] | None


def read_settings(value: Callable[[str], Any]) -> Settings:
    """Check every parameter and convert it to what the device and the node use.

    :param value: the current value of the parameter with the given name.
    :raises ConfigError: a value cannot be used; ``source`` names the parameter.
    """

    def text(name: str) -> str:
        # Surrounding blanks come from YAML quoting slips, never from intent.
        return checks.string(value(name), where=_where(name)).strip()

    port = text("comm.serial_port")
    baudrate = checks.integer(value("comm.baudrate"), where=_where("comm.baudrate"), minimum=0)
    timeout_ms = checks.number(value("comm.timeout_msec"), where=_where("comm.timeout_msec"), positive=True)
    poll_ms = checks.number(value("comm.poll_msec"), where=_where("comm.poll_msec"), minimum=0, maximum=_MAX_POLL_MS)
    try:
        model = get_model(text("lidar.model"))
    except ValueError as exc:
        raise ConfigError(str(exc), source=_where("lidar.model")) from None
    verse = text("lidar.rot_verse").upper()
    if verse not in ("CW", "CCW"):
        raise ConfigError(f"must be 'CW' or 'CCW', not {verse!r}", source=_where("lidar.rot_verse"))
    frame_id = text("lidar.frame_id")
    bins = checks.integer(value("lidar.bins"), where=_where("lidar.bins"), minimum=0)
    range_min = checks.number(value("lidar.range_min"), where=_where("lidar.range_min"), minimum=0)
    range_max = checks.number(value("lidar.range_max"), where=_where("lidar.range_max"))
    if range_max <= range_min:
        raise ConfigError(
            f"must be above lidar.range_min ({range_min:g}), not {range_max:g}", source=_where("lidar.range_max")
        )
    crop: tuple[float, float] | None = None
    if checks.boolean(value("lidar.enable_angle_crop"), where=_where("lidar.enable_angle_crop")):
        # No order between the two: a sector with min > max wraps through the front.
        low, high = (
            checks.number(value(name), where=_where(name), minimum=0, maximum=360)
            for name in ("lidar.angle_crop_min", "lidar.angle_crop_max")
        )
        crop = (low, high)
    return Settings(
        port=port,
        baudrate=baudrate or None,
        timeout=timeout_ms / 1000,
        poll_interval=poll_ms / 1000 or None,
        model=model,
        direction="cw" if verse == "CW" else "ccw",
        frame_id=frame_id,
        bins=bins,
        range_min=range_min,
        range_max=range_max,
        crop=crop,
    )


def _where(name: str) -> str:
    return f"parameter {name!r}"
