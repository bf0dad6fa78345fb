"""CRC-8/SAE-J1850 and the E2E receiver state machine (virtsensor.e2e)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from virtsensor.e2e import (
    USABLE,
    E2EReceiver,
    E2EStatus,
    crc8_sae_j1850,
    data_id_seed,
    frame_crc,
)


def _bitwise_crc8(data: bytes) -> int:
    """Reference: bit-by-bit CRC-8, poly 0x1D, init 0xFF, xorout 0xFF."""
    c = 0xFF
    for b in data:
        c ^= b
        for _ in range(8):
            c = ((c << 1) ^ 0x1D) & 0xFF if c & 0x80 else (c << 1) & 0xFF
    return c ^ 0xFF


def test_check_value():
    assert crc8_sae_j1850("123456789") == 0x4B
    assert crc8_sae_j1850(b"123456789") == 0x4B


@pytest.mark.parametrize(
    "hexdata, crc",
    [
        ("00 00 00 00", 0x59),
        ("F2 01 83", 0x37),
        ("0F AA 00 55", 0x79),
        ("00 FF 55 11", 0xB8),
        ("33 22 55 AA BB CC DD EE FF", 0xCB),
        ("92 6B 55", 0x8C),
        ("FF FF FF FF", 0x74),
    ],
)
def test_autosar_crc_library_vectors(hexdata, crc):
    assert crc8_sae_j1850(bytes.fromhex(hexdata)) == crc


@given(st.binary(max_size=64))
def test_table_matches_bitwise_reference(data):
    assert crc8_sae_j1850(data) == _bitwise_crc8(data)


@given(st.integers(0, 0xFFFF), st.binary(min_size=8, max_size=8))
def test_frame_crc_covers_data_id_low_byte_first_then_bytes_1_to_7(data_id, payload):
    expected = _bitwise_crc8(bytes((data_id & 0xFF, data_id >> 8)) + payload[1:])
    assert frame_crc(data_id_seed(data_id), payload) == expected


def test_data_id_must_be_16_bit():
    with pytest.raises(ValueError):
        data_id_seed(0x10000)


def _feed(rx: E2EReceiver, counters, dt=0.01, t0=0.0):
    return [rx.check(c, True, t0 + i * dt) for i, c in enumerate(counters)]


def test_first_frame_initial_then_ok_with_wraparound():
    rx = E2EReceiver(max_delta=3, timeout_s=0.05)
    out = _feed(rx, [13, 14, 15, 0, 1])
    assert out == [E2EStatus.INITIAL, E2EStatus.OK, E2EStatus.OK, E2EStatus.OK, E2EStatus.OK]


def test_repeated_somelost_wrongsequence():
    rx = E2EReceiver(max_delta=3, timeout_s=1.0)
    out = _feed(rx, [5, 5, 7, 10, 15, 0])
    assert out == [
        E2EStatus.INITIAL,
        E2EStatus.REPEATED,  # delta 0
        E2EStatus.OKSOMELOST,  # delta 2
        E2EStatus.OKSOMELOST,  # delta 3 == max_delta
        E2EStatus.WRONGSEQUENCE,  # delta 5
        E2EStatus.OK,  # resynchronised on 15
    ]


def test_somelost_across_wrap():
    rx = E2EReceiver(max_delta=3, timeout_s=1.0)
    assert _feed(rx, [14, 1]) == [E2EStatus.INITIAL, E2EStatus.OKSOMELOST]  # 14 -> 1 is delta 3


def test_crc_error_keeps_state():
    rx = E2EReceiver(max_delta=3, timeout_s=1.0)
    rx.check(3, True, 0.0)
    assert rx.check(4, False, 0.01) is E2EStatus.ERROR
    # the frame with counter 4 was rejected: 5 is two steps after the last good one
    assert rx.check(5, True, 0.02) is E2EStatus.OKSOMELOST
    assert rx.check(6, True, 0.03) is E2EStatus.OK


def test_timeout_nodata_then_initial():
    rx = E2EReceiver(max_delta=3, timeout_s=0.05)
    assert rx.poll(0.0) is E2EStatus.NODATA  # nothing received yet
    rx.check(0, True, 0.00)
    rx.check(1, True, 0.01)
    assert rx.poll(0.05) is E2EStatus.OK  # 40 ms since the last frame: within the timeout
    assert rx.poll(0.07) is E2EStatus.NODATA  # 60 ms > 50 ms
    assert rx.check(2, True, 0.08) is E2EStatus.INITIAL  # counter not checked after a timeout


def test_gap_longer_than_timeout_without_poll_is_initial():
    rx = E2EReceiver(max_delta=3, timeout_s=0.05)
    rx.check(0, True, 0.0)
    assert rx.check(9, True, 0.5) is E2EStatus.INITIAL


def test_reset():
    rx = E2EReceiver()
    rx.check(1, True, 0.0)
    rx.reset()
    assert rx.check(7, True, 0.01) is E2EStatus.INITIAL


@given(st.integers(0, 15), st.integers(0, 15), st.integers(1, 15))
def test_delta_classification(first, second, max_delta):
    rx = E2EReceiver(max_delta=max_delta)
    rx.check(first, True, 0.0)
    d = (second - first) % 16
    got = rx.check(second, True, 0.01)
    if d == 0:
        assert got is E2EStatus.REPEATED
    elif d == 1:
        assert got is E2EStatus.OK
    elif d <= max_delta:
        assert got is E2EStatus.OKSOMELOST
    else:
        assert got is E2EStatus.WRONGSEQUENCE


def test_usable_statuses():
    assert USABLE == {E2EStatus.OK, E2EStatus.OKSOMELOST, E2EStatus.INITIAL}


def test_bad_max_delta():
    with pytest.raises(ValueError):
        E2EReceiver(max_delta=0)
