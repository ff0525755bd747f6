"""Draw a scan as a PNG, seen from above, front up, with NumPy and zlib only."""

from __future__ import annotations

import math
import struct
import zlib

import numpy as np
from numpy.typing import NDArray

from ._scan import Scan

__all__ = ["encode_png", "render_scan"]

_BACKGROUND = (255, 255, 255)
_GRID = (225, 225, 225)
_AXIS = (170, 170, 170)
_POINT = (20, 60, 200)
_SENSOR = (220, 30, 30)


def encode_png(image: NDArray[np.uint8]) -> bytes:
    """Return PNG bytes for an ``(h, w, 3)`` RGB image."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"need an (h, w, 3) uint8 image, got {image.shape} {image.dtype}")
    height, width, _ = image.shape
    raw = np.zeros((height, 1 + 3 * width), dtype=np.uint8)
    raw[:, 1:] = image.reshape(height, -1)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
        + chunk(b"IEND", b"")
    )


def render_scan(scan: Scan, *, size: int = 800, extent: float | None = None) -> NDArray[np.uint8]:
    """Return an ``(size, size, 3)`` image of *scan*: x (front) up, y (left) left.

    :param extent: metres from the centre to the image edge; fitted to the
        farthest finite reading if not given. Grid rings are 1 m apart.
    """
    finite = np.isfinite(scan.ranges) & (scan.ranges > 0)
    ranges = scan.ranges[finite].astype(np.float64)
    angles = scan.angles[finite]
    if extent is None:
        extent = max(float(ranges.max()) * 1.1, 1.0) if len(ranges) else 5.0
    scale = (size / 2 - 4) / extent
    image = np.empty((size, size, 3), dtype=np.uint8)
    image[:] = _BACKGROUND
    centre = size / 2

    rows, cols = np.mgrid[0:size, 0:size]
    radius = np.hypot(rows - centre, cols - centre) / scale
    for ring in range(1, math.ceil(extent) + 1):
        image[np.abs(radius - ring) < 0.6 / scale] = _GRID
    mid = int(centre)
    image[mid, :] = _AXIS
    image[:, mid] = _AXIS

    x = ranges * np.cos(angles)
    y = ranges * np.sin(angles)
    r = np.rint(centre - x * scale).astype(np.int64)
    c = np.rint(centre - y * scale).astype(np.int64)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            rr, cc = r + dr, c + dc
            inside = (rr >= 0) & (rr < size) & (cc >= 0) & (cc < size)
            image[rr[inside], cc[inside]] = _POINT

    # The sensor: a dot, and a short line towards its front (+x, up).
    image[mid - 3 : mid + 4, mid - 3 : mid + 4] = _SENSOR
    image[max(mid - int(0.3 * scale), 0) : mid, mid - 1 : mid + 2] = _SENSOR
    return image
