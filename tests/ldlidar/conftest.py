"""Fixtures for the ldlidar plugin's tests."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from container.devices import DEFAULT_SERIAL_PATTERNS, DevicePolicy, set_device_policy
from tests.container_support import SHARED
from tests.ldlidar.ldlidar_support import CAPTURE


@pytest.fixture
def capture() -> Path:
    """The real LD06 capture (863 valid packets), or a skip when absent."""
    if not CAPTURE.is_file():
        pytest.skip(f"real capture not available at {CAPTURE}")
    return CAPTURE


@pytest.fixture(autouse=True)
def device_policy_for_tests() -> Iterator[DevicePolicy]:
    """Let the LiDAR node open what the tests give it: emulators' pseudo-terminals,
    through their links under the temporary directory (named explicitly:
    ``/dev/pts/*``), and captures there and in ``../shared``; the default
    policy allows neither (only a node's own emulator's pty)."""
    policy = DevicePolicy(
        serial=(*DEFAULT_SERIAL_PATTERNS, "/dev/pts/*"),
        replay_dirs=(Path(tempfile.gettempdir()).resolve(), SHARED.resolve()),
        origin="the tests' device policy",
    )
    previous = set_device_policy(policy)
    yield policy
    set_device_policy(previous)
