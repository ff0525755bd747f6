"""A long outage of valid packets, told in the log once when it starts and once when it ends.

``/diagnostics`` says every period whether valid packets arrive, but nobody
reads a topic after the fact: the log must tell that the scans stopped, why,
and for how long, without a line per period while they stay stopped (a 30 s
garbage flood used to leave no line at all). So an outage is logged when no
valid packet has been parsed for longer than a threshold (WARN: how long,
why, the byte rate) and when valid packets return (INFO: how long it
lasted). Any cause counts: silence, a lost device being reopened (whose own
``device lost`` and ``reconnected`` lines come too), bytes that form no
packet.

The check runs with each ``/diagnostics`` report, so a start or an end is
told up to one diagnostics period late, and an outage's duration is long by
at most that much. The threshold is ``diagnostics.outage_msec`` (5 s by
default; :mod:`ldlidar._settings` says why).
"""

from __future__ import annotations

from dataclasses import dataclass

from container import clip

from ._diagnostics import _Counts, byte_rate, why_no_packets
from ._lidar import Lidar

__all__ = ["OutageLog", "OutageNotice"]


@dataclass(frozen=True, slots=True)
class OutageNotice:
    """One log line about an outage.

    :param started: ``True`` for its start (log as WARN), ``False`` for its end (INFO).
    """

    started: bool
    message: str


class OutageLog:
    """Watch one open LiDAR's valid packets, report by report.

    :param lidar: the device, open (so it has parsed a valid packet).
    :param threshold: seconds without a valid packet that make an outage.
    """

    def __init__(self, lidar: Lidar, *, threshold: float) -> None:
        self._lidar = lidar
        self._threshold = threshold
        self._port = clip(lidar.port)
        #: Counters at the latest report that saw a valid packet: what rates
        #: and reasons during an outage are measured from.
        self._before: _Counts | None = None
        #: When the last valid packet before the outage being told was parsed.
        self._since: float | None = None

    @property
    def ongoing(self) -> bool:
        """Whether an outage was told to have started and not yet to have ended."""
        return self._since is not None

    def update(self, now: _Counts, *, reading: bool = True) -> OutageNotice | None:
        """Look at the counters of a report; return a line to log, if the outage starts or ends.

        :param reading: the port is still read; an outage does not start
            once reading has stopped (the end of a capture, a failure: told
            by lines of their own).
        """
        last_packet = self._lidar.packet_time
        if self._since is not None:
            if last_packet is not None and last_packet > self._since:
                lasted = now.when - self._since
                self._since = None
                self._before = now
                return OutageNotice(False, f"{self._port}: valid packets again after {lasted:.1f} s without one")
            return None
        if last_packet is None or now.when - last_packet <= self._threshold:
            if self._before is None or now.packets != self._before.packets:
                self._before = now
            return None
        if not reading:
            return None
        before = self._before or now
        self._since = last_packet
        return OutageNotice(
            True,
            f"{self._port}: no valid packet for {now.when - last_packet:.1f} s: {self._cause(before, now)}; "
            "the end of this outage will be logged",
        )

    def close(self, when: float) -> OutageNotice | None:
        """The port is being closed: end an ongoing outage, with how long it lasted."""
        if self._since is None:
            return None
        lasted, self._since = when - self._since, None
        return OutageNotice(False, f"{self._port}: closed after {lasted:.1f} s without a valid packet")

    def _cause(self, before: _Counts, now: _Counts) -> str:
        lidar = self._lidar
        if lidar.state == "reconnecting":
            return f"device lost ({clip(lidar.last_error or 'unknown')}), reopening"
        if now.bytes == before.bytes:
            return "no bytes arrive (is the LiDAR powered, and is this its port?)"
        return f"bytes arrive ({byte_rate(before, now)}) but {why_no_packets(lidar, before, now)}"
