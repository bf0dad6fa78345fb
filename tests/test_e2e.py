"""AUTOSAR E2E Profile 11 (virtsensor.canbus.e2e) and its cross-check against an independent implementation.

The independent implementation is the ``autosar-e2e`` package (module ``e2e``, C extension): its
``e2e.p11.e2e_p11_protect`` writes the counter (incrementing it modulo 15 when asked) and the CRC,
``e2e.p11.e2e_p11_check`` checks CRC and counter range (0..14). Frames are protected with one
implementation and checked with the other, both ways, on every message of the DBC, through counter
wraps (14 -> 0), repetitions and jumps.
"""

from __future__ import annotations

import math
import random

import e2e
import pytest
from hypothesis import given
from hypothesis import strategies as st

from virtsensor import signals as cat
from virtsensor.canbus.codec import CanMatrix
from virtsensor.canbus.e2e import (
    COUNTER_MAX,
    USABLE,
    E2EReceiver,
    E2EStatus,
    counter_sequence,
    crc8_sae_j1850,
    data_id_seed,
    frame_crc,
    next_counter,
)

MATRIX = CanMatrix.load()
MAX_DELTA = MATRIX.max_delta


def _bitwise_crc8(data: bytes, init: int, xorout: int) -> int:
    """Reference: bit-by-bit CRC-8, poly 0x1D, no reflection."""
    c = init
    for b in data:
        c ^= b
        for _ in range(8):
            c = ((c << 1) ^ 0x1D) & 0xFF if c & 0x80 else (c << 1) & 0xFF
    return c ^ xorout


# ------------------------------------------------------------------------------------------------ CRC
def test_check_value():
    assert crc8_sae_j1850("123456789") == 0x4B
    assert crc8_sae_j1850(b"123456789") == 0x4B == e2e.crc.calculate_crc8(b"123456789")


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
    assert crc8_sae_j1850(data) == _bitwise_crc8(data, 0xFF, 0xFF)


@given(st.integers(0, 0xFFFF), st.binary(min_size=2, max_size=8))
def test_frame_crc_is_profile_11_mode_both(data_id, payload):
    """Register start 0x00, no final XOR, over the data ID (low byte first) then bytes 1..n-1; the same
    as the Crc library's CRC-8 chained with start value 0xFF and IsFirstCall FALSE, XOR-ed back."""
    body = bytes((data_id & 0xFF, data_id >> 8)) + payload[1:]
    expected = _bitwise_crc8(body, 0x00, 0x00)
    assert frame_crc(data_id_seed(data_id), payload) == expected
    assert expected == e2e.crc.calculate_crc8(body, 0xFF, False) ^ 0xFF


def test_prs_profile_11_example():
    """The Profile 11 example of the AUTOSAR E2E protocol specification (data ID 0x123, mode BOTH,
    8 zero bytes): CRC 0xCC with counter 0, 0x91 with counter 1."""
    frame = bytearray(8)
    assert frame_crc(data_id_seed(0x123), frame) == 0xCC
    frame[1] = 1
    assert frame_crc(data_id_seed(0x123), frame) == 0x91


def test_data_id_must_be_16_bit():
    with pytest.raises(ValueError):
        data_id_seed(0x10000)


def test_counter_arithmetic():
    assert [next_counter(c) for c in range(15)] == [*range(1, 15), 0]
    assert list(counter_sequence(12, 6)) == [12, 13, 14, 0, 1, 2]
    assert list(counter_sequence(0, 31)) == [*range(15), *range(15), 0]


# ----------------------------------------------------------------------------------------- per-frame check
def _feed(rx: E2EReceiver, counters, dt=0.01, t0=0.0):
    return [rx.check(c, True, t0 + i * dt) for i, c in enumerate(counters)]


def test_initial_state_is_check_init():
    rx = E2EReceiver()
    assert rx.counter == COUNTER_MAX and rx.status is E2EStatus.ERROR
    assert _feed(rx, [0]) == [E2EStatus.OK]  # a sender starting at 0 is OK from its first frame


@pytest.mark.parametrize("first, expected", [(0, E2EStatus.OK), (1, E2EStatus.OKSOMELOST),
                                             (2, E2EStatus.OKSOMELOST), (3, E2EStatus.WRONGSEQUENCE),
                                             (14, E2EStatus.REPEATED)])
