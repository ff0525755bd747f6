"""The ``/diagnostics`` status, period by period, without a node or a device."""

from __future__ import annotations

import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus

from ldlidar import Lidar
from ldlidar._diagnostics import Diagnostics, _Counts, _health

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR

#: One second of a healthy LD06: 375 packets, 10 revolutions.
LAST = _Counts(when=10.0, packets=1000, scans=30)
NOW = _Counts(when=11.0, packets=1375, scans=40)


def lidar() -> Lidar:
    """A device that is never opened: its counters and state are set by hand."""
    return Lidar("/dev/ttyUSB9", model="LD06")


def test_a_streaming_device_is_ok() -> None:
    assert _health(lidar(), LAST, NOW, stopped=None, failed=False) == (OK, "streaming")


def test_silence_is_an_error() -> None:
    silent = _Counts(when=11.5, packets=1000, scans=30)
    assert _health(lidar(), LAST, silent, stopped=None, failed=False) == (ERROR, "no data for 1.5 s")


def test_packets_without_a_revolution_warn_of_the_motor() -> None:
    stalled = _Counts(when=11.0, packets=1375, scans=30)
    level, message = _health(lidar(), LAST, stalled, stopped=None, failed=False)
    assert level == WARN and "motor stopped?" in message


def test_a_health_frame_with_an_error_code_warns() -> None:
    device = lidar()
    device.stats.last_health_code = 3
    now = _Counts(when=11.0, packets=1375, scans=40, health_frames=1)
    assert _health(device, LAST, now, stopped=None, failed=False) == (WARN, "device reports health error code 3")


def test_line_noise_warns_for_one_period_only() -> None:
    noisy = _Counts(when=11.0, packets=1375, scans=40, crc_errors=2, skipped_bytes=300)
    level, message = _health(lidar(), LAST, noisy, stopped=None, failed=False)
    assert (level, message) == (WARN, "line noise: 2 CRC error(s), 300 byte(s) skipped in the last 1.0 s")
    quiet = _Counts(when=12.0, packets=1750, scans=50, crc_errors=2, skipped_bytes=300)
    assert _health(lidar(), noisy, quiet, stopped=None, failed=False) == (OK, "streaming")


def test_a_lost_device_is_an_error_while_it_is_reopened() -> None:
    device = lidar()
    device.state, device.last_error, device.reopens = "reconnecting", "port closed", 2
    level, message = _health(device, LAST, NOW, stopped=None, failed=False)
    assert (level, message) == (ERROR, "device lost (port closed); reopening, 2 reopen(s) so far")


@pytest.mark.parametrize(("failed", "level"), [(True, ERROR), (False, WARN)], ids=["failed", "ended"])
def test_a_stopped_reader_outranks_everything(failed: bool, level: bytes) -> None:
    device = lidar()
    device.state = "reconnecting"
    assert _health(device, LAST, NOW, stopped="why", failed=failed) == (level, "not reading: why")


def test_report_names_the_node_and_device_and_says_whether_it_publishes() -> None:
    device = lidar()
    diagnostics = Diagnostics(device, node_name="front", emulated=False)
    device.stats.packets += 375

    inactive = diagnostics.report(stamp=Time(sec=7), node_state="inactive", scans=10, published=0)
    [status] = inactive.status
    values = {v.key: v.value for v in status.values}
    assert inactive.header.stamp.sec == 7
    assert (status.name, status.hardware_id) == ("front: LiDAR", "LD06 on /dev/ttyUSB9")
    assert (status.level, status.message) == (OK, "streaming, not publishing (node inactive)")
    assert values["emulated"] == "no" and values["node state"] == "inactive"
    assert (values["packets"], values["scans"], values["scans published"]) == ("375", "10", "0")
    assert float(values["packet rate (Hz)"]) > 0

    device.stats.packets += 375
    [status] = diagnostics.report(stamp=Time(sec=8), node_state="active", scans=20, published=10).status
    assert (status.level, status.message) == (OK, "streaming, publishing")

    [status] = diagnostics.report(stamp=Time(sec=9), node_state="active", scans=20, published=10).status
    assert status.level == ERROR and status.message.startswith("no data for")


def test_simulated_scans_are_never_ok() -> None:
    """``comm.serial_port: auto`` fell back to the emulator: WARN, and the message says so."""
    device = lidar()
    diagnostics = Diagnostics(device, node_name="front", emulated=True)
    device.stats.packets += 375
    [status] = diagnostics.report(stamp=Time(sec=7), node_state="active", scans=10, published=10).status
    assert status.level == WARN
    assert status.message == "simulated: no LiDAR found, scans come from the built-in emulator, publishing"
    assert {v.key: v.value for v in status.values}["emulated"] == "yes"


def test_recovery_clears_the_last_error() -> None:
    """Only while the device is being reopened is there a last error to show."""
    device = lidar()
    diagnostics = Diagnostics(device, node_name="front", emulated=False)
    device.state, device.last_error = "reconnecting", "port closed"
    [status] = diagnostics.report(stamp=Time(sec=7), node_state="active", scans=0, published=0).status
    assert {v.key: v.value for v in status.values}["last error"] == "port closed"
    device.state, device.last_error, device.reopens = "open", None, 1  # what a reopen leaves
    device.stats.packets += 375
    [status] = diagnostics.report(stamp=Time(sec=8), node_state="active", scans=10, published=10).status
    values = {v.key: v.value for v in status.values}
    assert status.level == OK and values["last error"] == "none" and values["reconnects"] == "1"


def test_packets_with_a_valid_crc_but_impossible_angles_are_a_device_fault_not_line_noise() -> None:
    faulty = _Counts(when=11.0, packets=1375, scans=40, implausible=5, skipped_bytes=235)
    level, message = _health(lidar(), LAST, faulty, stopped=None, failed=False)
    assert (level, message) == (
        WARN, "device fault: 5 packet(s) with a valid CRC but impossible angles in the last 1.0 s"
    )
