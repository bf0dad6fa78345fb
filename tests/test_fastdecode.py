"""The generated encoders/decoders of the one codec (``virtsensor.canbus.codec``) against cantools.

* ``raw_expr`` (the raw field extraction every generated decoder uses) equals cantools' raw decoding on
  random payloads of every message of ``dbc/virtsensor.dbc`` and of an extra DBC with awkward fields
  (signed with offset, 1-bit, 64-bit, byte-crossing); ``CanMatrix.decode`` (a generated per-message
  decoder) equals cantools' scaled decoding on every message.
* ``compile_encoder`` equals ``CanMatrix.encode`` byte for byte (the matrix uses it).
* ``compile_receiver`` (the daemon's receive path) leaves exactly the state that ``CanMatrix.decode`` plus
  the documented bookkeeping leaves, frame after frame, on random frames with good and bad CRCs, wrong
  lengths, counter jumps, repeats and the invalid counter 15, SNA and implausible values, and gaps.
"""

from __future__ import annotations

import math
import random
import zlib

import cantools
import numpy as np
import pytest

from virtsensor import signals as cat
from virtsensor.canbus.codec import (
    DEFAULT_DBC,
    CanMatrix,
    compile_encoder,
    compile_receiver,
    crc_ok_expr,
    raw_expr,
)
from virtsensor.canbus.e2e import CRC8_TABLE, USABLE, E2EStatus, frame_crc, next_counter

MATRIX = CanMatrix.load()
DB = cantools.database.load_file(str(DEFAULT_DBC), database_format="dbc", strict=True)
N_FRAMES = 3000

EXTRA_DBC = """VERSION ""

NS_ :

BS_:

BU_: A

BO_ 1 Odd: 8 A
 SG_ SignedOffset : 3|11@1- (0.25,-100) [-356|155.75] "u" A
 SG_ OneBit : 14|1@1+ (1,0) [0|1] "" A
 SG_ OneBitSigned : 15|1@1- (1,0) [-1|0] "" A
 SG_ Crossing : 16|23@1- (0.001,12.5) [-4181.804|4206.803] "u" A
 SG_ IntScale : 39|9@1+ (3,-7) [-7|1526] "" A
 SG_ Top : 48|16@1- (1e-05,0) [-0.32768|0.32767] "" A

BO_ 2 Full: 8 A
 SG_ All64 : 0|64@1+ (1,0) [0|1.8446744073709552e+19] "" A

BO_ 3 Short: 3 A
 SG_ Low : 0|5@1- (2,1) [-31|31] "" A
 SG_ High : 5|19@1+ (0.5,0) [0|262143.5] "" A
"""


def _random_payloads(rng: np.random.Generator, length: int, n: int) -> list[bytes]:
    out = [bytes(rng.integers(0, 256, length, dtype=np.uint8)) for _ in range(n)]
    # the extremes of every field: all zeros, all ones, sign bits only
    return out + [bytes(length), b"\xff" * length, b"\x80" * length, b"\x7f" * length]


def _check_raw_against_cantools(msg, rng: np.random.Generator) -> None:
    names = [s.name for s in msg.signals]
    src = ", ".join(raw_expr(s.start, s.length, bool(s.is_signed)) for s in msg.signals)
    raws = eval(f"lambda v: ({src},)")  # noqa: S307 - the generator's own expressions
    for data in _random_payloads(rng, msg.length, N_FRAMES):
        theirs = msg.decode(data, decode_choices=False, scaling=False)
        ours = raws(int.from_bytes(data, "little"))
        for name, r in zip(names, ours, strict=True):
            assert r == theirs[name], (msg.name, name, data.hex(), r, theirs[name])


@pytest.mark.parametrize("name", [m.name for m in DB.messages])
def test_raw_fields_equal_cantools_on_random_frames(name):
    _check_raw_against_cantools(DB.get_message_by_name(name), np.random.default_rng(zlib.crc32(name.encode())))


def test_raw_fields_equal_cantools_on_awkward_fields():
    db = cantools.database.load_string(EXTRA_DBC, database_format="dbc", strict=True)
    rng = np.random.default_rng(7)
    for msg in db.messages:
        _check_raw_against_cantools(msg, rng)


def test_raw_expr_refuses_bad_fields():
    with pytest.raises(ValueError):
        raw_expr(0, 0, False)
    with pytest.raises(ValueError):
        raw_expr(-1, 8, True)


