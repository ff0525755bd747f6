"""The ``ldlidar::LdLidarNode`` lifecycle node: real rclpy, real DDS, real pseudo-terminals."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rcl_interfaces.msg import Log
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy
from sensor_msgs.msg import LaserScan

from container import AsyncioExecutor, PluginRegistry
from ldlidar import Emulator
from ldlidar.plugin import SCAN_QOS, LdLidarNode, find_serial_ports
from tests.container_support import REPO, ContainerProcess
from tests.ldlidar.node_support import ROSOUT_QOS, Recorder, lidar_parameters, logged
from tests.lifecycle_support import run
from tests.waiting import wait_until_async

EXAMPLE = REPO / "examples" / "lidar.yaml"


# -- helpers ---------------------------------------------------------------------------

def check_scan_fields(scans: list[LaserScan], *, bins: int = 455) -> None:
    for scan in scans:
        assert scan.header.frame_id == "ldlidar_link"
        assert len(scan.ranges) == bins == len(scan.intensities)
        span = scan.angle_max - scan.angle_min
        assert scan.angle_increment * (len(scan.ranges) - 1) == pytest.approx(span, rel=1e-5)
        # Ray i covers [-pi + i * 2pi/n, -pi + (i + 1) * 2pi/n); upright, ray 0 is measured last.
        assert scan.angle_min == pytest.approx(-math.pi + math.pi / bins)
        assert scan.scan_time == pytest.approx(0.1, abs=0.005)
        assert scan.time_increment == pytest.approx(-scan.scan_time / bins, rel=1e-3)
        assert (scan.range_min, scan.range_max) == pytest.approx((0.03, 15.0))
        finite = [r for r in scan.ranges if math.isfinite(r)]
        assert len(finite) > 0.8 * bins  # the emulated room has walls all round
    stamps = [s.header.stamp.sec + s.header.stamp.nanosec * 1e-9 for s in scans]
    steps = np.diff(stamps)
    assert np.all(steps > 0)
    assert np.all(np.abs(steps - 0.1) < 0.01), steps


# -- the plugin ------------------------------------------------------------------------------
def test_plugin_is_found_through_its_entry_point() -> None:
    registry = PluginRegistry()
    assert registry.types["ldlidar::LdLidarNode"].node_class is LdLidarNode
    assert not [f for f in registry.failures if f.distribution == "ldlidar"]
    out = subprocess.run(
        [sys.executable, "-m", "container", "types"], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert "ldlidar\n  ldlidar::LdLidarNode\n" in out.stdout


# -- the lifecycle -------------------------------------------------------------------------------
# Seconds of scans at 10 Hz.
@pytest.mark.slow
def test_full_lifecycle_streams_ten_hertz_and_deactivate_keeps_reading(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    observer = host(Node, "observer")
    scans = Recorder(observer, LaserScan, "/lidar/scan", SCAN_QOS)

    async def scenario() -> None:
        async with Emulator() as emu:
            node: LdLidarNode = host(LdLidarNode, "lidar", parameter_overrides=lidar_parameters(emu.link))
            assert await node.transition("configure")
            lidar = node.lidar
            assert lidar is not None and lidar.state == "open" and node.port == emu.link
            assert node.emulator is None
            await wait_until_async(lambda: scans.subscription.get_publisher_count() == 1, "the scan publisher")
            # Reading starts at configure, publishing only at activate.
            start = lidar.stats.packets
            await wait_until_async(lambda: lidar.stats.packets > start + 100, "packets while inactive")
            assert len(scans) == 0 and node.scans_published == 0

            assert await node.transition("activate")
            await wait_until_async(lambda: len(scans) >= 21, "21 scans", timeout=5)
            first = scans.since(0)[:21]
            rate = 20 / (first[-1].at - first[0].at)
            assert rate == pytest.approx(10.0, rel=0.15)
            check_scan_fields([r.msg for r in first])
            now = time.time()
            last = first[-1].msg.header.stamp
            assert 0 < now - (last.sec + last.nanosec * 1e-9) < 2.0  # a host-clock time, in the past

            assert await node.transition("deactivate")
            assert lidar.state == "open"
            mark = lidar.stats.packets
            # Anything published before the deactivation has landed by now.
            await wait_until_async(lambda: lidar.stats.packets > mark + 40, "packets after deactivate")
            held, published = len(scans), node.scans_published
            await wait_until_async(lambda: lidar.stats.packets > mark + 230, "half a second of packets")
            assert len(scans) == held and node.scans_published == published
            assert lidar.stats.crc_errors == 0

            assert await node.transition("activate")
            await wait_until_async(lambda: len(scans) >= held + 5, "scans after reactivation", timeout=5)
            check_scan_fields([r.msg for r in scans.since(held)][:5])

            assert await node.transition("deactivate")
            assert await node.transition("cleanup")
            assert node.lidar is None and lidar.closed
            await wait_until_async(lambda: scans.subscription.get_publisher_count() == 0, "the publisher to go")
            assert await node.transition("shutdown")
            assert node.lifecycle_state.label == "finalized"

    run(executor, scenario(), timeout=40)


def test_configure_fails_on_a_missing_port_and_can_be_retried(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    observer = host(Node, "observer")
    rosout = Recorder(observer, Log, "/rosout", ROSOUT_QOS)
    change = observer.create_client(ChangeState, "/nowhere/change_state")
    get = observer.create_client(GetState, "/nowhere/get_state")

    async def scenario() -> None:
        node: LdLidarNode = host(
            LdLidarNode, "nowhere", parameter_overrides=lidar_parameters("/dev/ttyUSB-does-not-exist")
        )
        await wait_until_async(lambda: change.service_is_ready() and get.service_is_ready(), "the lifecycle services")
        # Asked the way `ros2 lifecycle set` asks.
        response = await change.call_async(ChangeState.Request(transition=Transition(label="configure")))
        assert response.success is False
        state = await get.call_async(GetState.Request())
        assert state.current_state.label == "unconfigured"
        assert node.lidar is None and node.emulator is None  # an explicit port never falls back
        await wait_until_async(
            lambda: any(
                "'/dev/ttyUSB-does-not-exist': cannot open: No such file" in m for m in logged(rosout, "nowhere")
            ),
            "the logged reason",
        )
        async with Emulator() as emu:
            node.set_parameters(lidar_parameters(emu.link))
            assert await node.transition("configure")
            assert await node.transition("cleanup")

    run(executor, scenario())


@pytest.mark.parametrize(
    ("parameter", "value", "words"),
    [
        ("lidar.model", "LD99", "unknown LiDAR model 'LD99'"),
        ("lidar.rot_verse", "UP", "must be 'CW' or 'CCW'"),
        ("lidar.bins", -1, "must be >= 0"),
        ("lidar.range_max", 0.01, "must be above lidar.range_min"),
        ("comm.baudrate", "fast", "must be an integer"),
        ("comm.timeout_msec", 0, "must be positive"),
        ("comm.poll_msec", 100, "must be within [0, 30]"),
        ("lidar.frame_id", "", "non-empty string"),
        ("lidar.units", "MM", "only M (metres) is supported, not 'MM'"),
        ("topic_name", "scan", "remap it instead"),
        ("laser_scan_dir", "yes", "must be true or false"),
    ],
)
def test_configure_refuses_a_bad_parameter_naming_it(
    executor: AsyncioExecutor, host: Callable[..., Any], parameter: str, value: Any, words: str
) -> None:
    observer = host(Node, "observer")
    rosout = Recorder(observer, Log, "/rosout", ROSOUT_QOS)
    name = f"picky_{parameter.replace('.', '_')}"  # rcl keys /rosout by node name, process-wide

    async def scenario() -> None:
        node: LdLidarNode = host(
            LdLidarNode, name, parameter_overrides=[Parameter(parameter, value=value)]
        )
        assert not await node.transition("configure")
        assert node.lifecycle_state.label == "unconfigured"
        assert node.lidar is None and node.emulator is None  # refused before opening anything
        await wait_until_async(
            lambda: any(f"parameter {parameter!r}" in m and words in m for m in logged(rosout, name)),
            f"a log line naming {parameter}",
        )

    run(executor, scenario())


def test_angle_crop_outside_a_turn_is_refused(executor: AsyncioExecutor, host: Callable[..., Any]) -> None:
    async def scenario() -> None:
        node: LdLidarNode = host(
            LdLidarNode,
            "cropped",
            parameter_overrides=lidar_parameters(
                "/dev/unused", lidar__enable_angle_crop=True, lidar__angle_crop_min=400
            ),
        )
        assert not await node.transition("configure")

    run(executor, scenario())


def test_configure_times_out_on_a_silent_port(executor: AsyncioExecutor, host: Callable[..., Any]) -> None:
    master, slave = os.openpty()
    observer = host(Node, "observer")
    rosout = Recorder(observer, Log, "/rosout", ROSOUT_QOS)

    async def scenario() -> float:
        node: LdLidarNode = host(
            LdLidarNode,
            "silent",
            parameter_overrides=lidar_parameters(os.ttyname(slave), comm__timeout_msec=300),
        )
        began = time.monotonic()
        assert not await node.transition("configure")
        elapsed = time.monotonic() - began
        assert node.lifecycle_state.label == "unconfigured" and node.lidar is None
        assert openers(os.ttyname(slave)) == 1  # the test's own: the node closed its port
        await wait_until_async(
            lambda: any("silent: not one byte within 0.3 s" in m for m in logged(rosout, "silent")),
            "the reason, which is not a wrong baud rate",
        )
        return elapsed

    try:
        elapsed = run(executor, scenario())
    finally:
        os.close(master)
        os.close(slave)
    assert 0.3 <= elapsed < 2.0


def openers(path: str) -> int:
    """File descriptors of this process open on ``path``."""
    count = 0
    for fd in os.listdir("/proc/self/fd"):
        try:
            count += os.readlink(f"/proc/self/fd/{fd}") == path
        except OSError:
            continue
    return count


def test_configure_cut_short_by_transition_timeout_leaves_the_port_closed(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    master, slave = os.openpty()
    path = os.ttyname(slave)

    async def scenario() -> None:
        node: LdLidarNode = host(
            LdLidarNode,
            "hasty",
            parameter_overrides=[
                *lidar_parameters(path, comm__timeout_msec=5000),
                Parameter("transition_timeout", value=0.3),
            ],
        )
        assert openers(path) == 1  # the test's own
        assert not await node.transition("configure")
        assert node.lifecycle_state.label == "unconfigured" and node.lidar is None
        assert openers(path) == 1

    try:
        run(executor, scenario())
    finally:
        os.close(master)
        os.close(slave)


def test_auto_without_a_device_runs_the_emulator_until_cleanup(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    class Unplugged(LdLidarNode):
        auto_port_patterns = ()

    observer = host(Node, "observer")
    diagnostics = Recorder(observer, DiagnosticArray, "/diagnostics", 10)

    def statuses() -> list[DiagnosticStatus]:
        return [s for a in diagnostics.messages() for s in a.status if s.name == "auto_emu: LiDAR"]

    async def scenario() -> None:
        node: LdLidarNode = host(Unplugged, "auto_emu")
        assert await node.transition("configure")
        emulator = node.emulator
        assert emulator is not None
        running = emulator.state
        assert node.port == emulator.link and os.path.exists(emulator.link)
        assert await node.transition("activate")
        await wait_until_async(lambda: node.scans_published >= 3, "scans from the emulator")
        # Simulated scans are never OK: a robot must not mistake them for its surroundings.
        await wait_until_async(
            lambda: any("publishing" in s.message for s in statuses()), "an active status", timeout=5
        )
        active = [s for s in statuses() if s.message.endswith(", publishing")]
        assert active and all(s.level == DiagnosticStatus.WARN and "simulated" in s.message for s in active)
        assert await node.transition("deactivate")
        assert await node.transition("cleanup")
        assert running == "running" and emulator.state == "closed" and node.emulator is None
        assert not os.path.lexists(emulator.link)

    run(executor, scenario())


def test_auto_prefers_an_attached_device(executor: AsyncioExecutor, host: Callable[..., Any]) -> None:
    async def scenario() -> None:
        async with Emulator() as emu:

            class Attached(LdLidarNode):
                auto_port_patterns = ("/dev/no-such-lidar*", emu.link)

            node: LdLidarNode = host(Attached, "auto_dev")
            assert await node.transition("configure")
            assert node.port == emu.link and node.emulator is None
            assert await node.transition("cleanup")

    assert find_serial_ports(("/dev/no-such-lidar*",)) == []
    run(executor, scenario())


# -- migration from other drivers ----------------------------------------------------------------
def test_a_vendor_parameter_file_is_taken_with_notices_and_unknown_names_are_reported(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    """ldlidar_stl_ros2's names mean ours (each with a notice); a typo is never silently ignored."""
    observer = host(Node, "observer")
    rosout = Recorder(observer, Log, "/rosout", ROSOUT_QOS)

    async def scenario() -> None:
        async with Emulator() as emu:
            vendor = {
                "product_name": "LDLiDAR_LD06",
                "port_name": emu.link,
                "port_baudrate": 230400,
                "frame_id": "base_laser",
                "laser_scan_dir": False,
                "enable_angle_crop_func": True,
                "angle_crop_min": 135.0,
                "angle_crop_max": 225.0,
                "lidar.bin": 360,  # a typo of ours
                "general.debug_mode": True,
            }
            node: LdLidarNode = host(
                LdLidarNode, "migrated", parameter_overrides=[Parameter(k, value=v) for k, v in vendor.items()]
            )
            assert await node.transition("configure")
            assert node.port == emu.link
            values = {name: node.get_parameter(name).value for name in ("lidar.frame_id", "lidar.rot_verse")}
            assert values == {"lidar.frame_id": "base_laser", "lidar.rot_verse": "CW"}
            assert node.get_parameter("lidar.enable_angle_crop").value is True
            await wait_until_async(
                lambda: any("Unknown parameter 'lidar.bin'" in m for m in logged(rosout, "migrated")),
                "the unknown parameter reported",
            )
            lines = logged(rosout, "migrated")
            for old, ours in (("port_name", "comm.serial_port"), ("laser_scan_dir", "lidar.rot_verse")):
                assert f"Parameter {old!r} (vendor driver) is deprecated: use {ours!r}" in lines
            assert any("did you mean 'lidar.bins'?" in m for m in lines)
            assert await node.transition("activate")
            # general.debug_mode (the community driver's) is honoured: a debug line per revolution.
            await wait_until_async(
                lambda: any(m.startswith("scan ") for m in logged(rosout, "migrated")), "debug lines"
            )
            assert await node.transition("deactivate")
            assert await node.transition("cleanup")

    run(executor, scenario())


