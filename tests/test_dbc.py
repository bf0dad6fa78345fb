"""The generated DBC (virtsensor.canbus.dbcgen, dbc/virtsensor.dbc) and the codec (virtsensor.canbus.codec)."""

from __future__ import annotations

import math
import subprocess
import sys
import time
from pathlib import Path

import cantools
import e2e
import numpy as np
import pytest

from virtsensor import signals as cat
from virtsensor.canbus import codec as codec_module
from virtsensor.canbus import dbcgen
from virtsensor.canbus.codec import CanMatrix
from virtsensor.canbus.e2e import E2EStatus
from virtsensor.errors import UserError

REPO = Path(__file__).resolve().parents[1]
DBC = REPO / "dbc" / "virtsensor.dbc"


@pytest.fixture(scope="module")
def db():
    return cantools.database.load_file(str(DBC))


@pytest.fixture()
def matrix():
    return CanMatrix.load()


def test_committed_dbc_equals_generated():
    assert DBC.read_text() == dbcgen.generate(), (
        "regenerate: python -m virtsensor.canbus.dbcgen > dbc/virtsensor.dbc"
    )


def test_module_entry_point_prints_the_dbc():
    out = subprocess.run(
        [sys.executable, "-m", "virtsensor.canbus.dbcgen"], capture_output=True, text=True, cwd=REPO, check=True
    ).stdout
    assert out == DBC.read_text()


def test_messages_match_catalogue(db):
    assert {m.name for m in db.messages} == set(cat.MESSAGES)
    for spec in cat.MESSAGES.values():
        m = db.get_message_by_name(spec.name)
        assert m.frame_id == spec.frame_id
        assert m.senders == [spec.sender]
        assert m.cycle_time == round(spec.cycle_s * 1000)
        assert m.dbc.attributes["E2E_DataID"].value == spec.data_id
        assert m.length == 8
        assert not m.is_extended_frame
        assert m.comment
        crc = m.get_signal_by_name(f"{spec.name}_CRC")
        ctr = m.get_signal_by_name(f"{spec.name}_Counter")
        assert (crc.start, crc.length, crc.byte_order) == (0, 8, "little_endian")
        assert (ctr.start, ctr.length, ctr.byte_order) == (8, 4, "little_endian")
        bits = set()
        for s in m.signals:
            assert s.byte_order == "little_endian"
            assert s.comment, f"{m.name}.{s.name} has no comment"
            own = set(range(s.start, s.start + s.length))
            assert not bits & own, f"{m.name}.{s.name} overlaps"
            bits |= own
        assert max(bits) < 64


def test_nodes(db):
    assert [n.name for n in db.nodes] == ["ESC", "ACU", "EPAS", "PCU", "CHS", "TPMS", "VSENS", "TESTEQ"]
    assert all(n.comment for n in db.nodes)


def test_every_catalogue_can_signal_is_in_the_dbc(db):
    for name in cat.CAN_SIGNALS:
        spec = cat.SIGNALS[name]
        s = db.get_message_by_name(spec.message).get_signal_by_name(spec.dbc_signal)
        unit, factor = dbcgen.UNIT_CONVERSIONS.get(spec.unit, (spec.unit, 1.0))
        assert s.unit == unit, name
        assert spec.resolution > 0, name
        assert math.isclose(s.scale, spec.resolution * factor, rel_tol=1e-12), name
        assert math.isclose(s.minimum, spec.minimum * factor, abs_tol=1e-9), name
        assert math.isclose(s.maximum, spec.maximum * factor, abs_tol=1e-9), name
        # the raw range covers the catalogue range, with one spare code for SNA
        lo_raw = -(2 ** (s.length - 1)) if s.is_signed else 0
        hi_raw = 2 ** (s.length - 1) - 1 if s.is_signed else 2**s.length - 1
        assert lo_raw * s.scale + s.offset <= spec.minimum * factor + 1e-9, name
        assert hi_raw * s.scale + s.offset >= spec.maximum * factor - 1e-9, name
        assert "SNA" in [str(v) for v in s.choices.values()], name
        assert spec.description.split(",")[0] in s.comment


