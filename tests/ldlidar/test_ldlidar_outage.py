"""A LiDAR sending nothing valid: ``/diagnostics`` says what arrives, the log tells the outage twice.

The node reads a real pseudo-terminal. The test writes to it, paced in real
time, what a device sends (an LD06's packets) and then what a faulty line or
device sends instead (random bytes, packets whose angles are impossible, or
nothing), and listens as any ROS user would: a ``/diagnostics`` subscriber
and a ``/rosout`` one. Short ``diagnostics.*`` periods keep it fast.
"""

from __future__ import annotations

import os
import re
import statistics
import threading
import time
import tty
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import Log
from rclpy.node import Node

from container import AsyncioExecutor
from ldlidar import PacketGenerator, crc8
from ldlidar.plugin import LdLidarNode
from tests.ldlidar.node_support import ROSOUT_QOS, Recorder, lidar_parameters
from tests.lifecycle_support import run
from tests.waiting import wait_until_async

Mode = Literal["packets", "garbage", "impossible", "silence"]

#: Bytes per second of the random-bytes flood (an LD06 sends 17,625).
GARBAGE_RATE = 20_000
#: An LD06's packets per second, each 47 bytes.
PACKET_RATE = 375 * 47
PERIOD_S = 0.2
OUTAGE_S = 0.6


class Line:
    """A pseudo-terminal, and a thread writing to it what :attr:`mode` says, paced in real time.

    The device behind it keeps turning whatever the line carries: its
    packets are made at its rate in every mode, and sent, corrupted or lost.
    """

    TICK_S = 0.02

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.port = os.ttyname(self.slave)
        self.mode: Mode = "packets"
        self.dropped = 0
        self._generator = PacketGenerator("LD06")
        self._rng = np.random.default_rng(7)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._write, name="test-line", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        os.close(self.master)
        os.close(self.slave)

    def _write(self) -> None:
        begin = last = time.monotonic()
        owed = 0.0
        while not self._stop.wait(self.TICK_S):
            now = time.monotonic()
            due = int((now - begin) * self._generator.model.packets_per_second) - self._generator.count
            rows = self._generator.rows(max(due, 0))
            mode = self.mode
            if mode == "garbage":
                owed += GARBAGE_RATE * (now - last)
                data = self._rng.integers(0, 256, int(owed), dtype=np.uint8).tobytes()
                owed -= len(data)
            else:
                owed = 0.0
                data = b"" if mode == "silence" else (impossible(rows) if mode == "impossible" else rows.tobytes())
            last = now
            try:
                written = os.write(self.master, data) if data else 0
            except BlockingIOError:
                written = 0
            self.dropped += len(data) - written


def impossible(rows: np.ndarray[Any, Any]) -> bytes:
    """The packets with a start angle past a full turn and a valid CRC: what a faulty device sends."""
    out = rows.copy()
    out[:, 4:6] = 0xFF
    for row in out:
        row[46] = crc8(row[:46].tobytes())
    return out.tobytes()


@pytest.fixture
def line() -> Any:
    opened = Line()
    yield opened
    opened.close()