def test_first_frame_is_judged_against_the_initial_counter_14(first, expected):
    assert E2EReceiver(max_delta=3).check(first, True, 0.0) is expected


def test_ok_with_wraparound_14_to_0():
    rx = E2EReceiver(max_delta=3)
    out = _feed(rx, [12, 13, 14, 0, 1])
    assert out[1:] == [E2EStatus.OK] * 4


def test_repeated_somelost_wrongsequence():
    rx = E2EReceiver(max_delta=3)
    out = _feed(rx, [5, 5, 7, 10, 0, 1])
    assert out[1:] == [
        E2EStatus.REPEATED,  # delta 0
        E2EStatus.OKSOMELOST,  # delta 2
        E2EStatus.OKSOMELOST,  # delta 3 == MaxDeltaCounter
        E2EStatus.WRONGSEQUENCE,  # delta 5 (10 -> 0 modulo 15)
        E2EStatus.OK,  # synchronised on 0
    ]


def test_somelost_across_wrap():
    rx = E2EReceiver(max_delta=3)
    assert _feed(rx, [13, 1]) == [E2EStatus.WRONGSEQUENCE, E2EStatus.OKSOMELOST]  # 13 -> 1: delta 3 (mod 15)


def test_error_keeps_state():
    rx = E2EReceiver(max_delta=3)
    rx.check(3, True, 0.0)
    assert rx.check(4, False, 0.01) is E2EStatus.ERROR
    assert rx.counter == 3
    # the frame with counter 4 was rejected: 5 is two steps after the last good one
    assert rx.check(5, True, 0.02) is E2EStatus.OKSOMELOST
    assert rx.check(6, True, 0.03) is E2EStatus.OK


def test_counter_15_is_an_error():
    rx = E2EReceiver(max_delta=3)
    rx.check(14, True, 0.0)
    assert rx.check(15, True, 0.01) is E2EStatus.ERROR and rx.counter == 14
    assert rx.check(0, True, 0.02) is E2EStatus.OK


def test_poll_nonewdata_does_not_touch_the_counter():
    rx = E2EReceiver(max_delta=3, timeout_s=0.05)
    assert rx.poll(0.0) is E2EStatus.NONEWDATA is E2EStatus.NODATA  # nothing received yet
    rx.check(0, True, 0.00)
    rx.check(1, True, 0.01)
    assert rx.poll(0.05) is E2EStatus.OK  # 40 ms since the last frame: within the timeout
    assert rx.poll(0.07) is E2EStatus.NONEWDATA  # 60 ms > 50 ms
    assert rx.counter == 1


def test_poll_future_stamped_last_frame_is_nonewdata():
    """The same freshness rule as the daemon's: 0 <= now - last_rx_s <= timeout; a frame stamped after
    ``now`` is not data within the timeout, whatever its age's magnitude."""
    rx = E2EReceiver(max_delta=3, timeout_s=0.05)
    rx.check(0, True, 10.0)
    assert rx.poll(9.99) is E2EStatus.NONEWDATA  # stamped 10 ms after now
    assert rx.poll(10.0) is E2EStatus.NONEWDATA  # (the status stays until the next frame)
    rx.check(1, True, 10.01)
    assert rx.poll(10.01) is E2EStatus.OK and rx.poll(10.05) is E2EStatus.OK
    assert rx.poll(float("nan")) is E2EStatus.NONEWDATA


@pytest.mark.parametrize("t_next, why", [(0.005, "time step back"), (0.08, "gap past the timeout"),
                                          (float("nan"), "no time")])
def test_check_outside_the_timeout_window_is_wrongsequence_and_resynchronises(t_next, why):
    """A frame whose gap since the last one is negative or longer than the timeout is WRONGSEQUENCE even
    with the next counter (the counter cannot say how many frames were lost); it costs one frame."""
    rx = E2EReceiver(max_delta=3, timeout_s=0.05)
    assert _feed(rx, [0, 1]) == [E2EStatus.OK, E2EStatus.OK]  # last frame at t = 0.01
    assert rx.check(2, True, t_next) is E2EStatus.WRONGSEQUENCE, why
    assert rx.counter == 2
    if math.isnan(t_next):  # a NaN time cannot anchor the next gap: that frame resynchronises too
        assert rx.check(3, True, 0.02) is E2EStatus.WRONGSEQUENCE
        t_next = 0.02
    assert rx.check(rx.counter + 1, True, t_next + 0.01) is E2EStatus.OK