@pytest.mark.parametrize("name", [m.name for m in DB.messages])
def test_matrix_decode_equals_cantools(name):
    """Frames with random payload bits and a right CRC: every signal as cantools scales it (SI values
    times the unit factor), SNA codes as unavailable (catalogue) or nan (others), out-of-range as
    implausible."""
    msg, mc = DB.get_message_by_name(name), MATRIX.messages[name]
    rng = np.random.default_rng(zlib.crc32(b"scaled" + name.encode()))
    for data in _random_payloads(rng, msg.length, 500):
        frame = bytearray(data)
        frame[1] &= 0xF0  # counter 0
        frame[0] = frame_crc(mc.seed, frame)
        d = MATRIX.fresh().decode(mc.frame_id, bytes(frame), 0.0)
        assert d.crc_ok and d.status is E2EStatus.OK
        theirs = msg.decode(bytes(frame), decode_choices=False)
        raw = msg.decode(bytes(frame), decode_choices=False, scaling=False)
        for s in mc.signals:
            if s.catalogue is None:
                want = math.nan if raw[s.name] == s.sna else theirs[s.name]
                got = d.other[s.name]
                assert got == want or (math.isnan(got) and math.isnan(want)), (name, s.name)
            elif raw[s.name] == s.sna:
                assert s.catalogue in d.unavailable and s.catalogue not in d.values
            elif s.catalogue in d.values:
                assert math.isclose(d.values[s.catalogue] * s.si_factor, theirs[s.name], rel_tol=1e-12, abs_tol=1e-12)
                assert s.lo_si - 1e-9 <= d.values[s.catalogue] <= s.hi_si + 1e-9
            else:
                assert s.catalogue in d.implausible


def test_crc_expression_equals_frame_crc():
    rng = np.random.default_rng(3)
    for m in MATRIX.messages.values():
        ok = eval(f"lambda T, b0, b1, b2, b3, b4, b5, b6, b7: {crc_ok_expr(m.seed, 8)}")  # noqa: S307
        for data in _random_payloads(rng, 8, 500):
            good = bytes([frame_crc(m.seed, data)]) + data[1:]
            assert ok(CRC8_TABLE, *good)
            assert not ok(CRC8_TABLE, good[0] ^ 0x01, *good[1:])


def test_generated_decoder_has_no_loop_per_frame():
    """What behaviour cannot show: the generated decoders are straight-line code."""
    src = MATRIX.messages["ESC_WheelSpeeds_F"].decode_frame.__source__
    assert "for " not in src and "while " not in src


def test_encoder_equals_codec():
    rng = random.Random(11)
    for name, mc in MATRIX.messages.items():
        enc = compile_encoder(mc)
        for _ in range(2000):
            values: dict[str, float] = {}
            for s in mc.signals:
                key = s.catalogue if (s.catalogue and rng.random() < 0.8) else s.name
                r = rng.random()
                if r < 0.05:
                    continue
                if r < 0.1:
                    values[key] = math.nan
                elif r < 0.2:
                    values[key] = rng.choice([-1e9, 1e9, math.inf, -math.inf])
                elif r < 0.3:
                    values[key] = rng.randrange(-5, 5)
                else:
                    span = max(abs(s.raw_lo), abs(s.raw_hi)) * s.scale / s.si_factor
                    values[key] = rng.uniform(-1.5, 1.5) * span
            counter = rng.randrange(0, 40)
            assert enc(values, counter) == MATRIX.encode(name, values, counter), (name, values, counter)


# ----------------------------------------------------------------------------------------------- receiver
_KEYS = {s: f"e2e_{s.name.lower()}" for s in E2EStatus}  # the daemon's counter names
_COUNTERS = ("crc_errors", "dlc_errors", "sna_values", "implausible_values", *_KEYS.values())


class _Reference:
    """The daemon's receive path before the generated receivers: ``CanMatrix.decode`` then bookkeeping."""

    def __init__(self, name: str, slots: list[tuple[str, int]], n: int, matrix: CanMatrix = MATRIX) -> None:
        self.matrix = matrix.fresh()
        self.fid = matrix.messages[name].frame_id
        self.slots = slots
        self.values, self.times, self.flags = [math.nan] * n, [-math.inf] * n, [False] * n
        self.last_ok, self.errors = [-math.inf], [False]
        self.counters = dict.fromkeys(_COUNTERS, 0)

    def __call__(self, data: bytes, t: float) -> None:
        d = self.matrix.decode(self.fid, data, t)
        c = self.counters
        c[_KEYS[d.status]] += 1
        if d.status in USABLE:
            self.last_ok[0] = t
            for cname, i in self.slots:
                if cname in d.values:
                    self.values[i], self.times[i], self.flags[i] = d.values[cname], t, False
                elif cname in d.unavailable:
                    self.flags[i] = True
                    c["sna_values"] += 1
                else:
                    assert cname in d.implausible
                    self.flags[i] = True
                    c["implausible_values"] += 1
        elif d.status in (E2EStatus.ERROR, E2EStatus.REPEATED, E2EStatus.WRONGSEQUENCE):
            self.errors[0] = True
            if d.status is E2EStatus.ERROR and not (d.dlc_ok and d.crc_ok):  # else: the invalid counter 15
                c["dlc_errors" if not d.dlc_ok else "crc_errors"] += 1


