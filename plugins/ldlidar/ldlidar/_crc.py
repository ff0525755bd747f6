"""The CRC-8 of data packets with NumPy: per-position tables, and the check of a few packets at once.

The CRC is linear over GF(2): the CRC of bytes 0..45 of a packet is the XOR
of one table lookup per byte, at the row of the byte's position. The
streaming parser checks the packets of a clean read with :func:`crc_ok`;
the bulk decoder builds its byte-pair tables from :func:`position_tables`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ._protocol import CRC_TABLE, PACKET_SIZE

if TYPE_CHECKING:
    # Only for annotations: importing numpy.typing costs start-up time.
    from numpy.typing import NDArray

__all__ = ["crc_ok", "position_tables"]

#: Rows of :func:`position_tables`: the packet's 47 bytes and a byte past it.
_ROWS = PACKET_SIZE + 1


def position_tables() -> NDArray[np.uint8]:
    """Return the ``(48, 256)`` CRC contribution of each byte value at each position of a packet.

    The CRC of bytes 0..45 is the XOR of rows 0..45 looked up at each byte.
    Row 46 is the CRC byte itself, row 47 zero.
    """
    table = np.array(CRC_TABLE, dtype=np.uint8)
    single = np.zeros((_ROWS, 256), dtype=np.uint8)
    cur = np.arange(256, dtype=np.uint8)
    single[PACKET_SIZE - 1] = cur
    for i in range(PACKET_SIZE - 2, -1, -1):
        cur = table[cur]
        single[i] = cur
    return single


_BYTE_TABLE: NDArray[np.uint8] | None = None
_BYTE_BASE = (np.arange(PACKET_SIZE - 1, dtype=np.intp) << 8)


def crc_ok(rows: NDArray[np.uint8]) -> NDArray[np.bool_]:
    """Return which of the ``(n, 47)`` rows carry a correct CRC.

    For a handful of packets at a time (the streaming parser's fast path):
    one gather from the per-byte tables (12 KB, which stay in cache between
    revolutions, unlike the bulk decoder's 1.5 MB pair tables), whatever
    the number of rows.
    """
    global _BYTE_TABLE
    if _BYTE_TABLE is None:
        _BYTE_TABLE = position_tables()[: PACKET_SIZE - 1].ravel()
    crc = np.bitwise_xor.reduce(_BYTE_TABLE.take(rows[:, : PACKET_SIZE - 1] + _BYTE_BASE), axis=1)
    ok: NDArray[np.bool_] = crc == rows[:, PACKET_SIZE - 1]
    return ok