@pytest.mark.parametrize(
    ("cause", "rate", "status", "start"),
    [
        (
            "garbage", GARBAGE_RATE,
            "bytes but no valid packet for", r"bytes arrive \((?P<rate>[\d.]+) kB/s\) but no packet header in them",
        ),
        (
            "impossible", PACKET_RATE,
            "bytes but no valid packet for",
            r"bytes arrive \((?P<rate>[\d.]+) kB/s\) but packets with a valid CRC but impossible angles",
        ),
        ("silence", 0, "no bytes for", r"no bytes arrive"),
    ],
)  # fmt: skip
def test_an_outage_is_on_diagnostics_every_period_and_logged_when_it_starts_and_ends(
    executor: AsyncioExecutor, host: Callable[..., Any], line: Line, cause: Mode, rate: int, status: str, start: str
) -> None:
    name = f"outage_{cause}"
    observer = host(Node, "observer")
    diagnostics = Recorder(observer, DiagnosticArray, "/diagnostics", 50)
    rosout = Recorder(observer, Log, "/rosout", ROSOUT_QOS)

    def statuses() -> list[DiagnosticStatus]:
        return [s for a in diagnostics.messages() for s in a.status if s.name == f"{name}: LiDAR"]

    def logged(level: int, words: str) -> list[str]:
        return [m.msg for m in rosout.messages() if m.name == name and m.level == level and words in m.msg]

    async def scenario() -> None:
        node: LdLidarNode = host(
            LdLidarNode,
            name,
            parameter_overrides=lidar_parameters(
                line.port,
                comm__timeout_msec=30_000,  # no reopening here: silence stays silence
                diagnostics__period_msec=round(PERIOD_S * 1000),
                diagnostics__outage_msec=round(OUTAGE_S * 1000),
            ),
        )
        assert await node.transition("configure")
        await wait_until_async(
            lambda: any(s.level == DiagnosticStatus.OK for s in statuses()), "an OK report while packets arrive"
        )

        line.mode = cause
        began = time.monotonic()
        seen = len(statuses())
        # Every period of the outage says so: ERROR, with the byte rate and the reason.
        await wait_until_async(
            lambda: len([s for s in statuses()[seen:] if s.message.startswith(status)]) >= 5,
            lambda: f"five ERROR reports saying {status!r}; got {[s.message for s in statuses()[seen:]]}",
        )
        failing = [s for s in statuses()[seen:] if s.message.startswith(status)]
        assert all(s.level == DiagnosticStatus.ERROR for s in failing)
        rates = [float({v.key: v.value for v in s.values}["byte rate (B/s)"]) for s in failing]
        if rate:
            assert statistics.median(rates) == pytest.approx(rate, rel=0.35), rates
            reason = "no packet header" if cause == "garbage" else "impossible angles"
            assert all(reason in s.message for s in failing), [s.message for s in failing]
        else:
            assert rates == [0.0] * len(rates)

        # The log: one WARN when the outage passes its threshold, however many periods it lasts.
        await wait_until_async(lambda: logged(Log.WARN, "no valid packet for"), "the outage's start in the log")
        held = len(statuses())
        await wait_until_async(lambda: len(statuses()) >= held + 3, "three more periods of outage")
        [warned] = logged(Log.WARN, "no valid packet for")
        found = re.search(start, warned)
        assert found is not None, warned
        if rate:
            assert float(found["rate"]) * 1000 == pytest.approx(rate, rel=0.35), warned

        line.mode = "packets"
        lasted = time.monotonic() - began
        await wait_until_async(lambda: logged(Log.INFO, "valid packets again after"), "the outage's end in the log")
        [ended] = logged(Log.INFO, "valid packets again after")
        told = float(re.findall(r"after ([\d.]+) s", ended)[0])
        # From the last valid packet parsed (late on a busy machine) to the report that saw the next ones.
        assert lasted - 0.5 <= told <= lasted + PERIOD_S + 0.8, (lasted, ended)
        seen = len(statuses())
        await wait_until_async(lambda: any(s.level == DiagnosticStatus.OK for s in statuses()[seen:]), "OK again")
        assert len(logged(Log.WARN, "no valid packet for")) == 1
        assert len(logged(Log.INFO, "valid packets again")) == 1
        assert await node.transition("cleanup")
        assert not logged(Log.INFO, "without a valid packet")  # no outage was left to end at cleanup

    run(executor, scenario(), timeout=40)


def test_cleanup_during_an_outage_ends_it_in_the_log(
    executor: AsyncioExecutor, host: Callable[..., Any], line: Line
) -> None:
    observer = host(Node, "observer")
    rosout = Recorder(observer, Log, "/rosout", ROSOUT_QOS)

    def logged(words: str) -> list[str]:
        return [m.msg for m in rosout.messages() if m.name == "cut" and words in m.msg]

    async def scenario() -> None:
        node: LdLidarNode = host(
            LdLidarNode,
            "cut",
            parameter_overrides=lidar_parameters(
                line.port, comm__timeout_msec=30_000, diagnostics__period_msec=100, diagnostics__outage_msec=300
            ),
        )
        assert await node.transition("configure")
        line.mode = "garbage"
        await wait_until_async(lambda: logged("no valid packet for"), "the outage's start in the log")
        assert await node.transition("cleanup")
        await wait_until_async(lambda: logged("closed after"), "the outage's end at cleanup")
        assert re.search(r"closed after [\d.]+ s without a valid packet$", logged("closed after")[0])

    run(executor, scenario())