def test_check_gap_at_the_bounds_is_within_the_timeout():
    rx = E2EReceiver(max_delta=3, timeout_s=0.0625)
    rx.check(0, True, 0.5)
    assert rx.check(1, True, 0.5) is E2EStatus.OK  # gap 0
    assert rx.check(2, True, 0.5625) is E2EStatus.OK  # gap == timeout (exact in binary)
    assert rx.check(4, True, 0.5725) is E2EStatus.OKSOMELOST
    assert E2EReceiver(timeout_s=0.05).check(0, True, -5.0) is E2EStatus.OK  # nothing before: counter only


def test_reset_is_check_init():
    rx = E2EReceiver()
    rx.check(7, True, 0.0)
    rx.reset()
    assert rx.counter == COUNTER_MAX and rx.check(0, True, 0.01) is E2EStatus.OK


@given(st.integers(0, 14), st.integers(0, 14), st.integers(1, 14))
def test_delta_classification(first, second, max_delta):
    rx = E2EReceiver(max_delta=max_delta)
    rx.check(first, True, 0.0)
    d = (second - first) % 15
    got = rx.check(second, True, 0.01)
    if d == 0:
        assert got is E2EStatus.REPEATED
    elif d == 1:
        assert got is E2EStatus.OK
    elif d <= max_delta:
        assert got is E2EStatus.OKSOMELOST
    else:
        assert got is E2EStatus.WRONGSEQUENCE
    assert rx.counter == second


def test_usable_statuses_and_codes():
    assert USABLE == {E2EStatus.OK, E2EStatus.OKSOMELOST}
    # the values of E2E_P11CheckStatusType
    assert [(s.name, int(s)) for s in E2EStatus] == [
        ("OK", 0x00), ("NONEWDATA", 0x01), ("ERROR", 0x07), ("REPEATED", 0x08), ("OKSOMELOST", 0x20),
        ("WRONGSEQUENCE", 0x40)]


def test_bad_max_delta():
    for bad in (0, 15):
        with pytest.raises(ValueError):
            E2EReceiver(max_delta=bad)


# ------------------------------------------------------------------------------- cross-check with autosar-e2e
ALL_MESSAGES = sorted(MATRIX.messages)


def _random_values(name: str, rng: random.Random) -> dict[str, float]:
    """Values of every signal of ``name`` (catalogue names in range, other signals by DBC raw range)."""
    out: dict[str, float] = {}
    for s in MATRIX.messages[name].signals:
        if s.catalogue:
            spec = cat.SIGNALS[s.catalogue]
            out[s.catalogue] = rng.uniform(spec.minimum, spec.maximum)
        else:
            out[s.name] = rng.randint(max(s.raw_lo, 0), min(s.raw_hi, 1000)) * s.scale + s.offset
    return out


def _sender_events(rng: random.Random, n: int) -> list[int]:
    """How many counter increments before each frame: mostly 1, with repeats (0) and jumps (2..20,
    so some jumps wrap the counter more than once)."""
    return [rng.choice([1] * 6 + [0, 2, 3, rng.randint(4, 20)]) for _ in range(n)]


def _expected(increments: int) -> E2EStatus:
    """Profile 11 status of a frame ``increments`` counter steps after the last accepted one."""
    d = increments % 15
    if d == 0:
        return E2EStatus.REPEATED
    if d == 1:
        return E2EStatus.OK
    return E2EStatus.OKSOMELOST if d <= MAX_DELTA else E2EStatus.WRONGSEQUENCE