def _frames(name: str, rng: random.Random, n: int) -> list[tuple[bytes, float]]:
    """Random frames of ``name``: mostly good (right CRC, counter +1), with every kind of fault."""
    mc = MATRIX.messages[name]
    out: list[tuple[bytes, float]] = []
    t, ctr = 100.0, 0
    for _ in range(n):
        t += mc.cycle_s * (rng.choice([1.0] * 8 + [0.2, 7.0]))  # some gaps longer than the E2E timeout
        r = rng.random()
        if r < 0.6:  # plausible values
            values = {s.catalogue: rng.uniform(cat.SIGNALS[s.catalogue].minimum, cat.SIGNALS[s.catalogue].maximum)
                      for s in mc.signals if s.catalogue}
            data = bytearray(MATRIX.encode(name, values, ctr))
        else:  # any bits: SNA, implausible, anything
            data = bytearray(rng.randbytes(mc.length))
            data[1] = (data[1] & 0xF0) | (15 if rng.random() < 0.03 else ctr)  # 15: the invalid counter
            data[0] = frame_crc(mc.seed, data)
            if r < 0.7:  # force SNA codes
                for s in mc.signals:
                    if s.sna is not None and rng.random() < 0.5:
                        v = int.from_bytes(data, "little") & ~(s.mask << s.start) | ((s.sna & s.mask) << s.start)
                        data = bytearray(v.to_bytes(mc.length, "little"))
                data[0] = frame_crc(mc.seed, data)
        f = rng.random()
        if f < 0.05:
            data[0] ^= 1 << rng.randrange(8)  # CRC error
        elif f < 0.08:
            data[rng.randrange(1, mc.length)] ^= 1 << rng.randrange(8)  # corrupted payload: CRC error
        elif f < 0.11:
            data = data[: rng.randrange(0, mc.length)] if rng.random() < 0.7 else data + b"\x00"  # DLC
        elif f < 0.14:
            for _ in range(rng.randrange(1, 20)):  # lost frames: the next counter jumps by 2..20
                ctr = next_counter(ctr)
        elif f < 0.17:
            out.append((bytes(data), t))  # sent twice: repeated counter
        ctr = next_counter(ctr)
        out.append((bytes(data), t))
    return out


@pytest.mark.parametrize("name", [n for n, m in MATRIX.messages.items() if m.catalogue_names])
def test_receiver_leaves_the_reference_state(name):
    mc = MATRIX.messages[name]
    slots = [(s.catalogue, k + 1) for k, s in enumerate(mc.signals) if s.catalogue]  # index 0: someone else's
    n = len(slots) + 2
    ref = _Reference(name, slots, n)
    fresh = MATRIX.fresh()
    values, times, flags = [math.nan] * n, [-math.inf] * n, [False] * n
    last_ok, errors = [-math.inf], [False]
    counters = dict.fromkeys(_COUNTERS, 0)
    codec = {s.catalogue: s for s in mc.signals}
    rx = compile_receiver(mc, fresh.receivers[name], 0, [(codec[c], i) for c, i in slots], values, times, flags,
                          last_ok, errors, counters)
    frames = _frames(name, random.Random(name), N_FRAMES)
    for k, (data, t) in enumerate(frames):
        ref(data, t)
        rx(bytearray(data) if k % 2 else data, t)
        assert counters == ref.counters, (k, data.hex())
        assert times == ref.times and flags == ref.flags and last_ok == ref.last_ok and errors == ref.errors, k
        assert all(a == b or (math.isnan(a) and math.isnan(b)) for a, b in zip(values, ref.values, strict=True)), k
        if k % 97 == 0:  # the daemon clears the error flags at each tick
            errors[0] = ref.errors[0] = False
    seen = {k for k, v in counters.items() if v}
    assert {"e2e_ok", "e2e_error", "e2e_repeated", "crc_errors", "dlc_errors"} <= seen, seen
    assert counters["e2e_error"] > counters["crc_errors"] + counters["dlc_errors"]  # and counter-15 frames
    assert {"e2e_oksomelost", "e2e_wrongsequence"} <= seen, seen
    if any(s.sna is not None for s in mc.signals if s.catalogue):
        assert counters["sna_values"] > 0
    assert math.isnan(values[0]) and times[0] == -math.inf and flags[0] is False  # untouched


