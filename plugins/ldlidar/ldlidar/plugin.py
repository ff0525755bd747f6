"""The ROS 2 face of the driver: the ``ldlidar::LdLidarNode`` lifecycle node.

This module is the distribution's ``container.plugins`` entry point; the rest
of the package stays free of ROS. The node fixes what hurts users of the
community driver (Myzhar/ldrobot-lidar-ros2) while keeping its parameter
names: ``comm.baudrate`` is honoured (the STL-27L needs 921600), a port that
cannot open fails the configure transition instead of calling ``exit()``, a
port that vanishes is reopened, ``range_min``/``range_max`` are applied, and
scans are stamped with the time of their first ray.

Parameters (read by ``configure``; change them, then ``cleanup`` and
``configure`` again):

========================  ==================  =============================================
name                      default             meaning
========================  ==================  =============================================
comm.serial_port          ``auto``            device path, pyserial URL
                                              (``socket://host:port``), or
                                              ``file://capture.bin`` (replayed at line
                                              rate, once); ``auto``: the first of
                                              :data:`AUTO_PORT_PATTERNS` that exists,
                                              else the built-in emulator on a
                                              pseudo-terminal
comm.baudrate             0                   line speed; 0 = the model's own
comm.timeout_msec         1000                ms to wait for a valid packet: at
                                              configure, and while streaming before the
                                              port counts as lost and is reopened
comm.poll_msec            20                  read the port every so many ms, and when
                                              each revolution is predicted to complete
                                              (few large reads: less CPU, same
                                              latency); 0 = read whenever bytes arrive
                                              (not in the community driver)
lidar.model               ``LD06``            ``LD06``, ``LD19``, ``STL27L`` (also
                                              ``LDLiDAR_LD19``, ``STL-27L``, any case)
lidar.rot_verse           ``CCW``             ``CCW`` for a sensor mounted upright,
                                              ``CW`` for one mounted upside down
lidar.frame_id            ``ldlidar_link``    ``header.frame_id`` of the scans
lidar.bins                455                 rays per scan, fixed (what slam_toolbox
                                              needs); 0 = one ray per measured point
                                              (the length varies between turns)
lidar.range_min           0.03                metres; closer readings are published -inf
lidar.range_max           15.0                metres; farther readings are published +inf
lidar.enable_angle_crop   false               blank out a sector
lidar.angle_crop_min      90.0                sector start, degrees clockwise from the
                                              sensor's front
lidar.angle_crop_max      270.0               sector end; cropped rays are NaN
========================  ==================  =============================================

Topics:

* ``~/scan`` (``sensor_msgs/LaserScan``), one per revolution, while active,
  stamped with the system (wall-clock) time of the revolution's first ray,
  derived from the device's millisecond clock.
  QoS: reliable, volatile, keep last 10. rviz2's LaserScan display
  subscribes reliable by default and would never match a best-effort
  publisher; a best-effort (SensorData) subscriber such as slam_toolbox's
  still matches a reliable one.
* ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``), about once a second
  while configured (inactive or active): packet and scan rates, CRC errors,
  resyncs, skipped bytes, reopens; level ERROR when no data arrives.

The port is read by one asyncio task on the executor's event loop, from
``configure`` to ``cleanup``: a deactivated node stops publishing but keeps
reading, so the parser and the device clock stay in sync.
"""

from __future__ import annotations

import array
import asyncio
import glob
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.lifecycle import LifecyclePublisher, LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.timer import Timer
from sensor_msgs.msg import LaserScan

from container import DeviceError, LifecycleNode, RegisterNodeType, hookimpl

from . import _errors
from ._emulator import Emulator
from ._lidar import Lidar
from ._protocol import Model, get_model
from ._scan import Direction, Scan

__all__ = [
    "AUTO_PORT_PATTERNS",
    "DIAGNOSTICS_PERIOD",
    "SCAN_QOS",
    "LdLidarNode",
    "find_serial_ports",
    "register_node_types",
    "to_laser_scan",
]

SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE

