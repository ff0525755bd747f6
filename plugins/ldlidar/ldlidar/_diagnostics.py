"""The node's ``/diagnostics`` status: rates over the last period and one health verdict.

Rates and the verdict cover the period since the previous report, not the
whole run: a burst of line noise warns once and then clears, and a device
that stops sending turns ERROR within one period however long it ran well.

A period without a valid packet says which of two faults it is, since they
call for different fixes: no bytes at all (power, cable, the wrong port) or
bytes that form no valid packet, with their rate and what the parser made
of them (packets failing their CRC, packets with impossible angles, no
packet header at all: see :func:`why_no_packets`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Final

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from container import clip

from ._lidar import Lidar
from ._protocol import PACKET_SIZE

__all__ = ["DIAGNOSTICS_PERIOD", "Diagnostics", "byte_rate", "why_no_packets"]

#: Seconds between two ``/diagnostics`` messages unless ``diagnostics.period_msec`` says otherwise.
DIAGNOSTICS_PERIOD: Final = 1.0


@dataclass(frozen=True, slots=True)
class _Counts:
    """Counters at one diagnostics message; the next one reports the difference."""

    when: float
    packets: int = 0
    bytes: int = 0
    scans: int = 0
    crc_errors: int = 0
    implausible: int = 0
    skipped_bytes: int = 0
    health_frames: int = 0

    @classmethod
    def now(cls, lidar: Lidar, scans: int) -> _Counts:
        stats = lidar.stats
        return cls(
            when=time.monotonic(),
            packets=stats.packets,
            bytes=lidar.bytes_read,
            scans=scans,
            crc_errors=stats.crc_errors,
            implausible=stats.implausible,
            skipped_bytes=stats.skipped_bytes,
            health_frames=stats.health_frames,
        )


class Diagnostics:
    """The ``/diagnostics`` status of one open LiDAR, one period at a time.

    :param lidar: the device, open; its counters are the baseline of the first period.
    :param node_name: the node's name, which names the status.
    :param emulated: the device is the node's own emulator: the level is
        then WARN at best and the message says "simulated".
    """

    def __init__(self, lidar: Lidar, *, node_name: str, emulated: bool) -> None:
        self._lidar = lidar
        self._name = f"{node_name}: LiDAR"
        self._emulated = emulated
        self._counts = _Counts.now(lidar, 0)

    @property
    def counts(self) -> _Counts:
        """The counters at the latest report (at creation, before the first)."""
        return self._counts

    def report(
        self,
        *,
        stamp: Time,
        node_state: str,
        scans: int,
        published: int,
        stopped: str | None = None,
        failed: bool = False,
    ) -> DiagnosticArray:
        """Return the status of the period since the previous report, and start the next.

        :param stamp: the time of the message.
        :param node_state: the node's lifecycle state label; only ``active`` publishes.
        :param scans: revolutions assembled since configure.
        :param published: revolutions published since configure.
        :param stopped: why the port is no longer read, or ``None`` while it is.
        :param failed: reading stopped on an error rather than at the end of a capture.
        """
        lidar, stats = self._lidar, self._lidar.stats
        last, now = self._counts, _Counts.now(lidar, scans)
        self._counts = now
        elapsed = max(now.when - last.when, 1e-6)
        level, message = _health(lidar, last, now, stopped=stopped, failed=failed)
        if level == DiagnosticStatus.OK and self._emulated:
            # Never OK: a robot must not take simulated scans for its surroundings.
            level, message = DiagnosticStatus.WARN, "simulated: no LiDAR found, scans come from the built-in emulator"
        if level == DiagnosticStatus.OK or self._emulated:
            message += ", publishing" if node_state == "active" else ", not publishing (node inactive)"
        port = clip(lidar.port)
        values = {
            "port": port,
            "emulated": "yes" if self._emulated else "no",
            "baudrate": str(lidar.baudrate),
            "device state": lidar.state,
            "node state": node_state,
            "packet rate (Hz)": f"{(now.packets - last.packets) / elapsed:.1f}",
            "byte rate (B/s)": f"{(now.bytes - last.bytes) / elapsed:.0f}",
            "scan rate (Hz)": f"{(now.scans - last.scans) / elapsed:.2f}",
            "packets": str(stats.packets),
            "bytes": str(lidar.bytes_read),
            "scans": str(scans),
            "scans published": str(published),
            "crc errors": str(stats.crc_errors),
            "implausible packets": str(stats.implausible),
            "resyncs": str(stats.resyncs),
            "skipped bytes": str(stats.skipped_bytes),
            "health frames": str(stats.health_frames),
            "last health code": "none" if stats.last_health_code is None else str(stats.last_health_code),
            "reconnects": str(lidar.reopens),
            "stalls": str(lidar.stalls),
            "device clock jumps": str(lidar.assembler.clock.jumps),
            "last error": clip(lidar.last_error or "none"),
        }
        status = DiagnosticStatus(
            level=level,
            name=self._name,
            message=message,
            hardware_id=f"{lidar.model.name} on {port}",
            values=[KeyValue(key=key, value=text) for key, text in values.items()],
        )
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = stamp
        return msg


def _health(lidar: Lidar, last: _Counts, now: _Counts, *, stopped: str | None, failed: bool) -> tuple[bytes, str]:
    """The level and one-line message of the period from *last* to *now*, worst first."""
    elapsed = now.when - last.when
    if stopped is not None:
        return (DiagnosticStatus.ERROR if failed else DiagnosticStatus.WARN), f"not reading: {stopped}"
    if lidar.state == "reconnecting":
        return DiagnosticStatus.ERROR, (
            f"device lost ({clip(lidar.last_error or 'unknown')}); reopening, {lidar.reopens} reopen(s) so far"
        )
    if now.packets == last.packets:
        if now.bytes == last.bytes:
            return DiagnosticStatus.ERROR, f"no bytes for {elapsed:.1f} s"
        return DiagnosticStatus.ERROR, (
            f"bytes but no valid packet for {elapsed:.1f} s: {byte_rate(last, now)}, {why_no_packets(lidar, last, now)}"
        )
    if now.scans == last.scans:
        return DiagnosticStatus.WARN, "packets but no complete revolution (motor stopped?)"
    code = lidar.stats.last_health_code
    if now.health_frames > last.health_frames and code:
        return DiagnosticStatus.WARN, f"device reports health error code {code}"
    implausible = now.implausible - last.implausible
    if implausible:
        # A valid CRC over impossible content is the device's doing, not the line's.
        return DiagnosticStatus.WARN, (
            f"device fault: {implausible} packet(s) with a valid CRC but impossible angles "
            f"in the last {elapsed:.1f} s"
        )
    crc_errors = now.crc_errors - last.crc_errors
    skipped = now.skipped_bytes - last.skipped_bytes
    if crc_errors or skipped:
        return DiagnosticStatus.WARN, (
            f"line noise: {crc_errors} CRC error(s), {skipped} byte(s) skipped in the last {elapsed:.1f} s"
        )
    return DiagnosticStatus.OK, "streaming"


def byte_rate(last: _Counts, now: _Counts) -> str:
    """The rate bytes arrived at from *last* to *now*, for a person: ``23.4 kB/s``, ``120 B/s``."""
    rate = (now.bytes - last.bytes) / max(now.when - last.when, 1e-6)
    return f"{rate / 1000:.1f} kB/s" if rate >= 1000 else f"{rate:.0f} B/s"


def why_no_packets(lidar: Lidar, last: _Counts, now: _Counts) -> str:
    """What the parser made of bytes that held no valid packet, from *last* to *now*, likeliest cause first.

    A valid CRC over impossible angles is the device's doing (random bytes
    pass both checks about once in 200 million); packet windows failing
    their CRC, when they account for most of the bytes, are line noise or a
    wrong baud rate; bytes with no packet header at all are a wrong baud
    rate or another device. (Random bytes hold a data packet's two-byte
    header once in 65,536, so a few CRC failures among many bytes do not
    make noise the cause.)
    """
    received = now.bytes - last.bytes
    implausible = now.implausible - last.implausible
    crc_errors = now.crc_errors - last.crc_errors
    health = now.health_frames - last.health_frames
    counts = f"{crc_errors} failed CRC, {implausible} with impossible angles"
    if implausible:
        return f"packets with a valid CRC but impossible angles: a device fault ({counts})"
    if health:
        code = lidar.stats.last_health_code
        return f"{health} health frame(s), last error code {code}, and no data packet ({counts})"
    if crc_errors * PACKET_SIZE * 2 >= received:
        return f"packets failing their CRC: line noise or a wrong baud rate ({counts})"
    return (
        f"no packet header in them: a wrong baud rate (reading at {lidar.baudrate}) or not an LD-series LiDAR "
        f"({counts})"
    )
