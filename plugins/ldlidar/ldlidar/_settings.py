"""The node's parameters: their table, their values checked as one configure sees them, and migration.

The checks are the container's (:mod:`container.checks`), so a bad LiDAR
parameter is reported in the same words as a bad container setting; only
what is particular to a LiDAR (its models, its turning sense, range and crop
limits) is checked here, raising the same :class:`~container.ConfigError`.

A parameter file written for another driver must not be silently ignored:
the vendor driver's names (ldlidar_stl_ros2, ldlidar_ros2) that mean one of
ours are taken as aliases, with a deprecation notice naming ours
(:func:`migrate`); the few that cannot mean anything here are refused with
what to do instead (:data:`REFUSED`); the community driver's ``lidar.units``
is refused unless metres.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Final

from container import ConfigError, checks, clip

from ._protocol import Model, get_model
from ._scan import Direction

__all__ = ["ALIASES", "PARAMETERS", "REFUSED", "Migration", "Settings", "migrate", "read_settings"]

#: Largest ``comm.poll_msec``: 30 ms of an STL-27L at 921600 baud is 2.8 kB,
#: within the 4 KiB the kernel's line discipline buffers between two reads.
_MAX_POLL_MS: Final = 30

#: Bounds of ``diagnostics.period_msec``: a report costs a message of some
#: 20 values; ten a second is plenty for a person or an aggregator, and one a
#: minute is as rare as a status can be and still be current.
_MIN_PERIOD_MS: Final = 100
_MAX_PERIOD_MS: Final = 60000

#: Default ``diagnostics.outage_msec``. Longer than what the node rides out
#: by itself, each with a line or a count of its own (a stall, a revolution
#: of line noise, a replug: ``comm.timeout_msec`` and the first reopen
#: attempts, 1 + 0.1 + 0.2 + 0.4 + 0.8 + 1.6 s by default), so that only
#: an outage a person must hear of is logged; the same as
#: diagnostic_aggregator's default ``timeout``, after which it marks a
#: silent status stale.
_OUTAGE_MS: Final = 5000

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
        "Read the port every so many milliseconds (1-30) until a revolution can be predicted, "
        "then once per revolution when it is due.",
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
    (
        "lidar.noise_filter",
        False,
        "Drop isolated dim returns closer than 5 m, as the vendor's LD06/LD19 driver does.",
    ),
    ("lidar.units", "M", "Units of the ranges: only M (metres, as sensor_msgs/LaserScan defines them)."),
    ("general.publish_when_subscribed", False, "Build and publish scans only while ~/scan has a subscriber."),
    ("general.debug_mode", False, "Log at debug level, one line per revolution."),
    (
        "diagnostics.period_msec",
        1000,
        f"Milliseconds between two /diagnostics reports ({_MIN_PERIOD_MS}-{_MAX_PERIOD_MS}).",
    ),
    (
        "diagnostics.outage_msec",
        _OUTAGE_MS,
        "Milliseconds without a valid packet after which an outage is logged (a WARN when it starts, "
        "an INFO when it ends).",
    ),
)

_TOPIC_REMAP = (
    "this node publishes ~/scan: remap it instead (a container file: remappings: "
    "['~/scan:=/scan']; a command line: -r ~/scan:=/scan)"
)

#: Parameters of other drivers that cannot mean anything here, and what to do instead.
REFUSED: Final[Mapping[str, str]] = MappingProxyType(
    {
        "topic_name": _TOPIC_REMAP,
        "laser_scan_topic_name": _TOPIC_REMAP,
        "point_cloud_2d_topic_name": "this node publishes no point cloud: project ~/scan (laser_geometry)",
    }
)


def _counter_clockwise(value: Any) -> str:
    # The vendor's laser_scan_dir: true publishes counter-clockwise (upright).
    return "CCW" if checks.boolean(value, where="parameter 'laser_scan_dir'") else "CW"


#: Parameters of the vendor's drivers (ldlidar_stl_ros2, ldlidar_ros2) that
#: mean one of ours: vendor name -> (our name, conversion of the value).
ALIASES: Final[Mapping[str, tuple[str, Callable[[Any], Any] | None]]] = MappingProxyType(
    {
        "port_name": ("comm.serial_port", None),
        "port_baudrate": ("comm.baudrate", None),
        "serial_baudrate": ("comm.baudrate", None),
        "product_name": ("lidar.model", None),
        "frame_id": ("lidar.frame_id", None),
        "laser_scan_dir": ("lidar.rot_verse", _counter_clockwise),
        "enable_angle_crop_func": ("lidar.enable_angle_crop", None),
        "angle_crop_min": ("lidar.angle_crop_min", None),
        "angle_crop_max": ("lidar.angle_crop_max", None),
        "range_min": ("lidar.range_min", None),
        "range_max": ("lidar.range_max", None),
    }
)


@dataclass(slots=True)
class Migration:
    """What :func:`migrate` made of a node's parameter overrides.

    :param values: the overrides to give the node, under our names.
    :param notices: one line per alias taken (or ignored), for the log.
    :param refused: the refusals, each naming its parameter; configure fails on them.
    """

    values: dict[str, Any] = field(default_factory=dict)
    notices: list[str] = field(default_factory=list)
    refused: list[ConfigError] = field(default_factory=list)


def migrate(overrides: Iterable[tuple[str, Any]]) -> Migration:
    """Translate other drivers' parameter names into ours.

    Our own name wins over an alias given beside it.
    """
    given = list(overrides)
    ours = {name for name, _ in given if name not in ALIASES}
    out = Migration()
    for name, value in given:
        if name in REFUSED:
            out.refused.append(ConfigError(f"not supported: {REFUSED[name]}", source=_where(name)))
            continue
        alias = ALIASES.get(name)
        if alias is None:
            out.values[name] = value
            continue
        target, convert = alias
        if target in ours:
            out.notices.append(f"Parameter {name!r} (vendor driver) ignored: {target!r} is given too")
            continue
        try:
            out.values[target] = convert(value) if convert is not None else value
        except ConfigError as exc:
            out.refused.append(exc)
            continue
        out.notices.append(f"Parameter {name!r} (vendor driver) is deprecated: use {target!r}")
    return out


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
    #: Seconds between two ``/diagnostics`` reports.
    diagnostics_period: float
    #: Seconds without a valid packet that make an outage worth a log line.
    outage: float
    noise_filter: bool = False
    publish_when_subscribed: bool = False
    debug: bool = False


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
    if poll_ms == 0:
        # It read whenever bytes arrived: every USB burst woke the event loop,
        # twice the CPU of polling (bench_lidar: 4.3% of a core against 2.2%)
        # for no lower latency (median 1.11 ms against 0.91 ms).
        raise ConfigError(
            "0 (read whenever bytes arrive) is not offered: it cost twice the CPU of polling for no "
            "lower latency, since a revolution is read as soon as its last bytes arrive anyway; "
            f"use 1-{_MAX_POLL_MS}",
            source=_where("comm.poll_msec"),
        )
    try:
        model = get_model(text("lidar.model"))
    except ValueError as exc:
        raise ConfigError(str(exc), source=_where("lidar.model")) from None
    verse = text("lidar.rot_verse").upper()
    if verse not in ("CW", "CCW"):
        raise ConfigError(f"must be 'CW' or 'CCW', not {clip(verse, quote=True)}", source=_where("lidar.rot_verse"))
    frame_id = text("lidar.frame_id")
    bins = checks.integer(value("lidar.bins"), where=_where("lidar.bins"), minimum=0)
    range_min = checks.number(value("lidar.range_min"), where=_where("lidar.range_min"), minimum=0)
    range_max = checks.number(value("lidar.range_max"), where=_where("lidar.range_max"))
    if range_max <= range_min:
        raise ConfigError(
            f"must be above lidar.range_min ({range_min:g}), not {range_max:g}", source=_where("lidar.range_max")
        )
    units = text("lidar.units").upper()
    if units not in ("M", "METERS", "METRES"):
        raise ConfigError(
            f"only M (metres) is supported, not {clip(units, quote=True)}: sensor_msgs/LaserScan ranges are metres "
            "(REP 103), and consumers (slam_toolbox, nav2, rviz2) read them so",
            source=_where("lidar.units"),
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
        poll_interval=poll_ms / 1000,
        model=model,
        direction="cw" if verse == "CW" else "ccw",
        frame_id=frame_id,
        bins=bins,
        range_min=range_min,
        range_max=range_max,
        crop=crop,
        noise_filter=checks.boolean(value("lidar.noise_filter"), where=_where("lidar.noise_filter")),
        publish_when_subscribed=checks.boolean(
            value("general.publish_when_subscribed"), where=_where("general.publish_when_subscribed")
        ),
        debug=checks.boolean(value("general.debug_mode"), where=_where("general.debug_mode")),
        diagnostics_period=checks.number(
            value("diagnostics.period_msec"),
            where=_where("diagnostics.period_msec"),
            minimum=_MIN_PERIOD_MS,
            maximum=_MAX_PERIOD_MS,
        )
        / 1000,
        outage=checks.number(value("diagnostics.outage_msec"), where=_where("diagnostics.outage_msec"), positive=True)
        / 1000,
    )


def _where(name: str) -> str:
    return f"parameter {name!r}"