# A DBC that changes every constant the receivers inline: VehSpeed moved to bit 20 with another scale,
# offset and SNA code; Pressure_FL in Pa (unit factor 1 instead of 1e-5) at another scale.
_VEHSPEED = ' SG_ VehSpeed : 12|14@1+ (0.01,-20) [-20|90] "m/s" VSENS'
_PRESSURE = ' SG_ Pressure_FL : 12|10@1+ (0.005,0) [0|5.1] "bar" VSENS'
_CHANGED = (
    (_VEHSPEED, ' SG_ VehSpeed : 20|14@1+ (0.02,-30) [-20|90] "m/s" VSENS'),
    ('VAL_ 257 VehSpeed 16383 "SNA" ;', 'VAL_ 257 VehSpeed 9000 "SNA" ;'),
    (_PRESSURE, ' SG_ Pressure_FL : 12|10@1+ (250,0) [0|255000] "Pa" VSENS'),
)
_RESEEDED = (('BA_ "E2E_DataID" BO_ 257 4113;', 'BA_ "E2E_DataID" BO_ 257 4114;'),)


def _dbc_variant(path, edits) -> CanMatrix:
    text = DEFAULT_DBC.read_text()
    for old, new in edits:
        assert text.count(old) == 1, old  # the bundled DBC changed: update the edit
        text = text.replace(old, new)
    path.write_text(text)
    return CanMatrix.load(path)


def _frame(mc, body: int, counter: int) -> bytes:
    """``mc``'s payload with the bits ``body`` (from bit 12), the alive counter and a good CRC."""
    data = bytearray(((body << 12) | ((counter % 15) << 8)).to_bytes(mc.length, "little"))
    data[0] = frame_crc(mc.seed, data)
    return bytes(data)


def _receive(matrix: CanMatrix, name: str, frames: list[bytes], msg_index: int = 2):
    """Feed ``frames`` to the receiver compiled from ``matrix``'s ``name`` and to the reference (``decode`` of
    the same matrix); both must leave the same state after every frame. Returns the slot values after each
    frame (NaN: not written yet), the counters and the per-message lists."""
    mc = matrix.messages[name]
    slots = [(s.catalogue, k + 1) for k, s in enumerate(mc.signals) if s.catalogue]
    n = len(slots) + 2
    ref = _Reference(name, slots, n, matrix)
    values, times, flags = [math.nan] * n, [-math.inf] * n, [False] * n
    last_ok, errors = [-math.inf] * 4, [False] * 4
    counters = dict.fromkeys(_COUNTERS, 0)
    codec = {s.catalogue: s for s in mc.signals}
    rx = compile_receiver(mc, matrix.fresh().receivers[name], msg_index, [(codec[c], i) for c, i in slots],
                          values, times, flags, last_ok, errors, counters)
    trace = []
    for k, data in enumerate(frames):
        t = 100.0 + k * mc.cycle_s
        ref(data, t)
        rx(data, t)
        assert counters == ref.counters, (name, k, data.hex())
        assert times == ref.times and flags == ref.flags, (name, k, data.hex())
        assert all(a == b or (math.isnan(a) and math.isnan(b)) for a, b in zip(values, ref.values, strict=True)), (
            name, k, data.hex(), values, ref.values)
        assert last_ok[msg_index] == ref.last_ok[0] and errors[msg_index] == ref.errors[0], (name, k)
        trace.append(list(values))
    # the other messages' entries are untouched
    assert all(x == -math.inf for i, x in enumerate(last_ok) if i != msg_index)
    assert not any(e for i, e in enumerate(errors) if i != msg_index)
    assert math.isnan(values[0]) and math.isnan(values[-1])
    return trace, counters, last_ok, errors


