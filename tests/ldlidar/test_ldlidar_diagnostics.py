"""The ``/diagnostics`` status, period by period, without a node or a device."""

from __future__ import annotations

import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus

from ldlidar import Lidar
from ldlidar._diagnostics import Diagnostics, _Counts, _health, byte_rate
from ldlidar._outage import OutageLog

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
    assert _health(lidar(), LAST, silent, stopped=None, failed=False) == (ERROR, "no bytes for 1.5 s")


def test_bytes_without_a_packet_header_are_told_from_silence() -> None:
    """A wrong baud rate or another device: bytes at a rate, and never a header."""
    garbled = _Counts(when=11.0, packets=1000, scans=30, bytes=23_400, crc_errors=1, skipped_bytes=23_400)
    level, message = _health(lidar(), LAST, garbled, stopped=None, failed=False)
    assert level == ERROR
    assert message == (
        "bytes but no valid packet for 1.0 s: 23.4 kB/s, no packet header in them: a wrong baud rate "
        "(reading at 230400) or not an LD-series LiDAR (1 failed CRC, 0 with impossible angles)"
    )


def test_bytes_failing_their_crc_are_line_noise() -> None:
    noisy = _Counts(when=11.0, packets=1000, scans=30, bytes=17_625, crc_errors=375)
    level, message = _health(lidar(), LAST, noisy, stopped=None, failed=False)
    assert level == ERROR and "17.6 kB/s, packets failing their CRC: line noise or a wrong baud rate" in message


def test_packets_with_impossible_angles_and_no_valid_one_are_a_device_fault() -> None:
    faulty = _Counts(when=12.0, packets=1000, scans=30, bytes=35_250, implausible=750)
    level, message = _health(lidar(), LAST, faulty, stopped=None, failed=False)
    assert level == ERROR
    assert message == (
        "bytes but no valid packet for 2.0 s: 17.6 kB/s, packets with a valid CRC but impossible angles: "
        "a device fault (0 failed CRC, 750 with impossible angles)"
    )


def test_byte_rates_read_as_a_person_would_say_them() -> None:
    assert byte_rate(LAST, _Counts(when=11.0, bytes=120)) == "120 B/s"
    assert byte_rate(LAST, _Counts(when=12.0, bytes=46_900)) == "23.4 kB/s"


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
    assert status.level == ERROR and status.message.startswith("no bytes for")
    values = {v.key: v.value for v in status.values}
    assert (values["bytes"], values["byte rate (B/s)"]) == ("0", "0")


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


# -- outages in the log ---------------------------------------------------------------------
def test_an_outage_is_told_once_when_it_starts_and_once_when_it_ends() -> None:
    device = lidar()
    device.packet_time = 10.0
    log = OutageLog(device, threshold=5.0)
    assert log.update(_Counts(when=10.0, packets=1000, bytes=47_000)) is None
    # Bytes keep coming, none valid: nothing until the threshold, then one line.
    assert log.update(_Counts(when=14.0, packets=1000, bytes=127_000)) is None
    started = log.update(_Counts(when=15.5, packets=1000, bytes=157_000, crc_errors=2))
    assert started is not None and started.started
    assert started.message == (
        "/dev/ttyUSB9: no valid packet for 5.5 s: bytes arrive (20.0 kB/s) but no packet header in them: "
        "a wrong baud rate (reading at 230400) or not an LD-series LiDAR (2 failed CRC, 0 with impossible angles); "
        "the end of this outage will be logged"
    )
    for second in range(16, 40):
        assert log.update(_Counts(when=float(second), packets=1000, bytes=second * 20_000)) is None
    device.packet_time = 40.2
    ended = log.update(_Counts(when=40.5, packets=1010, bytes=900_000))
    assert ended is not None and not ended.started and not log.ongoing
    assert ended.message == "/dev/ttyUSB9: valid packets again after 30.5 s without one"
    assert log.update(_Counts(when=41.5, packets=1385, bytes=917_625)) is None


def test_a_silent_or_lost_device_is_an_outage_with_its_cause() -> None:
    device = lidar()
    device.packet_time = 10.0
    log = OutageLog(device, threshold=5.0)
    assert log.update(_Counts(when=10.0, packets=1000, bytes=47_000)) is None
    silent = log.update(_Counts(when=16.0, packets=1000, bytes=47_000))
    assert silent is not None and "no valid packet for 6.0 s: no bytes arrive" in silent.message

    device = lidar()
    device.packet_time = 10.0
    device.state, device.last_error = "reconnecting", "/dev/ttyUSB9: port closed (device unplugged?)"
    log = OutageLog(device, threshold=5.0)
    lost = log.update(_Counts(when=16.0, packets=1000))
    assert lost is not None and "device lost (/dev/ttyUSB9: port closed (device unplugged?)), reopening" in lost.message


def test_no_outage_starts_once_reading_has_stopped_and_closing_ends_one() -> None:
    device = lidar()
    device.packet_time = 10.0
    log = OutageLog(device, threshold=5.0)
    assert log.update(_Counts(when=20.0, packets=1000), reading=False) is None
    assert log.close(21.0) is None
    assert log.update(_Counts(when=20.0, packets=1000)) is not None
    closed = log.close(23.0)
    assert closed is not None and not closed.started
    assert closed.message == "/dev/ttyUSB9: closed after 13.0 s without a valid packet"