def test_scan_qos_is_overridden_the_ros_way(executor: AsyncioExecutor, host: Callable[..., Any]) -> None:
    observer = host(Node, "observer")

    async def scenario() -> None:
        async with Emulator() as emu:
            node: LdLidarNode = host(
                LdLidarNode,
                "besteffort",
                parameter_overrides=[
                    *lidar_parameters(emu.link),
                    Parameter("qos_overrides./besteffort/scan.publisher.reliability", value="best_effort"),
                    Parameter("qos_overrides./besteffort/scan.publisher.depth", value=3),
                ],
            )
            assert await node.transition("configure")
            await wait_until_async(
                lambda: bool(observer.get_publishers_info_by_topic("/besteffort/scan")), "the publisher"
            )
            [info] = observer.get_publishers_info_by_topic("/besteffort/scan")
            assert info.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
            assert node.get_parameter("qos_overrides./besteffort/scan.publisher.depth").value == 3
            assert await node.transition("cleanup")
            bad: LdLidarNode = host(
                LdLidarNode,
                "badqos",
                parameter_overrides=[
                    *lidar_parameters(emu.link),
                    Parameter("qos_overrides./badqos/scan.publisher.reliability", value="sometimes"),
                ],
            )
            assert not await bad.transition("configure")
            assert bad.lidar is None and bad.lifecycle_state.label == "unconfigured"

    run(executor, scenario())