def test_every_signal_keeps_its_catalogue_resolution(db):
    for name in cat.CAN_SIGNALS:
        spec = cat.SIGNALS[name]
        sig = db.get_message_by_name(spec.message).get_signal_by_name(spec.dbc_signal)
        factor = dbcgen.UNIT_CONVERSIONS.get(spec.unit, (spec.unit, 1.0))[1]
        assert sig.scale == pytest.approx(spec.resolution * factor), name


def test_vsens_messages(db):
    sat = db.get_message_by_name("SAT_FRONT")
    names = [s.name for s in sat.signals]
    assert names[2:] == ["SAT_FL", "SAT_FR", "SAT_FL_Status", "SAT_FR_Status"]
    for c in ("FL", "FR"):
        s = sat.get_signal_by_name(f"SAT_{c}")
        assert s.unit == "Nm" and s.scale == 0.02 and s.minimum == -300 and s.maximum == 300
        assert "negative in a left turn" in s.comment
        st = sat.get_signal_by_name(f"SAT_{c}_Status")
        assert st.length == 2
        assert {k: str(v) for k, v in st.choices.items()} == {
            0: "VALID",
            1: "DEGRADED",
            2: "INVALID",
            3: "INIT",
        }
    health = db.get_message_by_name("VS_Health")
    hn = {s.name: s for s in health.signals}
    assert hn["VS_TickLatency"].unit == "us"
    assert {"VS_TickOverruns", "VS_InputStatus", "VS_ModelId"} <= set(hn)
    for m in (
        "IMU_Motion",
        "EPAS_Steering",
        "PT_Torque",
        "ESC_WheelSpeeds_F",
        "ESC_VehicleSpeed",
        "CHS_Suspension",
    ):
        assert m in hn["VS_InputStatus"].comment
    # carries no estimator input, but the yaw-rate check's reference: last, bit 7
    assert "bit 7 ESC_WheelSpeeds_R (a plausibility check's reference" in hn["VS_InputStatus"].comment
    te = db.get_message_by_name("TE_WheelForceTransducer")
    assert [s.name for s in te.signals][2:] == ["Mz_FL", "Mz_FR"]