def test_receiver_decodes_with_the_dbc_constants(tmp_path):
    """The receivers inline the DBC's constants: compiled from a DBC with other bit positions, scale,
    offset, SNA code and unit factor, a receiver decodes as ``CanMatrix.decode`` of that DBC (and
    differently from one compiled from the bundled DBC, on the very same frames)."""
    changed = _dbc_variant(tmp_path / "changed.dbc", _CHANGED)
    rng = random.Random(5)
    for name in ("ESC_VehicleSpeed", "TPMS_Pressures"):
        mc = MATRIX.messages[name]
        assert changed.messages[name].seed == mc.seed  # same data ID: the frames pass both CRCs
        frames = [_frame(mc, rng.getrandbits(52), k) for k in range(400)]
        ours, c_ours, _, _ = _receive(changed, name, frames)
        bundled, c_bundled, _, _ = _receive(MATRIX, name, frames)
        assert c_ours["e2e_ok"] == c_bundled["e2e_ok"] == 400
        # the same frames, other values (but raw 0 of the unsigned pressure, 0 Pa whatever the scale)
        both = [(a[1], b[1]) for a, b in zip(ours, bundled, strict=True) if not math.isnan(a[1] + b[1])]
        assert len(both) > 50 and all(a != b for a, b in both if a or b), name
    # values worked out by hand from the changed DBC (slot 1 is the first signal)
    mc = MATRIX.messages["ESC_VehicleSpeed"]
    frames = [_frame(mc, 2000 << 8, 0),   # raw 2000 at bit 20: 2000 * 0.02 - 30 = 10 m/s
              _frame(mc, 9000 << 8, 1),   # the changed SNA code
              _frame(mc, 16383, 2),       # the bundled SNA code at bit 12; at bit 20 raw 63: -28.74 m/s, implausible
              _frame(mc, 6000 << 8, 3)]   # 90 m/s: the top of the range
    trace, counters, last_ok, _ = _receive(changed, "ESC_VehicleSpeed", frames)
    assert [v[1] for v in trace] == pytest.approx([10.0, 10.0, 10.0, 90.0], abs=1e-12)
    assert counters["sna_values"] == 1 and counters["implausible_values"] == 1
    assert last_ok[2] == 100.0 + 3 * mc.cycle_s
    trace, counters, _, _ = _receive(MATRIX, "ESC_VehicleSpeed", frames)
    assert trace[0][1] == pytest.approx(4096 * 0.01 - 20) and counters["sna_values"] == 1  # the bundled code
    mc = MATRIX.messages["TPMS_Pressures"]
    trace, _, _, _ = _receive(changed, "TPMS_Pressures", [_frame(mc, 7, 0)])
    assert trace[0][1] == pytest.approx(7 * 250.0)  # Pa: unit factor 1, not the bundled kPa's 1e-3
    trace, _, _, _ = _receive(MATRIX, "TPMS_Pressures", [_frame(mc, 7, 0)])
    assert trace[0][1] == pytest.approx(7 * 0.5 / 1e-3)


def test_receiver_checks_the_crc_of_the_dbc_data_id(tmp_path):
    """The CRC seed inlined is the DBC's data ID: frames protected with another data ID are CRC errors."""
    reseeded = _dbc_variant(tmp_path / "reseeded.dbc", _RESEEDED)
    name = "ESC_VehicleSpeed"
    rng = random.Random(6)
    bodies = [rng.getrandbits(52) for _ in range(50)]
    for rx_matrix, tx_matrix in ((reseeded, MATRIX), (MATRIX, reseeded)):
        good = [_frame(rx_matrix.messages[name], b, k) for k, b in enumerate(bodies)]
        bad = [_frame(tx_matrix.messages[name], b, k) for k, b in enumerate(bodies)]
        _, counters, last_ok, errors = _receive(rx_matrix, name, good)
        assert counters["e2e_ok"] == 50 and counters["crc_errors"] == 0 and not errors[2]
        _, counters, last_ok, errors = _receive(rx_matrix, name, bad)
        assert counters["crc_errors"] >= 48 and errors[2]  # a random CRC byte matches 1 time in 256


def test_receiver_has_no_loop_per_frame():
    """What behaviour cannot show: the generated receiver is straight-line code (its reason to exist is
    speed)."""
    mc = MATRIX.messages["ESC_WheelSpeeds_F"]
    rx = compile_receiver(mc, MATRIX.fresh().receivers[mc.name], 0, [(s, k) for k, s in enumerate(mc.signals)],
                          [0.0] * 4, [0.0] * 4, [False] * 4, [0.0], [False], dict.fromkeys(_COUNTERS, 0))
    assert "for " not in rx.__source__ and "while " not in rx.__source__