def test_publish_when_subscribed_builds_scans_only_for_a_listener(
    executor: AsyncioExecutor, host: Callable[..., Any]
) -> None:
    observer = host(Node, "observer")

    async def scenario() -> None:
        async with Emulator() as emu:
            node: LdLidarNode = host(
                LdLidarNode,
                "lazy",
                parameter_overrides=lidar_parameters(emu.link, general__publish_when_subscribed=True),
            )
            assert await node.transition("configure")
            assert await node.transition("activate")
            lidar = node.lidar
            assert lidar is not None
            mark = lidar.stats.packets
            await wait_until_async(lambda: lidar.stats.packets > mark + 200, "half a second of packets")
            assert node.scans_published == 0
            scans = Recorder(observer, LaserScan, "/lazy/scan", SCAN_QOS)
            await wait_until_async(lambda: len(scans) >= 3, "scans once someone listens")
            assert await node.transition("deactivate")
            assert await node.transition("cleanup")

    run(executor, scenario())


# -- trouble while active ----------------------------------------------------------------------
# Seconds of scans around an unplug and the reopen.
@pytest.mark.slow
@pytest.mark.parametrize("poll_msec", [1, 30], ids=["polled-1ms", "polled-30ms"])
def test_unplug_while_active_reports_an_error_then_resumes(
    executor: AsyncioExecutor, host: Callable[..., Any], poll_msec: int
) -> None:
    observer = host(Node, "observer")
    scans = Recorder(observer, LaserScan, "/plugged/scan", SCAN_QOS)
    diagnostics = Recorder(observer, DiagnosticArray, "/diagnostics", 10)
    rosout = Recorder(observer, Log, "/rosout", ROSOUT_QOS)

    def warnings() -> list[str]:
        return [m.msg for m in rosout.messages() if m.name == "plugged" and m.level == Log.WARN]

    def statuses() -> list[DiagnosticStatus]:
        return [s for a in diagnostics.messages() for s in a.status if s.name == "plugged: LiDAR"]

    async def scenario() -> None:
        async with Emulator() as emu:
            node: LdLidarNode = host(
                LdLidarNode,
                "plugged",
                parameter_overrides=lidar_parameters(emu.link, comm__timeout_msec=500, comm__poll_msec=poll_msec),
            )
            assert await node.transition("configure")
            await wait_until_async(lambda: scans.subscription.get_publisher_count() == 1, "the scan publisher")
            assert await node.transition("activate")
            await wait_until_async(lambda: len(scans) >= 3, "scans before the unplug")
            assert node.reconnects == 0

            await emu.unplug()
            lidar = node.lidar
            assert lidar is not None
            await wait_until_async(lambda: lidar.state == "reconnecting", "the node to notice")
            seen = len(statuses())
            await wait_until_async(
                lambda: any(s.level == DiagnosticStatus.ERROR for s in statuses()[seen:]),
                "an ERROR diagnostic while unplugged",
                timeout=5,
            )
            held = len(scans)
            await emu.replug()
            await wait_until_async(lambda: node.reconnects == 1, "the reopen", timeout=5)
            await wait_until_async(lambda: len(scans) >= held + 5, "scans after the replug", timeout=5)
            check_scan_fields([r.msg for r in scans.since(held)][1:5])
            assert lidar.state == "open"
            seen = len(statuses())
            await wait_until_async(
                lambda: any(
                    s.level == DiagnosticStatus.OK
                    and dict((v.key, v.value) for v in s.values)["reconnects"] == "1"
                    and dict((v.key, v.value) for v in s.values)["last error"] == "none"
                    for s in statuses()[seen:]
                ),
                "an OK diagnostic counting the reconnect, the error cleared",
                timeout=5,
            )
            # Never only on /diagnostics: the log says it too.
            await wait_until_async(lambda: any("reconnected after" in m for m in warnings()), "a WARN on reconnecting")
            assert any("device lost (port" in m for m in warnings()), warnings()
            assert await node.transition("deactivate")
            assert await node.transition("cleanup")

    run(executor, scenario(), timeout=40)


