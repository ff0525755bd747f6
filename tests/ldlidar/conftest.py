"""Fixtures for the ldlidar plugin's tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.ldlidar.ldlidar_support import CAPTURE


@pytest.fixture
def capture() -> Path:
    """The real LD06 capture (863 valid packets), or a skip when absent."""
    if not CAPTURE.is_file():
        pytest.skip(f"real capture not available at {CAPTURE}")
    return CAPTURE
