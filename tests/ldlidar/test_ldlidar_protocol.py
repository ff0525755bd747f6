from __future__ import annotations

import pytest

from ldlidar import (
    MODELS,
    PACKET_SIZE,
    ProtocolError,
    crc8,
    decode_packet,
    encode_health,
    encode_info,
    encode_packet,
    get_model,
)
from ldlidar._protocol import CRC_TABLE

MANUAL = bytes.fromhex(
    "542C6808AB7EE000E4DC00E2D900E5D500E3D300E4D000E9CD00E4CA00"
    "E2C700E9C500E5C200E5C000E5BE823A1A50"
)


def test_manual_packet_decodes_to_documented_values() -> None:
    packet = decode_packet(MANUAL)
    assert packet.speed == 2152
    assert packet.start_deg == pytest.approx(324.27)
    assert packet.end_deg == pytest.approx(334.70)
    assert packet.timestamp == 6714
    assert packet.crc == 0x50
    assert packet.distances[0] == 0xE0 and packet.intensities[0] == 0xE4


def test_crc_table_is_poly_0x4d() -> None:
    assert CRC_TABLE[1] == 0x4D
    assert CRC_TABLE[0] == 0
    assert len(set(CRC_TABLE)) == 256
    assert crc8(MANUAL[:-1]) == 0x50
    assert crc8(MANUAL) == 0  # a message followed by its CRC checks to zero


def test_crc_can_run_in_pieces() -> None:
    assert crc8(MANUAL[20:-1], crc=crc8(MANUAL[:20])) == 0x50


def test_encode_reproduces_the_manual_packet() -> None:
    packet = decode_packet(MANUAL)
    assert (
        encode_packet(
            speed=packet.speed,
            start_angle=packet.start_angle,
            end_angle=packet.end_angle,
            timestamp=packet.timestamp,
            distances=packet.distances,
            intensities=packet.intensities,
        )
        == MANUAL
    )


def test_encode_reduces_angles_and_timestamp() -> None:
    data = encode_packet(
        speed=3600, start_angle=36000 + 5, end_angle=100, timestamp=30001,
        distances=[1] * 12, intensities=[2] * 12,
    )
    packet = decode_packet(data)
    assert (packet.start_angle, packet.timestamp) == (5, 1)


def test_encode_rejects_wrong_point_count() -> None:
    with pytest.raises(ValueError, match="12"):
        encode_packet(speed=0, start_angle=0, end_angle=0, timestamp=0, distances=[1], intensities=[1])


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (MANUAL[:-1], "47 bytes"),
        (b"\x55" + MANUAL[1:], "header"),
        (MANUAL[:-1] + b"\x51", "CRC"),
        (MANUAL[:10] + bytes([MANUAL[10] ^ 1]) + MANUAL[11:], "CRC"),
    ],
)
def test_decode_rejects_bad_packets(data: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        decode_packet(data)


def test_point_angles_interpolate_across_zero() -> None:
    packet = decode_packet(
        encode_packet(
            speed=3600, start_angle=35945, end_angle=45, timestamp=0,
            distances=[1] * 12, intensities=[0] * 12,
        )
    )
    assert packet.span == 100
    angles = packet.angles()
    assert angles[0] == pytest.approx(359.45)
    assert angles[-1] == pytest.approx(0.45)
    assert angles[5] == pytest.approx(359.45 + 5 / 11, abs=1e-9) or angles[5] < 1
    assert all(0 <= a < 360 for a in angles)


def test_manual_packet_step_is_span_over_eleven() -> None:
    angles = decode_packet(MANUAL).angles()
    step = (334.70 - 324.27) / 11
    assert angles == pytest.approx([324.27 + step * k for k in range(12)])


def test_health_and_info_frames_carry_valid_crcs() -> None:
    health = encode_health(7)
    assert len(health) == 4 and health[:3] == b"\x54\xe0\x07" and crc8(health) == 0
    info = encode_info(bytes(range(20)))
    assert len(info) == 23 and crc8(info) == 0


def test_model_table() -> None:
    assert (MODELS["LD06"].baudrate, MODELS["LD06"].packets_per_second, MODELS["LD06"].points_per_second) == (
        230400, 375, 4500,
    )
    assert MODELS["LD19"].baudrate == 230400
    stl = MODELS["STL27L"]
    assert (stl.baudrate, stl.packets_per_second, stl.points_per_second) == (921600, 1800, 21600)
    for model in MODELS.values():
        assert model.points_per_second == 12 * model.packets_per_second
        assert model.packets_per_second * PACKET_SIZE < model.bytes_per_second


@pytest.mark.parametrize(
    ("name", "canonical"),
    [("LD06", "LD06"), ("ld19", "LD19"), ("LDLiDAR_LD19", "LD19"), ("STL-27L", "STL27L"), ("stl27l", "STL27L")],
)
def test_model_names_users_meet(name: str, canonical: str) -> None:
    assert get_model(name).name == canonical


def test_unknown_model_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="unknown LiDAR model 'LD99'"):
        get_model("LD99")