def test_a_reader_failure_while_active_goes_through_error_processing(
    executor: AsyncioExecutor, host: Callable[..., Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    async def scenario() -> None:
        async with Emulator() as emu:
            node: LdLidarNode = host(LdLidarNode, "fragile", parameter_overrides=lidar_parameters(emu.link))
            assert await node.transition("configure")
            assert await node.transition("activate")
            await wait_until_async(lambda: node.scans_published >= 2, "scans")
            lidar = node.lidar
            assert lidar is not None

            def boom(scan: Any) -> None:
                raise RuntimeError("injected")

            monkeypatch.setattr(node, "_on_scan", boom)
            await wait_until_async(lambda: node.lifecycle_state.label == "unconfigured", "error processing")
            assert lidar.closed and node.lidar is None
            monkeypatch.undo()
            assert await node.transition("configure")  # recovered: the node can start over
            assert await node.transition("cleanup")

    run(executor, scenario())


# Rates measured over seconds of scans.
@pytest.mark.slow
def test_diagnostics_report_rates_and_state(executor: AsyncioExecutor, host: Callable[..., Any]) -> None:
    observer = host(Node, "observer")
    diagnostics = Recorder(observer, DiagnosticArray, "/diagnostics", 10)

    def values_of(level: bytes, words: str) -> list[dict[str, str]]:
        return [
            {v.key: v.value for v in s.values}
            for a in diagnostics.messages()
            for s in a.status
            if s.name == "healthy: LiDAR" and s.level == level and words in s.message
        ]

    async def scenario() -> None:
        async with Emulator() as emu:
            node: LdLidarNode = host(LdLidarNode, "healthy", parameter_overrides=lidar_parameters(emu.link))
            assert await node.transition("configure")
            await wait_until_async(
                lambda: len(values_of(DiagnosticStatus.OK, "not publishing (node inactive)")) >= 2,
                "diagnostics while inactive",
                timeout=5,
            )
            assert await node.transition("activate")
            await wait_until_async(
                lambda: len(values_of(DiagnosticStatus.OK, "streaming, publishing")) >= 2,
                "diagnostics while active",
                timeout=5,
            )
            values = values_of(DiagnosticStatus.OK, "streaming, publishing")[-1]
            assert float(values["packet rate (Hz)"]) == pytest.approx(375, rel=0.15)
            assert float(values["scan rate (Hz)"]) == pytest.approx(10, rel=0.25)
            assert values["port"] == emu.link and values["emulated"] == "no"
            assert values["crc errors"] == values["reconnects"] == "0"
            assert int(values["scans published"]) > 0

            emu.inject_garbage(300, seed=3)
            emu.inject(b"\x54\x2c" + bytes(45))  # a data packet's header, then a bad CRC
            await wait_until_async(
                lambda: bool(values_of(DiagnosticStatus.WARN, "line noise")), "a WARN for line noise", timeout=5
            )
            warned = values_of(DiagnosticStatus.WARN, "line noise")[-1]
            assert int(warned["skipped bytes"]) >= 347 and int(warned["resyncs"]) >= 1
            assert int(warned["crc errors"]) >= 1
            assert await node.transition("deactivate")
            assert await node.transition("cleanup")

    run(executor, scenario(), timeout=30)


# A 3 s window of scans.
@pytest.mark.slow
def test_blocking_neighbour_does_not_delay_scans(executor: AsyncioExecutor, host: Callable[..., Any]) -> None:
    """A plain callback that blocks for 1 s, in the same container, costs the LiDAR nothing."""
    observer = host(Node, "observer")
    scans = Recorder(observer, LaserScan, "/steady/scan", SCAN_QOS)
    blocker = host(Node, "blocker")
    blocks: list[tuple[float, float]] = []

    def block() -> None:
        began = time.monotonic()
        time.sleep(1.0)
        blocks.append((began, time.monotonic()))

    async def scenario() -> tuple[float, float]:
        async with Emulator() as emu:
            node: LdLidarNode = host(LdLidarNode, "steady", parameter_overrides=lidar_parameters(emu.link))
            assert await node.transition("configure")
            await wait_until_async(lambda: scans.subscription.get_publisher_count() == 1, "the scan publisher")
            assert await node.transition("activate")
            await wait_until_async(lambda: len(scans) >= 2, "the first scans")
            blocker.create_timer(0.05, block)
            await wait_until_async(lambda: len(blocks) >= 1, "the first blocking callback", timeout=5)
            window_start = blocks[0][0]
            await wait_until_async(lambda: time.monotonic() > window_start + 3.0, "a 3 s window", timeout=6)
            window_end = time.monotonic()
            assert await node.transition("deactivate")
            assert await node.transition("cleanup")
            return window_start, window_end

    window_start, window_end = run(executor, scenario(), timeout=30)
    inside = [r.at for r in scans.since(0) if window_start <= r.at <= window_end]
    completed = [b for b in blocks if b[1] <= window_end]
    assert len(completed) >= 2, blocks
    assert all(end - began >= 0.99 for began, end in completed)
    gaps = np.diff([window_start, *inside, window_end])
    assert len(inside) >= 25
    assert gaps.max() < 0.25, f"largest gap {gaps.max() * 1000:.0f} ms"


# -- across processes and from a capture --------------------------------------------------------
# A container process and a listener process.
@pytest.mark.slow
def test_container_run_example_streams_scans_to_another_process(
    run_container: Callable[..., ContainerProcess],
    executor: AsyncioExecutor,
    host: Callable[..., Any],
) -> None:
    if find_serial_ports():
        pytest.skip("a serial device is attached: 'auto' would use it instead of the emulator")
    proc = run_container(EXAMPLE.read_text(encoding="utf-8"))
    proc.wait_for_line("started the built-in LD06 emulator")
    observer = host(Node, "remote_observer")
    scans = Recorder(observer, LaserScan, "/ldlidar/scan", 10)

    async def scenario() -> None:
        await wait_until_async(lambda: len(scans) >= 26, "26 scans from the container process", timeout=20)

    run(executor, scenario(), timeout=30)
    # The last 21: over the first few revolutions the device-to-host clock
    # mapping settles, and a first step 11 ms short was measured once in CI.
    received = [r.msg for r in scans.since(0)][-21:]
    check_scan_fields(received)
    # The scans' own stamps: receipt times in this process carry DDS's
    # delivery (the first scans after discovery can arrive together: 12.5 Hz
    # measured once that way in CI).
    stamps = [s.header.stamp.sec + s.header.stamp.nanosec * 1e-9 for s in received]
    assert 20 / (stamps[-1] - stamps[0]) == pytest.approx(10.0, rel=0.15)
    code = proc.stop()
    output = "\n".join(proc.lines)
    assert code == 0, output
    assert "Unloaded '/ldlidar'" in output and "Stopped the built-in emulator" in output
    assert "threads left behind" not in output


# A container process, and its load read over a few seconds.
@pytest.mark.slow
@pytest.mark.timeout(120)  # a container's start-up, the emulator's, then four windows of 1 s
def test_the_examples_lidar_node_is_credited_its_reading_and_parsing(
    run_container: Callable[..., ContainerProcess],
    executor: AsyncioExecutor,
    host: Callable[..., Any],
) -> None:
    """``container top`` on the README's first command: ``/ldlidar`` reads the emulator's
    pseudo-terminal (a reader on the loop), parses in its own asyncio task and runs its emulator
    in a thread of its own, all of it its own CPU, not the executor's."""
    from lifecycle_container_interfaces.msg import ContainerLoad

    if find_serial_ports():
        pytest.skip("a serial device is attached: 'auto' would use it instead of the emulator")
    proc = run_container(EXAMPLE.read_text(encoding="utf-8"))
    proc.wait_for_line("started the built-in LD06 emulator")
    loads = Recorder(host(Node, "top_observer"), ContainerLoad, "/ComponentManager/load", 5)

    async def scenario() -> None:
        await wait_until_async(lambda: len(loads) >= 4, "four windows of the container's load", timeout=20)

    run(executor, scenario(), timeout=30)
    lidar = [next(node for node in load.nodes if node.name == "/ldlidar") for load in loads.messages()[-3:]]
    cpu = sum(node.cpu for node in lidar) / len(lidar)
    rows = {c.kind: c for c in lidar[-1].callbacks}
    assert cpu > 0.005, [(c.kind, c.cpu) for c in lidar[-1].callbacks]
    assert rows["task"].cpu_seconds_total > 0, "its parsing, in the task it reads in"
    assert rows["fd"].runs_total > 0 and rows["loop_timer"].runs_total > 0, "its reads: the port's reader, its polls"
    if "thread" in rows:  # Python 3.12 on: its emulator's writer thread
        assert rows["thread"].cpu_seconds_total > 0
    assert proc.stop() == 0, proc.output()


# Replays seconds of a real capture at the device's pace.
@pytest.mark.slow
@pytest.mark.shared
def test_replay_of_a_real_capture_through_the_node(
    executor: AsyncioExecutor, host: Callable[..., Any], capture: Path
) -> None:
    observer = host(Node, "observer")
    scans = Recorder(observer, LaserScan, "/replay/scan", SCAN_QOS)

    async def scenario() -> int:
        node: LdLidarNode = host(LdLidarNode, "replay", parameter_overrides=lidar_parameters(f"file://{capture}"))
        assert await node.transition("configure")
        await wait_until_async(lambda: scans.subscription.get_publisher_count() == 1, "the scan publisher")
        assert await node.transition("activate")
        lidar = node.lidar
        assert lidar is not None
        await wait_until_async(lambda: lidar.closed, "the end of the capture", timeout=10)  # 2.3 s of device time
        assert lidar.stats.packets == 863 and lidar.stats.crc_errors == 0
        published = node.scans_published
        await wait_until_async(lambda: len(scans) == published, "every published scan")
        assert await node.transition("deactivate")
        assert await node.transition("cleanup")
        return published

    published = run(executor, scenario(), timeout=30)
    assert published >= 15  # about 23 revolutions, less what went by before activation
    messages = scans.messages()
    for msg in messages:
        assert len(msg.ranges) == 455
        assert msg.scan_time == pytest.approx(0.1, abs=0.01)  # 3588..3613 deg/s
        assert sum(math.isfinite(r) for r in msg.ranges) > 300
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in messages]
    # Replayed at the device's pace: stamps step by scan_time (line rate made that 77 ms for 100 ms).
    steps = np.diff(stamps)
    assert np.all(steps > 0)
    assert steps == pytest.approx([m.scan_time for m in messages[1:]], rel=0.03)