@pytest.mark.parametrize("name", ALL_MESSAGES)
def test_ours_protect_autosar_e2e_checks(name):
    """Frames encoded by the codec (counter by ``next_counter`` from 0, through several wraps) pass
    ``e2e_p11_check``; ``e2e_p11_protect`` writes the very same CRC, and its counter increment gives our
    next counter; any single bit flipped, or the counter 15, fails both checks."""
    mc = MATRIX.messages[name]
    rng = random.Random(name)
    rx = MATRIX.fresh()
    counter = 0
    for k in range(50):
        values = _random_values(name, rng)
        frame = bytearray(MATRIX.encode(name, values, counter))
        assert frame[1] & 0xF == counter
        assert e2e.p11.e2e_p11_check(frame, mc.data_id), (name, k, frame.hex())
        theirs = bytearray(frame)
        e2e.p11.e2e_p11_protect(theirs, mc.data_id, increment_counter=False)
        assert theirs == frame
        e2e.p11.e2e_p11_protect(theirs, mc.data_id, increment_counter=True)
        counter = next_counter(counter)
        assert theirs == MATRIX.encode(name, values, counter)  # same counter step, wrap 14 -> 0 included
        assert rx.decode(mc.frame_id, bytes(frame), 0.01 * k).status is E2EStatus.OK
        bad = bytearray(frame)
        bad[rng.randrange(mc.length)] ^= 1 << rng.randrange(8)
        assert not e2e.p11.e2e_p11_check(bad, mc.data_id)
        assert MATRIX.fresh().decode(mc.frame_id, bytes(bad), 0.0).status is E2EStatus.ERROR
    invalid = bytearray(MATRIX.encode(name, {}, 0))
    invalid[1] |= 0xF
    e2e.p11.e2e_p11_protect(invalid, mc.data_id, increment_counter=False)  # a right CRC over counter 15
    assert not e2e.p11.e2e_p11_check(invalid, mc.data_id)
    d = MATRIX.fresh().decode(mc.frame_id, bytes(invalid), 0.0)
    assert d.crc_ok and d.counter == 15 and d.status is E2EStatus.ERROR


@pytest.mark.parametrize("name", ALL_MESSAGES)
def test_autosar_e2e_protects_ours_checks(name):
    """Frames protected by ``e2e_p11_protect`` (its counter, its CRC) through increments, repeats and
    jumps, fed to the codec's receive paths (``CanMatrix.decode`` and the daemon's compiled receiver):
    the status follows the number of increments since the last accepted frame, and the values are
    those encoded."""
    from virtsensor.canbus.codec import STATUS_KEYS, compile_receiver

    mc = MATRIX.messages[name]
    rng = random.Random(f"autosar-{name}")
    matrix = MATRIX.fresh()
    daemon_state = MATRIX.fresh()
    slots = [(s, i) for i, s in enumerate(s for s in mc.signals if s.catalogue)]
    n = len(slots)
    vals, times, flags, last_ok, errs = [float("nan")] * n, [0.0] * n, [False] * n, [0.0], [False]
    counters = dict.fromkeys(("crc_errors", "dlc_errors", "sna_values", "implausible_values",
                              *STATUS_KEYS.values()), 0)
    rx = compile_receiver(mc, daemon_state.receivers[name], 0, slots, vals, times, flags, last_ok, errs, counters)
    frame = bytearray(MATRIX.encode(name, {}, COUNTER_MAX))  # protect's first increment gives counter 0
    seen = set()
    for k, inc in enumerate([1, *_sender_events(rng, 300)]):
        values = _random_values(name, rng)
        payload = bytearray(MATRIX.encode(name, values, 0))
        frame[2:] = payload[2:]
        frame[1] = (frame[1] & 0x0F) | (payload[1] & 0xF0)  # bits 12..15 are payload in mode BOTH
        for _ in range(inc):
            e2e.p11.e2e_p11_protect(frame, mc.data_id, increment_counter=True)
        e2e.p11.e2e_p11_protect(frame, mc.data_id, increment_counter=False)
        expected = _expected(inc)  # every frame passes the CRC: each one resynchronises the receiver
        d = matrix.decode(mc.frame_id, bytes(frame), 0.01 * k)
        assert d.crc_ok and d.status is expected, (name, k, inc, d.status, expected)
        before = dict(counters)
        rx(frame, 0.01 * k)
        assert counters[STATUS_KEYS[expected]] == before[STATUS_KEYS[expected]] + 1
        ours = MATRIX.encode(name, values, d.counter)
        assert ours[2:] == bytes(frame[2:])
        for s in mc.signals:
            if s.catalogue:
                assert abs(d.values[s.catalogue] - values[s.catalogue]) <= 0.5 * s.resolution_si + 1e-9
        seen.add(expected)
    assert seen == {E2EStatus.OK, E2EStatus.REPEATED, E2EStatus.OKSOMELOST, E2EStatus.WRONGSEQUENCE}
    assert counters["e2e_error"] == counters["crc_errors"] == 0