#: Where ``comm.serial_port: auto`` looks, in order: the community driver's
#: udev link, stable by-id names, then raw USB-serial and CDC-ACM devices.
AUTO_PORT_PATTERNS: Final = ("/dev/ldlidar", "/dev/serial/by-id/*", "/dev/ttyUSB*", "/dev/ttyACM*")

#: Seconds between two ``/diagnostics`` messages.
DIAGNOSTICS_PERIOD: Final = 1.0

#: QoS of ``~/scan``; see the module docstring for why reliable.
SCAN_QOS: Final = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

#: Largest ``comm.poll_msec``: 30 ms of an STL-27L at 921600 baud is 2.8 kB,
#: within the 4 KiB the kernel's line discipline buffers between two reads.
_MAX_POLL_MS: Final = 30

#: The node's own emulator writes every so many seconds, as a USB adapter
#: delivers bursts; finer ticks cost the container CPU for nothing.
_EMULATOR_TICK: Final = 0.01

#: First reopen attempt after this many seconds; then doubling up to the max.
_REOPEN_INTERVAL: Final = 0.1
_REOPEN_MAX_INTERVAL: Final = 2.0

#: (name, default, description) of every parameter, in declaration order.
_PARAMETERS: Final[tuple[tuple[str, Any, str], ...]] = (
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


def find_serial_ports(patterns: Sequence[str] = AUTO_PORT_PATTERNS) -> list[str]:
    """Return the existing devices matching *patterns*, in pattern order, each once."""
    found: list[str] = []
    for pattern in patterns:
        for path in sorted(glob.glob(pattern)):
            if path not in found:
                found.append(path)
    return found


def to_laser_scan(scan: Scan, *, frame_id: str) -> LaserScan:
    """Return *scan* as a ``sensor_msgs/LaserScan`` stamped with its first ray's time."""
    msg = LaserScan()
    msg.header.frame_id = frame_id
    msg.header.stamp = _to_time(scan.stamp)
    msg.angle_min = scan.angle_min
    msg.angle_max = scan.angle_max
    msg.angle_increment = scan.angle_increment
    msg.time_increment = scan.time_increment
    msg.scan_time = scan.scan_time
    msg.range_min = scan.range_min
    msg.range_max = scan.range_max
    # The arrays are float32 already: a byte copy, not a per-element check.
    msg.ranges = array.array("f", scan.ranges.tobytes())
    msg.intensities = array.array("f", scan.intensities.tobytes())
    return msg


def _to_time(seconds: float) -> Time:
    sec = math.floor(seconds)
    nanosec = round((seconds - sec) * 1e9)
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return Time(sec=sec, nanosec=nanosec)


class _InvalidParameter(Exception):
    """A parameter's value cannot be used; the message names it."""

    def __init__(self, name: str, reason: str) -> None:
        super().__init__(f"parameter {name!r}: {reason}")
        self.name = name


@dataclass(frozen=True, slots=True)
class _Settings:
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


@dataclass(frozen=True, slots=True)
class _Counts:
    """Counters at one diagnostics message; the next one reports the difference."""

    when: float
    packets: int = 0
    scans: int = 0
    crc_errors: int = 0
    skipped_bytes: int = 0
    health_frames: int = 0

    @classmethod
    def now(cls, lidar: Lidar, scans: int) -> _Counts:
        stats = lidar.stats
        return cls(
            when=time.monotonic(),
            packets=stats.packets,
            scans=scans,
            crc_errors=stats.crc_errors,
            skipped_bytes=stats.skipped_bytes,
            health_frames=stats.health_frames,
        )


class LdLidarNode(LifecycleNode):
    """An LDRobot LD06 / LD19 / STL-27L LiDAR publishing ``~/scan`` while active.

    See the module docstring for parameters and topics. ``configure`` opens
    the port and waits up to ``comm.timeout_msec`` for a valid packet;
    ``activate`` starts publishing; ``deactivate`` stops publishing and keeps
    reading; ``cleanup``, ``shutdown`` and error processing close the port
    (and stop the emulator if this node started it).
    """

    default_node_name = "ldlidar"

    #: Where ``comm.serial_port: auto`` looks; a subclass may narrow it.
    auto_port_patterns: Sequence[str] = AUTO_PORT_PATTERNS

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        for name, default, description in _PARAMETERS:
            # Dynamic typing: a YAML "15" for a float is fine, and any wrong
            # type is refused by configure with the parameter's name rather
            # than by the constructor with rclpy's generic type error.
            self.declare_parameter(
                name, default, ParameterDescriptor(description=description, dynamic_typing=True)
            )
        self._settings: _Settings | None = None
        self._lidar: Lidar | None = None
        self._emulator: Emulator | None = None
        self._reader: asyncio.Task[None] | None = None
        self._reader_error: BaseException | None = None
        self._failing: asyncio.Task[str] | None = None
        self._scan_publisher: LifecyclePublisher | None = None
        self._diagnostics_publisher: Publisher | None = None
        self._diagnostics_timer: Timer | None = None
        self._counts = _Counts(when=time.monotonic())
        self._scans = 0
        self._published = 0

    # -- what tests and tools may look at ------------------------------------------
    @property
    def lidar(self) -> Lidar | None:
        """The device while configured, else ``None``."""
        return self._lidar

    @property
    def emulator(self) -> Emulator | None:
        """The emulator this node started for ``comm.serial_port: auto``, if any."""
        return self._emulator

    @property
    def port(self) -> str | None:
        """The port or URL in use while configured."""
        return self._lidar.port if self._lidar is not None else None

    @property
    def reconnects(self) -> int:
        """Times the port was reopened after it failed, since configure."""
        return self._lidar.reopens if self._lidar is not None else 0

    @property
    def scans_published(self) -> int:
        """Scans published since configure."""
        return self._published

    # -- transitions ---------------------------------------------------------------
    async def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Check the parameters, open the port, wait for data, start reading."""
        log = self.get_logger()
        try:
            settings = self._read_settings()
        except _InvalidParameter as exc:
            log.error(f"Cannot configure: {exc}")
            return FAILURE
        try:
            await self._start(settings)
        except DeviceError as exc:
            log.error(f"Cannot configure: {exc}")
            await self._release()
            return FAILURE
        except BaseException:
            # Timed out (cancelled) or a bug: leave nothing open behind.
            await self._release()
            raise
        assert self._lidar is not None
        log.info(
            f"Configured: {settings.model.name} on {self._lidar.port} at {self._lidar.baudrate} "
            f"baud; publishing on {self._scan_publisher_topic()} once active"
        )
        return SUCCESS

    async def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Start publishing (the managed publisher follows the state)."""
        if self._lidar is None or self._reader is None or self._reader.done():
            self.get_logger().error(
                f"Cannot activate: {self._reader_stopped_reason()}; clean up and configure again"
            )
            return FAILURE
        self.get_logger().info(f"Publishing scans on {self._scan_publisher_topic()}")
        return SUCCESS

    async def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop publishing; the port stays open and read."""
        self.get_logger().info("Deactivated: scans are not published; the port is still read")
        return SUCCESS

    async def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Close the port and drop the publishers."""
        await self._release()
        return SUCCESS

    async def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Close everything, from whichever state."""
        await self._release()
        return SUCCESS

    async def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Close everything; the node may be configured again."""
        await self._release()
        return SUCCESS

    def destroy_node(self) -> None:
        # The container always brings a node down first; a bare destroy can
        # only stop the reader, whose port then closes with the event loop.
        if self._reader is not None and not self._reader.done():
            self.get_logger().warning("Destroyed while configured: the port was not closed cleanly")
            self._reader.cancel()
        super().destroy_node()

    # -- configure, step by step ----------------------------------------------------
    def _read_settings(self) -> _Settings:
        def value(name: str) -> Any:
            return self.get_parameter(name).value

        port = _string("comm.serial_port", value("comm.serial_port"))
        baudrate = _integer("comm.baudrate", value("comm.baudrate"), minimum=0)
        timeout_ms = _number("comm.timeout_msec", value("comm.timeout_msec"))
        if timeout_ms <= 0:
            raise _InvalidParameter("comm.timeout_msec", f"must be positive, not {timeout_ms:g}")
        poll_ms = _number("comm.poll_msec", value("comm.poll_msec"))
        if not 0 <= poll_ms <= _MAX_POLL_MS:
            raise _InvalidParameter("comm.poll_msec", f"must be within [0, {_MAX_POLL_MS}], not {poll_ms:g}")
        model_name = _string("lidar.model", value("lidar.model"))
        try:
            model = get_model(model_name)
        except ValueError as exc:
            raise _InvalidParameter("lidar.model", str(exc)) from None
        verse = _string("lidar.rot_verse", value("lidar.rot_verse")).upper()
        if verse not in ("CW", "CCW"):
            raise _InvalidParameter("lidar.rot_verse", f"must be 'CW' or 'CCW', not {verse!r}")
        direction: Direction = "cw" if verse == "CW" else "ccw"
        frame_id = _string("lidar.frame_id", value("lidar.frame_id"))
        bins = _integer("lidar.bins", value("lidar.bins"), minimum=0)
        range_min = _number("lidar.range_min", value("lidar.range_min"))
        range_max = _number("lidar.range_max", value("lidar.range_max"))
        if range_min < 0:
            raise _InvalidParameter("lidar.range_min", f"must be >= 0, not {range_min:g}")
        if range_max <= range_min:
            raise _InvalidParameter(
                "lidar.range_max", f"must be above lidar.range_min ({range_min:g}), not {range_max:g}"
            )
        crop: tuple[float, float] | None = None
        if _boolean("lidar.enable_angle_crop", value("lidar.enable_angle_crop")):
            low = _number("lidar.angle_crop_min", value("lidar.angle_crop_min"))
            high = _number("lidar.angle_crop_max", value("lidar.angle_crop_max"))
            for name, angle in (("lidar.angle_crop_min", low), ("lidar.angle_crop_max", high)):
                if not 0 <= angle <= 360:
                    raise _InvalidParameter(name, f"must be within [0, 360] degrees, not {angle:g}")
            crop = (low, high)
        return _Settings(
            port=port,
            baudrate=baudrate or None,
            timeout=timeout_ms / 1000,
            poll_interval=poll_ms / 1000 or None,
            model=model,
            direction=direction,
            frame_id=frame_id,
            bins=bins,
            range_min=range_min,
            range_max=range_max,
            crop=crop,
        )

    async def _start(self, settings: _Settings) -> None:
        """Open the device, create the publishers, start the reader.

        :raises DeviceError: the port (or the emulator) could not be opened,
            or sent no valid packet in time. Whatever was opened stays
            recorded on the node, for :meth:`_release` to close.
        """
        port = settings.port
        if port.lower() == "auto":
            port = await self._auto_port(settings.model)
        lidar = Lidar(
            port,
            model=settings.model,
            baudrate=settings.baudrate,
            bins=settings.bins,
            direction=settings.direction,
            range_min=settings.range_min,
            range_max=settings.range_max,
            crop=settings.crop,
            poll_interval=settings.poll_interval,
            timeout=settings.timeout,
            reopen=True,
            reopen_interval=_REOPEN_INTERVAL,
            reopen_max_interval=_REOPEN_MAX_INTERVAL,
        )
        try:
            await lidar.open()
        except _errors.DeviceError as exc:
            raise _device_error(exc) from exc
        self._settings = settings
        self._lidar = lidar
        self._scans = self._published = 0
        self._reader_error = None
        self._counts = _Counts.now(lidar, 0)
        self._scan_publisher = self.create_lifecycle_publisher(LaserScan, "~/scan", SCAN_QOS)
        self._diagnostics_publisher = self.create_publisher(
            DiagnosticArray, "/diagnostics", 10, managed=False
        )
        self._diagnostics_timer = self.create_timer(
            DIAGNOSTICS_PERIOD, self._publish_diagnostics, managed=False
        )
        self._reader = asyncio.get_running_loop().create_task(
            self._read(lidar), name=f"ldlidar-reader:{self.get_fully_qualified_name()}"
        )

    async def _auto_port(self, model: Model) -> str:
        """The first attached device, or the port of a freshly started emulator."""
        found = find_serial_ports(self.auto_port_patterns)
        if found:
            self.get_logger().info(f"comm.serial_port 'auto': using {found[0]} (found {', '.join(found)})")
            return found[0]
        emulator = Emulator(model=model, tick=_EMULATOR_TICK)
        self._emulator = emulator
        try:
            await emulator.start()
        except _errors.LidarError as exc:
            raise DeviceError(f"cannot start the emulator: {exc}", device="emulator") from exc
        self.get_logger().warning(
            f"comm.serial_port 'auto': no LiDAR attached (looked for "
            f"{' '.join(self.auto_port_patterns)}); started the built-in {model.name} "
            f"emulator on {emulator.port} (link {emulator.link}): the scans are simulated"
        )
        return emulator.link

    async def _release(self) -> None:
        """Stop the reader, close the port, drop publishers, stop our emulator."""
        reader, self._reader = self._reader, None
        if reader is not None and reader is not asyncio.current_task():
            reader.cancel()
            await asyncio.wait([reader])
        lidar, self._lidar = self._lidar, None
        if lidar is not None:
            await lidar.close()
        if self._diagnostics_timer is not None:
            self.destroy_timer(self._diagnostics_timer)
            self._diagnostics_timer = None
        for publisher in (self._scan_publisher, self._diagnostics_publisher):
            if publisher is not None:
                self.destroy_publisher(publisher)
        self._scan_publisher = self._diagnostics_publisher = None
        emulator, self._emulator = self._emulator, None
        if emulator is not None:
            await emulator.stop()
            self.get_logger().info("Stopped the built-in emulator")
        self._settings = None

    # -- the reader ---------------------------------------------------------------------
    async def _read(self, lidar: Lidar) -> None:
        """Turn the port's bytes into published scans until cancelled.

        The one task that touches the port. A lost port is reopened inside
        :meth:`Lidar.scans`; only the end of a capture or a bug ends it.
        """
        log = self.get_logger()
        try:
            async for scan in lidar.scans():
                self._on_scan(scan)
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            self._reader_error = exc
            log.error(f"Reading {lidar.port} failed: {type(exc).__name__}: {exc}")
            # Error processing closes everything; it must not run inside the
            # task it cancels, so it gets a task of its own.
            self._failing = asyncio.get_running_loop().create_task(self.fail(exc))
            return
        log.info(
            f"End of {lidar.port}: {lidar.stats.packets} packets, {self._scans} scans; "
            "nothing more to publish"
        )

    def _on_scan(self, scan: Scan) -> None:
        self._scans += 1
        publisher = self._scan_publisher
        settings = self._settings
        if publisher is None or settings is None or not publisher.is_activated:
            return
        publisher.publish(to_laser_scan(scan, frame_id=settings.frame_id))
        self._published += 1

    def _scan_publisher_topic(self) -> str:
        return self._scan_publisher.topic_name if self._scan_publisher is not None else "~/scan"

    def _reader_stopped_reason(self) -> str:
        if self._lidar is None:
            return "the port is not open"
        if self._reader_error is not None:
            return f"reading failed: {self._reader_error}"
        return f"{self._lidar.port} has ended"

    # -- diagnostics ------------------------------------------------------------------
    async def _publish_diagnostics(self) -> None:
        lidar, publisher, settings = self._lidar, self._diagnostics_publisher, self._settings
        if lidar is None or publisher is None or settings is None:
            return
        stats = lidar.stats
        last, now = self._counts, _Counts.now(lidar, self._scans)
        self._counts = now
        elapsed = max(now.when - last.when, 1e-6)
        packets = now.packets - last.packets
        scans = now.scans - last.scans
        active = self.lifecycle_state.label == "active"
        level, message = self._health(lidar, last, now)
        if level == DiagnosticStatus.OK:
            message += ", publishing" if active else ", not publishing (node inactive)"
        values = {
            "port": lidar.port,
            "emulated": "yes" if self._emulator is not None else "no",
            "baudrate": str(lidar.baudrate),
            "device state": lidar.state,
            "node state": self.lifecycle_state.label,
            "packet rate (Hz)": f"{packets / elapsed:.1f}",
            "scan rate (Hz)": f"{scans / elapsed:.2f}",
            "packets": str(stats.packets),
            "scans": str(self._scans),
            "scans published": str(self._published),
            "crc errors": str(stats.crc_errors),
            "resyncs": str(stats.resyncs),
            "skipped bytes": str(stats.skipped_bytes),
            "health frames": str(stats.health_frames),
            "last health code": "none" if stats.last_health_code is None else str(stats.last_health_code),
            "reconnects": str(lidar.reopens),
            "last error": lidar.last_error or "none",
        }
        status = DiagnosticStatus(
            level=level,
            name=f"{self.get_name()}: LiDAR",
            message=message,
            hardware_id=f"{settings.model.name} on {lidar.port}",
            values=[KeyValue(key=key, value=text) for key, text in values.items()],
        )
        array_msg = DiagnosticArray(status=[status])
        array_msg.header.stamp = self.get_clock().now().to_msg()
        publisher.publish(array_msg)

    def _health(self, lidar: Lidar, last: _Counts, now: _Counts) -> tuple[bytes, str]:
        """The level and one-line message of the period from *last* to *now*, worst first."""
        elapsed = now.when - last.when
        if self._reader is None or self._reader.done():
            level = DiagnosticStatus.ERROR if self._reader_error is not None else DiagnosticStatus.WARN
            return level, f"not reading: {self._reader_stopped_reason()}"
        if lidar.state == "reconnecting":
            return DiagnosticStatus.ERROR, (
                f"device lost ({lidar.last_error}); reopening, {lidar.reopens} reopen(s) so far"
            )
        if now.packets == last.packets:
            return DiagnosticStatus.ERROR, f"no data for {elapsed:.1f} s"
        if now.scans == last.scans:
            return DiagnosticStatus.WARN, "packets but no complete revolution (motor stopped?)"
        code = lidar.stats.last_health_code
        if now.health_frames > last.health_frames and code:
            return DiagnosticStatus.WARN, f"device reports health error code {code}"
        crc_errors = now.crc_errors - last.crc_errors
        skipped = now.skipped_bytes - last.skipped_bytes
        if crc_errors or skipped:
            return DiagnosticStatus.WARN, (
                f"line noise: {crc_errors} CRC error(s), {skipped} byte(s) skipped "
                f"in the last {elapsed:.1f} s"
            )
        return DiagnosticStatus.OK, "streaming"


def _device_error(exc: _errors.DeviceError) -> DeviceError:
    """The container's DeviceError for the core's, same device and reason."""
    reason = str(exc).removeprefix(f"{exc.device}: ")
    return DeviceError(reason, device=exc.device)


def _string(name: str, value: Any) -> str:
    if not isinstance(value, str) or not value.strip():
        raise _InvalidParameter(name, f"must be a non-empty string, not {value!r}")
    return value.strip()


def _integer(name: str, value: Any, *, minimum: int) -> int:
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        raise _InvalidParameter(name, f"must be an integer, not {value!r}")
    if value < minimum:
        raise _InvalidParameter(name, f"must be >= {minimum}, not {value}")
    return value


def _number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _InvalidParameter(name, f"must be a finite number, not {value!r}")
    return float(value)


def _boolean(name: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise _InvalidParameter(name, f"must be true or false, not {value!r}")
    return value


@hookimpl
def register_node_types(register: RegisterNodeType) -> None:
    """Register the LiDAR node as ``ldlidar::LdLidarNode``."""
    register(LdLidarNode)
