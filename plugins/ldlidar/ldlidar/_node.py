"""The ``ldlidar::LdLidarNode`` lifecycle node: its transitions and the task that reads the port.

The port is read by one asyncio task on the executor's event loop, from
``configure`` to ``cleanup``, whatever the node's state: a deactivated node
stops publishing but keeps reading, so the parser and the device clock stay
in sync and activating again publishes the very next revolution.

Nothing is silently ignored: parameters of the vendor driver are translated
(with a notice naming ours) or refused, any other override the node does not
know is reported at configure, and the device's troubles (lost, reconnected,
stalled, its clock jumping) are logged as warnings, not only counted on
``/diagnostics``.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Sequence
from typing import Any, Final

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.lifecycle import LifecyclePublisher, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSPolicyKind, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import InvalidQosOverridesError, QoSOverridingOptions
from rclpy.timer import Timer
from sensor_msgs.msg import LaserScan

from container import ConfigError, DeviceError, LifecycleNode, Throttle, clip
from container.devices import DevicePolicy, PortRefused, device_policy

from ._diagnostics import Diagnostics
from ._emulator import Emulator
from ._lidar import EventKind, Lidar
from ._messages import to_laser_scan
from ._outage import OutageLog
from ._ports import AUTO_PORT_PATTERNS, find_serial_ports
from ._protocol import Model
from ._scan import Scan
from ._settings import PARAMETERS, Settings, migrate, read_settings

__all__ = ["SCAN_QOS", "SCAN_QOS_OVERRIDES", "LdLidarNode"]

SUCCESS = TransitionCallbackReturn.SUCCESS
FAILURE = TransitionCallbackReturn.FAILURE

#: QoS of ``~/scan`` unless overridden. Reliable: rviz2's LaserScan display
#: subscribes reliable by default and would never match a best-effort
#: publisher, while a best-effort (SensorData) subscriber such as
#: slam_toolbox's still matches.
SCAN_QOS: Final = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)

#: QoS policies of ``~/scan`` that parameters override the ROS way:
#: ``qos_overrides./ldlidar/scan.publisher.reliability: best_effort`` (read
#: when the publisher is created, at configure).
SCAN_QOS_OVERRIDES: Final = (
    QoSPolicyKind.HISTORY,
    QoSPolicyKind.DEPTH,
    QoSPolicyKind.RELIABILITY,
    QoSPolicyKind.DURABILITY,
)

#: rcutils' DEBUG severity (what ``general.debug_mode`` sets the node's logger to).
_DEBUG: Final = 10

#: First reopen attempt after this many seconds; then doubling up to the max.
_REOPEN_INTERVAL: Final = 0.1
_REOPEN_MAX_INTERVAL: Final = 2.0

#: Events that can repeat many times a second (a device whose clock keeps
#: jumping) are logged at most this often per kind, with a count; the port's
#: losses and reconnections are state changes, always logged.
_EVENT_LOG_PERIOD: Final = 10.0
_THROTTLED_EVENTS: Final = frozenset({"clock_jump", "stalled"})

#: Characters of a device event's line: its port and its reason (an OS or
#: pyserial error may echo the port, which a peer chose), clipped beyond.
_EVENT_LIMIT: Final = 800


class LdLidarNode(LifecycleNode):
    """An LDRobot LD06 / LD19 / STL-27L LiDAR publishing ``~/scan`` while active.

    See :mod:`ldlidar.plugin` for parameters and topics. ``configure`` opens
    the port and waits up to ``comm.timeout_msec`` for a valid packet;
    ``activate`` starts publishing; ``deactivate`` stops publishing and keeps
    reading; ``cleanup``, ``shutdown`` and error processing close the port
    (and stop the emulator if this node started it).
    """

    default_node_name = "ldlidar"

    #: Where ``comm.serial_port: auto`` looks; a subclass may narrow it.
    auto_port_patterns: Sequence[str] = AUTO_PORT_PATTERNS

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        # Other drivers' names become ours before rclpy sees the overrides:
        # rclpy would keep them unread, and say nothing.
        given: Sequence[Parameter[Any]] = kwargs.get("parameter_overrides") or ()
        migration = migrate((p.name, p.value) for p in given)
        kwargs["parameter_overrides"] = [Parameter(name, value=value) for name, value in migration.values.items()]
        self._migration_notices = tuple(migration.notices)
        self._refused = tuple(migration.refused)
        super().__init__(node_name, **kwargs)
        for name, default, description in PARAMETERS:
            # Dynamic typing: a YAML "15" for a float is fine, and any wrong
            # type is refused by configure with the parameter's name rather
            # than by the constructor with rclpy's generic type error.
            self.declare_parameter(
                name, default, ParameterDescriptor(description=description, dynamic_typing=True)
            )
        self._settings: Settings | None = None
        self._lidar: Lidar | None = None
        self._emulator: Emulator | None = None
        self._reader: asyncio.Task[None] | None = None
        self._reader_error: BaseException | None = None
        self._failing: asyncio.Task[str] | None = None
        self._scan_publisher: LifecyclePublisher[Any] | None = None
        self._diagnostics_publisher: Publisher[Any] | None = None
        self._diagnostics_timer: Timer | None = None
        self._diagnostics: Diagnostics | None = None
        self._outage: OutageLog | None = None
        self._scans = 0
        self._published = 0
        self._message: LaserScan | None = None
        # The diagnostics count every device event; the log gets a readable rate.
        self._events = Throttle(self.get_logger().warning, period=_EVENT_LOG_PERIOD)

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
        for notice in self._migration_notices:
            log.warning(notice)
        try:
            if self._refused:
                raise self._refused[0]
            settings = read_settings(lambda name: self.get_parameter(name).value)
        except ConfigError as exc:
            return self.fail_transition(f"Cannot configure: {exc}")
        if settings.debug:
            log.set_level(_DEBUG)
        try:
            await self._start(settings)
        except (DeviceError, ConfigError) as exc:
            await self._release()
            # The reason reaches whoever asked (a load with autostart answers with it).
            return self.fail_transition(f"Cannot configure: {exc}")
        except BaseException:
            # Timed out (cancelled) or a bug: leave nothing open behind.
            await self._release()
            raise
        assert self._lidar is not None
        log.info(
            f"Configured: {settings.model.name} on {clip(self._lidar.port)} at {self._lidar.baudrate} "
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
    async def _start(self, settings: Settings) -> None:
        """Open the device, create the publishers, start the reader.

        :raises DeviceError: the port (or the emulator) could not be opened,
            or sent no valid packet in time. Whatever was opened stays
            recorded on the node, for :meth:`_release` to close.
        """
        port = settings.port
        # A parameter may come from any peer that can load a node: the
        # container's device policy (the operator's) says what it may name,
        # here and at every open the Lidar makes, reopens included.
        policy = device_policy()
        if port.lower() == "auto":
            port = await self._auto_port(settings.model)
            if self._emulator is not None:
                # Our own emulator's pty, whatever the operator's patterns
                # say of pseudo-terminals; no other pty.
                policy = policy.with_own_devices(self._emulator.owns)
        else:
            policy.check_port(port)
        lidar = Lidar(
            port,
            model=settings.model,
            baudrate=settings.baudrate,
            bins=settings.bins,
            direction=settings.direction,
            range_min=settings.range_min,
            range_max=settings.range_max,
            crop=settings.crop,
            noise_filter=settings.noise_filter,
            poll_interval=settings.poll_interval,
            timeout=settings.timeout,
            reopen=True,
            reopen_interval=_REOPEN_INTERVAL,
            reopen_max_interval=_REOPEN_MAX_INTERVAL,
            on_event=self._device_event,
            policy=policy,
        )
        await lidar.open()
        self._settings = settings
        self._lidar = lidar
        self._scans = self._published = 0
        self._reader_error = None
        self._diagnostics = Diagnostics(lidar, node_name=self.get_name(), emulated=self._emulator is not None)
        self._outage = OutageLog(lidar, threshold=settings.outage)
        self._scan_publisher = self._create_scan_publisher()
        self._diagnostics_publisher = self.create_publisher(
            DiagnosticArray, "/diagnostics", 10, managed=False
        )
        self._diagnostics_timer = self.create_timer(
            settings.diagnostics_period, self._publish_diagnostics, managed=False
        )
        self._reader = asyncio.get_running_loop().create_task(
            self._read(lidar), name=f"ldlidar-reader:{self.get_fully_qualified_name()}"
        )

    def _create_scan_publisher(self) -> LifecyclePublisher[Any]:
        """``~/scan`` with :data:`SCAN_QOS`, its policies overridable by ``qos_overrides.*`` parameters.

        :raises ConfigError: an override names an impossible policy value.
        """
        qos = QoSProfile(
            history=SCAN_QOS.history,
            depth=SCAN_QOS.depth,
            reliability=SCAN_QOS.reliability,
            durability=SCAN_QOS.durability,
        )
        options = QoSOverridingOptions(SCAN_QOS_OVERRIDES)
        try:
            return self.create_lifecycle_publisher(LaserScan, "~/scan", qos, qos_overriding_options=options)
        except (InvalidQosOverridesError, RuntimeError, ValueError) as exc:
            # rclpy names the policy and value: "Unexpected QoS override for policy `reliability`: `x`".
            raise ConfigError(str(exc), source=f"qos_overrides.{self.resolve_topic_name('~/scan')}") from None

    def _device_event(self, kind: EventKind, message: str) -> None:
        message = clip(message, limit=_EVENT_LIMIT)
        if kind in _THROTTLED_EVENTS:
            self._events(kind, message)
        else:
            self.get_logger().warning(message)

    async def _auto_port(self, model: Model) -> str:
        """The first attached device, or the port of a freshly started emulator.

        :raises DeviceError: no pseudo-terminal for the emulator.
        """
        policy = device_policy()
        found = [port for port in find_serial_ports(self.auto_port_patterns) if _allowed(policy, port)]
        if found:
            self.get_logger().info(f"comm.serial_port 'auto': using {found[0]} (found {', '.join(found)})")
            return found[0]
        emulator = Emulator(model=model)
        self._emulator = emulator
        await emulator.start()
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
        self._diagnostics = None
        outage, self._outage = self._outage, None
        notice = outage.close(time.monotonic()) if outage is not None else None
        if notice is not None:
            self.get_logger().info(notice.message)
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
            log.error(f"Reading {clip(lidar.port)} failed: {type(exc).__name__}: {clip(str(exc), limit=_EVENT_LIMIT)}")
            # Error processing closes everything; it must not run inside the
            # task it cancels, so it gets a task of its own.
            self._failing = asyncio.get_running_loop().create_task(self.fail(exc))
            return
        log.info(
            f"End of {clip(lidar.port)}: {lidar.stats.packets} packets, {self._scans} scans; "
            "nothing more to publish"
        )

    def _on_scan(self, scan: Scan) -> None:
        self._scans += 1
        publisher = self._scan_publisher
        settings = self._settings
        if publisher is None or settings is None or not publisher.is_activated:
            return
        if settings.publish_when_subscribed and not publisher.get_subscription_count():
            return
        self._message = to_laser_scan(scan, frame_id=settings.frame_id, into=self._message)
        publisher.publish(self._message)
        self._published += 1
        if settings.debug:
            self.get_logger().debug(
                f"scan {self._scans}: {len(scan.ranges)} rays from {scan.points} points, "
                f"stamp {scan.stamp:.6f}, scan_time {scan.scan_time * 1000:.2f} ms"
            )

    def _scan_publisher_topic(self) -> str:
        return self._scan_publisher.topic_name if self._scan_publisher is not None else "~/scan"

    def _reader_stopped_reason(self) -> str:
        if self._lidar is None:
            return "the port is not open"
        if self._reader_error is not None:
            return f"reading failed: {clip(str(self._reader_error), limit=_EVENT_LIMIT)}"
        return f"{clip(self._lidar.port)} has ended"

    async def _publish_diagnostics(self) -> None:
        diagnostics, publisher = self._diagnostics, self._diagnostics_publisher
        if diagnostics is None or publisher is None:
            return
        reading = self._reader is not None and not self._reader.done()
        publisher.publish(
            diagnostics.report(
                stamp=self.get_clock().now().to_msg(),
                node_state=self.lifecycle_state.label,
                scans=self._scans,
                published=self._published,
                stopped=None if reading else self._reader_stopped_reason(),
                failed=self._reader_error is not None,
            )
        )
        # The log hears of a long outage twice, when it starts and when it ends, never once a period.
        notice = self._outage.update(diagnostics.counts, reading=reading) if self._outage is not None else None
        if notice is None:
            return
        # Two call sites: rclpy refuses one call site logging at two severities.
        if notice.started:
            self.get_logger().warning(notice.message)
        else:
            self.get_logger().info(notice.message)


def _allowed(policy: DevicePolicy, port: str) -> bool:
    try:
        policy.check_port(port)
    except PortRefused:
        return False
    return True