def test_cantools_dump_reads_it():
    r = subprocess.run([sys.executable, "-m", "cantools", "dump", str(DBC)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for name in cat.MESSAGES:
        assert name in r.stdout


def test_load_dump_load_round_trip(db):
    again = cantools.database.load_string(db.as_dbc_string(), database_format="dbc")
    assert [m.name for m in again.messages] == [m.name for m in db.messages]
    for m1 in db.messages:
        m2 = again.get_message_by_name(m1.name)
        assert (m2.frame_id, m2.length, m2.senders, m2.cycle_time, m2.comment) == (
            m1.frame_id,
            m1.length,
            m1.senders,
            m1.cycle_time,
            m1.comment,
        )
        assert m2.dbc.attributes["E2E_DataID"].value == m1.dbc.attributes["E2E_DataID"].value
        assert [s.name for s in m2.signals] == [s.name for s in m1.signals]
        for s1 in m1.signals:
            s2 = m2.get_signal_by_name(s1.name)
            for attr in (
                "start",
                "length",
                "byte_order",
                "is_signed",
                "scale",
                "offset",
                "minimum",
                "maximum",
                "unit",
                "comment",
                "receivers",
            ):
                assert getattr(s2, attr) == getattr(s1, attr), (m1.name, s1.name, attr)
            assert dict(s2.choices or {}) == dict(s1.choices or {})


def _mid_values(message: str) -> dict[str, float]:
    return {s.name: 0.5 * (s.minimum + s.maximum) for s in cat.by_message(message)}


@pytest.mark.parametrize("name", cat.CAN_SIGNALS)
def test_encode_decode_min_max_and_one_step(name, matrix):
    spec = cat.SIGNALS[name]
    res = matrix.resolution(name)
    for value in (spec.minimum, spec.maximum, spec.minimum + res, spec.maximum - res, 0.0):
        values = _mid_values(spec.message)
        values[name] = value
        data = matrix.encode(spec.message, values, counter=0)
        d = matrix.fresh().decode(cat.MESSAGES[spec.message].frame_id, data, 0.0)
        assert d is not None and d.crc_ok and d.status is E2EStatus.OK  # 0 follows the check's initial 14
        assert d.counter == 0
        assert abs(d.values[name] - value) <= 0.5 * res + 1e-9, (name, value, d.values[name])


def test_codec_matches_cantools(db, matrix):
    rng = np.random.default_rng(0)
    for mname in cat.MESSAGES:
        cmsg = db.get_message_by_name(mname)
        codec = matrix.message(mname)
        for counter in range(15):
            dbc_vals = {}
            si = {}
            for s in codec.signals:
                if s.catalogue:
                    spec = cat.SIGNALS[s.catalogue]
                    v = float(rng.uniform(spec.minimum, spec.maximum))
                    si[s.catalogue] = v
                    dbc_vals[s.name] = v * s.si_factor
                else:
                    raw = int(rng.integers(max(s.raw_lo, 0), min(s.raw_hi, 3000) + 1))
                    si[s.name] = raw * s.scale + s.offset
                    dbc_vals[s.name] = si[s.name]
            ours = matrix.encode(mname, si, counter)
            theirs = bytearray(
                cmsg.encode(
                    {**dbc_vals, f"{mname}_CRC": 0, f"{mname}_Counter": counter}, scaling=True, strict=False
                )
            )
            assert bytes(ours[1:]) == bytes(theirs[1:]), mname
            did = cat.MESSAGES[mname].data_id
            assert e2e.p11.e2e_p11_check(bytearray(ours), did)  # autosar-e2e: Profile 11, data ID mode BOTH
            decoded = cmsg.decode(ours, decode_choices=False)
            assert decoded[f"{mname}_Counter"] == counter
            ours_dec = matrix.fresh().decode(cmsg.frame_id, ours, 0.0)
            for s in codec.signals:
                if s.catalogue:
                    assert math.isclose(
                        ours_dec.values[s.catalogue] * s.si_factor, decoded[s.name], abs_tol=1e-9
                    )
                else:
                    assert math.isclose(ours_dec.other[s.name], decoded[s.name], abs_tol=1e-9)


def test_pressure_is_bar_on_can_pa_in_the_codec(matrix, db):
    data = matrix.encode("TPMS_Pressures", {"tyre_pressure_fl_pa": 250_000.0}, 0)
    assert db.decode_message(0x3A0, data)["Pressure_FL"] == pytest.approx(2.5)
    assert matrix.decode(0x3A0, data, 0.0).values["tyre_pressure_fl_pa"] == pytest.approx(250_000.0)


def test_tpms_is_slow_and_each_wheel_can_report_its_sensor_missing(matrix, db):
    """Production TPMS: one frame a second, gauge bar, a per-wheel 'sensor missing' code (SNA); the raw codes
    are those of the earlier kPa layout (0.5 kPa = 0.005 bar per bit), so older logs decode to the same Pa."""
    msg = db.get_message_by_frame_id(0x3A0)
    assert msg.cycle_time == 1000
    assert {s.name: s.unit for s in msg.signals if s.name.startswith("Pressure_")} == {
        f"Pressure_{w}": "bar" for w in ("FL", "FR", "RL", "RR")}
    raw = db.encode_message(0x3A0, {"TPMS_Pressures_CRC": 0, "TPMS_Pressures_Counter": 0, "Pressure_FL": 2.2,
                                    "Pressure_FR": 2.2, "Pressure_RL": 2.2, "Pressure_RR": 2.2}, strict=False)
    assert int.from_bytes(raw, "little") >> 12 & 0x3FF == 440  # 220 kPa at 0.5 kPa per bit, as before
    data = matrix.encode("TPMS_Pressures", {"tyre_pressure_fl_pa": 230_000.0, "tyre_pressure_fr_pa": float("nan"),
                                            "tyre_pressure_rl_pa": 210_000.0, "tyre_pressure_rr_pa": 215_000.0}, 0)
    d = matrix.decode(0x3A0, data, 0.0)
    assert "tyre_pressure_fr_pa" in d.unavailable and "tyre_pressure_fr_pa" not in d.values
    assert d.values["tyre_pressure_fl_pa"] == pytest.approx(230_000.0)


def test_clipping_missing_and_nan_are_sna(matrix):
    data = matrix.encode(
        "IMU_Motion", {"ax_mps2": 1e9, "ay_mps2": float("nan"), "yaw_rate_radps": -math.inf}, 0
    )
    d = matrix.decode(0x080, data, 0.0)
    assert d.values["ax_mps2"] == pytest.approx(20.0)
    assert d.values["yaw_rate_radps"] == pytest.approx(-2.0)
    assert "ay_mps2" not in d.values and d.unavailable == ("ay_mps2",)
    d2 = matrix.decode(0x100, matrix.encode("ESC_WheelSpeeds_F", {"wheel_speed_fl_radps": 12.0}, 0), 0.0)
    assert set(d2.values) == {"wheel_speed_fl_radps"}
    assert set(d2.unavailable) == {"wheel_speed_fr_radps"}


def test_implausible_raw_value_is_rejected(matrix):
    codec = matrix.message("IMU_Motion")
    s = next(x for x in codec.signals if x.catalogue == "ax_mps2")
    data = bytearray(matrix.encode("IMU_Motion", {"ax_mps2": 0.0, "ay_mps2": 0.0, "yaw_rate_radps": 0.0}, 1))
    v = int.from_bytes(data, "little") | ((2047 & s.mask) << s.start)  # 20.47 m/s^2 > 20
    data = bytearray(v.to_bytes(8, "little"))
    from virtsensor.canbus.e2e import data_id_seed, frame_crc

    data[0] = frame_crc(data_id_seed(codec.data_id), data)
    d = matrix.decode(0x080, bytes(data), 0.0)
    assert d.crc_ok and d.implausible == ("ax_mps2",) and "ax_mps2" not in d.values


def test_crc_dlc_and_unknown(matrix):
    good = matrix.encode("PT_Torque", {"motor_torque_nm": 12.3}, 4)
    bad = bytes([good[0] ^ 0x01]) + good[1:]
    d = matrix.decode(0x0C0, bad, 0.0)
    assert not d.crc_ok and d.status is E2EStatus.ERROR and d.values == {}
    short = matrix.decode(0x0C0, good[:7], 0.01)
    assert not short.dlc_ok and short.status is E2EStatus.ERROR
    assert matrix.decode(0x7FF, good, 0.0) is None
    assert matrix.decode(0x0C0, good, 0.0, is_extended=True) is None
    # a payload bit flip is caught too
    flipped = good[:5] + bytes([good[5] ^ 0x10]) + good[6:]
    assert matrix.decode(0x0C0, flipped, 0.02).status is E2EStatus.ERROR


def test_same_payload_other_message_fails_crc(matrix):
    """The data ID makes a frame valid only under its own identifier (masquerade)."""
    data = matrix.encode("ESC_WheelSpeeds_F", {"wheel_speed_fl_radps": 1.0}, 0)
    assert matrix.decode(0x100, data, 0.0).crc_ok
    assert not matrix.decode(0x120, data, 0.0).crc_ok


def test_encode_many_equals_encode(matrix):
    rng = np.random.default_rng(1)
    n = 50
    for mname in cat.MESSAGES:
        codec = matrix.message(mname)
        cols = {}
        for s in codec.signals:
            key = s.catalogue or s.name
            lo = cat.SIGNALS[s.catalogue].minimum if s.catalogue else 0
            hi = cat.SIGNALS[s.catalogue].maximum if s.catalogue else 3
            cols[key] = rng.uniform(lo * 1.1 - 1, hi * 1.1 + 1, n)
            cols[key][::7] = np.nan
        counters = np.arange(n) + 5
        arr = matrix.encode_many(mname, cols, counters)
        for i in range(n):
            assert bytes(arr[i]) == matrix.encode(
                mname, {k: float(v[i]) for k, v in cols.items()}, int(counters[i])
            )


def test_vsens_output_encoding(matrix):
    data = matrix.encode(
        "SAT_FRONT", {"SAT_FL": -12.34, "SAT_FR": 56.78, "SAT_FL_Status": 0, "SAT_FR_Status": 1}, 9
    )
    d = matrix.decode(0x200, data, 0.0)
    assert d.values == {}  # estimates are never mixed with the catalogue's reference SATs
    assert d.other["SAT_FL"] == pytest.approx(-12.34) and d.other["SAT_FR"] == pytest.approx(56.78)
    assert d.other["SAT_FL_Status"] == 0 and d.other["SAT_FR_Status"] == 1


def test_bad_dbc_gives_user_error(tmp_path):
    bad = tmp_path / "bad.dbc"
    bad.write_text('VERSION ""\nBO_ 1 X: 8 Y\n SG_ broken\n')
    with pytest.raises(UserError) as e:
        CanMatrix.load(bad)
    assert str(bad) in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(UserError, match="cannot read"):
        CanMatrix.load(tmp_path / "missing.dbc")


def test_dbc_without_e2e_layout_is_rejected(tmp_path):
    p = tmp_path / "plain.dbc"
    p.write_text('VERSION ""\nBU_: A\nBO_ 16 M: 8 A\n SG_ S : 0|8@1+ (1,0) [0|255] "" Vector__XXX\n')
    with pytest.raises(UserError, match="M_CRC"):
        CanMatrix.load(p)


def test_two_messages_on_one_id_are_refused(tmp_path, capsys):
    """VS_Grip moved onto EPAS_Steering's id: cantools kept one by id with a plain log line, and the daemon sent its
    frames on the steering angle's id. Refused in one line naming both; nothing else printed."""
    text = DBC.read_text().replace(" 514 ", " 160 ")
    p = tmp_path / "dup.dbc"
    p.write_text(text)
    with pytest.raises(UserError) as e:
        CanMatrix.load(p)
    assert str(e.value) == f"{p}: messages EPAS_Steering and VS_Grip share the frame id 0x0A0 (one id, one message)"
    assert capsys.readouterr().err == ""


def test_the_default_matrix_is_the_bundled_package_data():
    from virtsensor.assets import dbc_path

    assert codec_module.DEFAULT_DBC == dbc_path() and dbc_path().samefile(DBC)
    m = CanMatrix.load()
    assert Path(m.source).samefile(DBC)


def test_codec_speed(matrix):
    values = {
        "wheel_speed_fl_radps": 10.0,
        "wheel_speed_fr_radps": 10.1,
        "wheel_speed_rl_radps": 10.2,
        "wheel_speed_rr_radps": 10.3,
    }
    data = matrix.encode("ESC_WheelSpeeds_F", values, 0)
    n = 20000
    t = time.perf_counter()
    for i in range(n):
        matrix.encode("ESC_WheelSpeeds_F", values, i)
    enc = (time.perf_counter() - t) / n
    t = time.perf_counter()
    for _ in range(n):
        matrix.decode(0x100, data, 0.0)
    dec = (time.perf_counter() - t) / n
    # generous bounds (shared CI machines); typical is ~3-4 us each
    assert enc < 50e-6 and dec < 50e-6, (enc, dec)
