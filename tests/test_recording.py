"""CAN logs (virtsensor.recordings.canlog) and the front-end (virtsensor.frontend)."""

from __future__ import annotations

import re
import subprocess
import sys
import uuid
from pathlib import Path

import can
import cantools
import numpy as np
import pytest

from virtsensor import signals as cat
from virtsensor.canbus.codec import CanMatrix
from virtsensor.canbus.e2e import E2EStatus
from virtsensor.errors import UserError
from virtsensor.frontend import SampleHoldStore, to_table
from virtsensor.recordings.canlog import (
    PHASE_STEP_S,
    iter_frames,
    iter_log,
    read_csv,
    read_log,
    write_csv,
    write_log,
)

REPO = Path(__file__).resolve().parents[1]
DBC = REPO / "dbc" / "virtsensor.dbc"
MATRIX = CanMatrix.load()


def synthetic(duration: float = 4.0, dt: float = 0.01, seed: int = 1, names=cat.CAN_SIGNALS):
    """Smooth signals on a 100 Hz grid, held at each message's own cycle (as the simulator does)."""
    n = int(round(duration / dt)) + 1
    t = np.arange(n) * dt
    rng = np.random.default_rng(seed)
    out = {}
    for name in names:
        s = cat.SIGNALS[name]
        mid, amp = 0.5 * (s.minimum + s.maximum), 0.4 * (s.maximum - s.minimum)
        x = mid + amp * np.sin(2 * np.pi * rng.uniform(0.1, 1.0) * t + rng.uniform(0, 6.3))
        cycle = MATRIX.message(MATRIX.message_of(name)).cycle_s
        held = np.floor(t / cycle + 1e-9) * cycle
        out[name] = x[np.searchsorted(t, held + 1e-9, side="right") - 1]
    return t, out


def hold(t: np.ndarray, x: np.ndarray, at: np.ndarray) -> np.ndarray:
    return x[np.searchsorted(t, at + 1e-9, side="right") - 1]


@pytest.fixture(scope="module")
def run():
    return synthetic()


@pytest.mark.parametrize("suffix", [".blf", ".asc", ".log", ".csv", ".trc"])
def test_round_trip_equals_sample_and_hold_of_the_input(tmp_path, run, suffix):
    t, sig = run
    path = tmp_path / f"run{suffix}"
    summary = write_log(path, t, sig)
    assert summary.frames == sum(summary.per_message.values()) > 0
    # ticks 5 ms after the grid: every message's frame of the current slot (phase <= 2.25 ms) is in
    rec = read_log(path, signals=list(sig), t0=0.005)
    assert rec.frames == summary.frames and rec.unknown_frames == 0
    assert rec.e2e_errors == 0
    assert rec.count("OK") == rec.frames  # counters start at 0: even each message's first frame is OK
    assert rec.dropped_ticks == 0
    tt = rec.table["time_s"]
    assert list(rec.table)[0] == "time_s"
    np.testing.assert_allclose(tt, 0.005 + np.arange(tt.size) / 20.0)
    assert tt[-1] > t[-1] - 0.05
    for name, x in sig.items():
        err = np.abs(rec.table[name] - hold(t, x, tt))
        assert err.max() <= 0.5 * MATRIX.resolution(name) + 1e-9, name


def test_default_ticks_see_the_transport_delay(tmp_path, run):
    """With t0=0 a tick at k*50 ms sees a 10 ms message sent at phase > 0 one cycle late."""
    t, sig = run
    path = tmp_path / "run.log"
    write_log(path, t, sig)
    rec = read_log(path, signals=["ax_mps2", "steer_angle_rad"])
    tt = rec.table["time_s"]
    ax = rec.table["ax_mps2"]  # IMU_Motion: phase 0, exactly on the grid
    np.testing.assert_allclose(ax, hold(t, sig["ax_mps2"], tt), atol=0.005 + 1e-9)
    sa = rec.table["steer_angle_rad"]  # EPAS_Steering: phase 0.25 ms -> previous frame
    np.testing.assert_allclose(sa, hold(t, sig["steer_angle_rad"], tt - 0.01), atol=0.0005 + 1e-9)


def test_messages_without_signals_are_not_sent(tmp_path):
    t, sig = synthetic(1.0, names=[n for n in cat.CAN_SIGNALS if "pressure" not in n])
    path = tmp_path / "nopress.blf"
    summary = write_log(path, t, sig)
    assert "TPMS_Pressures" not in summary.per_message
    ids = {m.arbitration_id for m in can.LogReader(path)}
    assert 0x3A0 not in ids and 0x080 in ids
    assert 0x200 not in ids and 0x201 not in ids  # VSENS outputs are not simulated


def test_frame_schedule_counters_and_phases(run):
    t, sig = run
    frames = list(iter_frames(t, sig))
    ts = np.array([f.timestamp for f in frames])
    assert np.all(np.diff(ts) > 0), "no two frames share a timestamp"
    by_id: dict[int, list] = {}
    for f in frames:
        by_id.setdefault(f.arbitration_id, []).append(f)
    ranks = sorted(m.frame_id for m in MATRIX.messages.values())
    for fid, fs in by_id.items():
        m = MATRIX.by_id[fid]
        times = np.array([f.timestamp for f in fs])
        np.testing.assert_allclose(times, np.arange(len(fs)) * m.cycle_s + ranks.index(fid) * PHASE_STEP_S)
        counters = np.array([f.data[1] & 0xF for f in fs])
        assert counters[0] == 0 and counters.max() == min(14, len(fs) - 1)  # Profile 11: 0..14 (TPMS: 1 frame/s)
        assert np.all(np.diff(counters) % 15 == 1)
        assert all(len(f.data) == 8 and not f.is_extended_id for f in fs)


def _tamper(frames, fid, index, how):
    """Frames with the index-th frame of id ``fid`` corrupted ('crc') or removed ('drop')."""
    out, k = [], -1
    for f in frames:
        if f.arbitration_id == fid:
            k += 1
            if k == index:
                if how == "drop":
                    continue
                data = bytearray(f.data)
                data[0] ^= 0xFF
                f = can.Message(
                    timestamp=f.timestamp, arbitration_id=fid, data=bytes(data), is_extended_id=False
                )
        out.append(f)
    return out


def _write(path, frames):
    with can.Logger(path) as w:
        for f in frames:
            w.on_message_received(f)


@pytest.mark.parametrize("suffix", [".blf", ".asc", ".log"])
def test_crc_error_skipped_counter_and_unknown_frames_are_counted(tmp_path, run, suffix):
    t, sig = run
    frames = list(iter_frames(t, sig))
    frames = _tamper(frames, 0x080, 10, "crc")
    frames = _tamper(frames, 0x0A0, 20, "drop")  # the counter of the next EPAS frame skips one value
    unknown = [
        can.Message(timestamp=0.0031 + 0.1 * i, arbitration_id=0x7AB, data=b"\x01\x02", is_extended_id=False)
        for i in range(7)
    ]
    frames = sorted(frames + unknown, key=lambda f: f.timestamp)
    path = tmp_path / f"bad{suffix}"
    _write(path, frames)
    rec = read_log(path, signals=["ax_mps2", "steer_angle_rad"])
    assert rec.unknown_frames == 7
    assert rec.count(E2EStatus.ERROR, "IMU_Motion") == 1
    # the frame after the rejected one is two counter steps after the last intact one
    assert rec.count(E2EStatus.OKSOMELOST, "IMU_Motion") == 1
    assert rec.count(E2EStatus.OKSOMELOST, "EPAS_Steering") == 1
    assert rec.count("ERROR") == 1 and rec.count("OKSOMELOST") == 2 and rec.count("WRONGSEQUENCE") == 0
    assert rec.e2e_errors == 3


def test_vectorised_and_online_front_end_agree_exactly(run):
    t, sig = run
    frames = _tamper(list(iter_frames(t, sig)), 0x100, 5, "crc")
    frames = _tamper(frames, 0x3A0, 3, "drop")
    m = MATRIX.fresh()
    decoded = [m.decode(f.arbitration_id, f.data, f.timestamp) for f in frames]
    names = list(cat.TABLE_COLUMNS[1:]) + ["tyre_pressure_fl_pa"]
    for t0 in (None, 0.0, 0.0123):
        a = to_table(decoded, names, 20.0, t0)
        b = to_table(decoded, names, 20.0, t0, online=True)
        assert a.dropped_ticks == b.dropped_ticks and a.ticks == b.ticks
        assert list(a.table) == list(b.table) == ["time_s", *names]
        for k in a.table:
            np.testing.assert_array_equal(a.table[k], b.table[k])
    # shuffled input is replayed in time order
    rng = np.random.default_rng(0)
    shuffled = [decoded[i] for i in rng.permutation(len(decoded))]
    c = to_table(shuffled, names, 20.0, 0.0)
    d = to_table(decoded, names, 20.0, 0.0)
    for k in c.table:
        np.testing.assert_array_equal(c.table[k], d.table[k])


def test_front_end_drops_ticks_until_every_signal_is_seen(run):
    t, sig = run
    frames = [f for f in iter_frames(t, sig) if not (f.arbitration_id == 0x3A0 and f.timestamp < 0.5)]
    m = MATRIX.fresh()
    decoded = [m.decode(f.arbitration_id, f.data, f.timestamp) for f in frames]
    b = to_table(decoded, ["ax_mps2", "tyre_pressure_fl_pa"], 20.0, 0.0)
    # TPMS (1 s, phase 2 ms) first seen at 1.002 s with counter 1: 2 steps after the Profile 11 check's initial
    # counter 14 (within MaxDeltaCounter 3): OKSOMELOST, usable; ticks 0.00 .. 1.00 are dropped
    assert [d.status for d in decoded if d.frame_id == 0x3A0][:1] == [E2EStatus.OKSOMELOST]
    assert b.dropped_ticks == 21
    assert b.table["time_s"][0] == pytest.approx(1.05)
    assert b.ticks == b.dropped_ticks + b.table["time_s"].size


def test_sample_hold_store():
    store = SampleHoldStore(["ax_mps2", "vx_mps"])
    v, age = store.sample(1.0)
    assert np.isnan(v).all() and np.isinf(age).all() and not store.complete
    m = MATRIX.fresh()
    f = m.decode(0x080, MATRIX.encode("IMU_Motion", {"ax_mps2": 1.5}, 0), 0.25)
    assert store.update(f) == 1
    bad = m.decode(0x080, b"\x00" * 8, 0.3)  # CRC error: not stored
    assert store.update(bad) == 0
    v, age = store.sample(1.0)
    assert v[0] == pytest.approx(1.5) and age[0] == pytest.approx(0.75) and np.isnan(v[1])


def test_truncated_blf_names_file_and_position(tmp_path, run):
    t, sig = run
    path = tmp_path / "cut.blf"
    write_log(path, t, sig)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError) as e:
        read_log(path)
    msg = str(e.value)
    assert str(path) in msg and "byte offset" in msg and "frame" in msg and "\n" not in msg


def test_corrupt_blf_names_file(tmp_path, run):
    t, sig = run
    path = tmp_path / "corrupt.blf"
    write_log(path, t, sig)
    data = bytearray(path.read_bytes())
    data[200:240] = b"\xab" * 40  # inside the first container
    path.write_bytes(bytes(data))
    with pytest.raises(UserError) as e:
        read_log(path)
    assert str(path) in str(e.value)


def test_not_a_blf(tmp_path):
    path = tmp_path / "text.blf"
    path.write_text("hello")
    with pytest.raises(UserError, match="text.blf"):
        read_log(path)


def test_garbage_asc_line_names_the_line(tmp_path, run):
    t, sig = run
    path = tmp_path / "g.asc"
    write_log(path, t, sig)
    lines = path.read_text().splitlines(keepends=True)
    lines.insert(20, "this is not a CAN frame\n")
    path.write_text("".join(lines))
    with pytest.raises(UserError) as e:
        read_log(path)
    assert str(path) in str(e.value) and "line 21" in str(e.value)


def test_bad_bytes_in_asc_frame_name_the_line(tmp_path, run):
    t, sig = run
    path = tmp_path / "b.asc"
    write_log(path, t, sig)
    lines = path.read_text().splitlines(keepends=True)
    i = next(k for k, ln in enumerate(lines) if " Rx " in ln) + 3
    lines[i] = lines[i].rsplit(" ", 1)[0] + " ZZ\n"
    path.write_text("".join(lines))
    with pytest.raises(UserError) as e:
        read_log(path)
    assert f"line {i + 1}" in str(e.value)


def test_garbage_candump_line_names_the_line(tmp_path, run):
    t, sig = run
    path = tmp_path / "g.log"
    write_log(path, t, sig)
    lines = path.read_text().splitlines(keepends=True)
    lines.insert(4, "garbage\n")
    path.write_text("".join(lines))
    with pytest.raises(UserError, match="line 5"):
        list(iter_log(path))


def test_garbage_trc_line_names_the_line_and_python_can_stays_quiet(tmp_path, run, caplog):
    """python-can's TRC reader warns about a line it cannot parse and drops the frame: the read fails instead,
    with our one line, and the warning does not reach stderr."""
    t, sig = run
    path = tmp_path / "g.trc"
    write_log(path, t, sig)
    lines = path.read_text().splitlines(keepends=True)
    i = next(k for k, ln in enumerate(lines) if not ln.startswith(";")) + 3
    lines.insert(i, "garbage\n")
    path.write_text("".join(lines))
    with pytest.raises(UserError, match=f"line {i + 1}: unparsable line 'garbage'"):
        list(iter_log(path))
    assert not [r for r in caplog.records if r.name.startswith("can")]  # (pytest holds what would go to stderr)


def test_an_empty_trc_is_refused_without_python_cans_warning(tmp_path, caplog):
    path = tmp_path / "empty.trc"
    path.write_bytes(b"")
    for read in (lambda p: list(iter_log(p)), read_log):
        with pytest.raises(UserError, match="empty.trc: the file is empty"):
            read(path)
    assert not [r for r in caplog.records if r.name.startswith("can")]


def test_unsupported_and_missing_files(tmp_path, run):
    t, sig = run
    with pytest.raises(UserError, match="unsupported"):
        write_log(tmp_path / "x.mdf", t, sig)
    with pytest.raises(UserError, match="no such log file"):
        read_log(tmp_path / "missing.blf")


def test_requested_signal_never_received(tmp_path):
    t, sig = synthetic(1.0, names=["ax_mps2", "ay_mps2", "yaw_rate_radps"])
    path = tmp_path / "imu.log"
    write_log(path, t, sig)
    with pytest.raises(UserError, match="vx_mps"):
        read_log(path, signals=["ax_mps2", "vx_mps"])
    rec = read_log(path)  # default: the table columns present
    assert rec.signals == ("ax_mps2", "ay_mps2", "yaw_rate_radps")
    assert "vx_mps" in rec.missing_signals


# ------------------------------------------------------------------ interoperability with other tools
def test_our_log_decodes_with_plain_python_can_and_cantools(tmp_path, run):
    t, sig = run
    path = tmp_path / "interop.blf"
    write_log(path, t, sig)
    db = cantools.database.load_file(str(DBC))
    ours = MATRIX.fresh()
    n = 0
    for msg in can.LogReader(path):
        theirs = db.decode_message(msg.arbitration_id, msg.data, decode_choices=False)
        d = ours.decode(msg.arbitration_id, msg.data, msg.timestamp)
        for cname, v in d.values.items():
            s = cat.SIGNALS[cname]
            factor = 1e-5 if s.unit == "Pa" else 1.0  # pressures: bar on CAN
            assert theirs[s.dbc_signal] == pytest.approx(v * factor, abs=1e-9)
        n += 1
    assert n > 1000


def test_cantools_decode_reads_our_candump_log(tmp_path, run):
    t, sig = run
    path = tmp_path / "cd.log"
    write_log(path, t, sig)
    head = "".join(path.read_text().splitlines(keepends=True)[:20])
    r = subprocess.run(
        [sys.executable, "-m", "cantools", "decode", str(DBC)],
        input=head,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    first = next(iter(can.LogReader(path)))
    ax = MATRIX.fresh().decode(first.arbitration_id, first.data, 0.0).values["ax_mps2"]
    assert "IMU_Motion(" in r.stdout and f"AccelLong: {ax:g} m/s^2" in r.stdout
    assert "WhlSpd_FL:" in r.stdout and "Pressure_FL:" in r.stdout


def test_python_can_player_plays_our_log(tmp_path):
    t, sig = synthetic(0.2)
    path = tmp_path / "short.asc"
    write_log(path, t, sig)
    h = subprocess.run(
        [sys.executable, "-m", "can.player", "--help"], capture_output=True, text=True, timeout=60
    )
    assert h.returncode == 0
    r = subprocess.run(
        [sys.executable, "-m", "can.player", "-i", "virtual", "-c", f"vs-{uuid.uuid4().hex}", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr


# ------------------------------------------------------------------------------- canonical CSV table
def test_csv_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    table = {"time_s": np.arange(50) / 20.0, **{n: rng.normal(size=50) for n in cat.INPUTS}}
    table["ax_mps2"][3] = np.nan
    path = tmp_path / "t.csv"
    write_csv(path, table)
    back = read_csv(path)
    assert list(back) == list(table)
    for k in table:
        np.testing.assert_array_equal(back[k], table[k])
    assert path.read_text().splitlines()[0] == ",".join(table)


def test_a_csv_with_a_byte_order_mark_reads_as_without(tmp_path):
    """A spreadsheet's "CSV UTF-8" starts with a byte-order mark: it is no part of the first column's name."""
    p = tmp_path / "bom.csv"
    p.write_bytes(b"\xef\xbb\xbftime_s,ax_mps2\n0.0,1.0\n0.05,2.0\n")
    back = read_csv(p)
    assert list(back) == ["time_s", "ax_mps2"] and back["ax_mps2"].tolist() == [1.0, 2.0]


def test_csv_errors_name_file_and_line(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("time_s,ax_mps2\n0.0,1.0\n0.05,oops\n")
    with pytest.raises(UserError, match=r"bad\.csv:3: column ax_mps2: 'oops' is not a number"):
        read_csv(p)
    p.write_text("time_s,ax_mps2\n0.0,1.0\n,2.0\n")
    with pytest.raises(UserError, match=r"bad\.csv:3: column time_s: '' is not a number"):
        read_csv(p)
    p.write_text("time_s,ax_mps2\n0.0,1.0\n0.05\n")
    with pytest.raises(UserError, match=r"bad\.csv:3: expected 2 fields, got 1"):
        read_csv(p)
    p.write_text("time_s,not_a_signal\n0,1\n")
    with pytest.raises(UserError, match=r"bad\.csv:1: unknown column 'not_a_signal'"):
        read_csv(p)


@pytest.mark.parametrize(("data", "where"), [
    (b"time_s,ax_mps2\n0.0,1.0\n0.05,\xe9\n", r"bad\.csv:3: not UTF-8 text \(byte 0xe9 at byte offset 28\)"),
    ("time_s,ax_mps2é\n0.0,1.0\n".encode("latin-1"), r"bad\.csv:1: not UTF-8 text \(byte 0xe9 at byte offset 14\)"),
    (b"LOGG\x90\x00\x00\x00\x01\x02", r"bad\.csv:1: not UTF-8 text \(byte 0x90 at byte offset 4\)"),  # a BLF
])
def test_a_csv_that_is_not_utf8_names_file_line_and_byte(tmp_path, data, where):
    p = tmp_path / "bad.csv"
    p.write_bytes(data)
    with pytest.raises(UserError, match=where):
        read_csv(p)


def test_phase_override(run):
    t, sig = run
    frames = list(iter_frames(t, sig, phases={"ESC_WheelSpeeds_F": 0.011}))
    ts = np.array([f.timestamp for f in frames if f.arbitration_id == 0x100])
    np.testing.assert_allclose(ts[:3], [0.011, 0.031, 0.051])
    # a frame sent at 0.011 carries the sample of 0.01 (the latest at or before it)
    d = MATRIX.fresh().decode(0x100, next(f for f in frames if f.arbitration_id == 0x100).data, 0.0)
    idx = int(np.searchsorted(t, 0.011, side="right") - 1)
    assert d.values["wheel_speed_fl_radps"] == pytest.approx(sig["wheel_speed_fl_radps"][idx], abs=0.025)
    with pytest.raises(ValueError, match="phase"):
        list(iter_frames(t, sig, phases={"ESC_WheelSpeeds_F": 0.02}))


@pytest.mark.parametrize("suffix", [".asc", ".log", ".trc", ".csv"])
def test_binary_data_named_as_a_text_log_is_refused_as_such(tmp_path, suffix):
    """Random bytes are no text log: said so, not taken for a log cut mid-record."""
    path = tmp_path / f"garbled{suffix}"
    path.write_bytes(np.random.default_rng(1).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(UserError, match=f"garbled{suffix}: not a \\{suffix} CAN log: binary data"):
        list(iter_log(path))


# ------------------------------------------------------------------------------- one run's time
def _restamped(frames, stamps):
    return [can.Message(timestamp=float(s), arbitration_id=f.arbitration_id, data=bytes(f.data),
                        is_extended_id=False) for f, s in zip(frames, stamps, strict=True)]


@pytest.mark.parametrize("where", ["last", "first"])
def test_a_log_whose_clock_jumps_is_refused_naming_the_jump(tmp_path, run, where):
    """One frame stamped in Unix time among frames counted from 0 (a logger's clock that jumped): refused, naming
    the file and the time of the jump (and, when the time goes back after it, the frame), instead of building a
    tick grid of 34 billion ticks (253 GiB)."""
    t, sig = run
    path = tmp_path / "jump.log"
    write_log(path, t, sig)
    lines = path.read_text().splitlines(keepends=True)
    last = lines[-1]
    stamped = "(1700000000.000000)" + last[last.index(")") + 1:]
    lines = lines + [stamped] if where == "last" else [stamped, *lines]
    path.write_text("".join(lines))
    first, end = float(lines[1 if where == "first" else 0][1:9]), float(last[1:last.index(")")])
    with pytest.raises(UserError) as e:
        read_log(path)
    message = str(e.value)
    if where == "last":
        assert message.startswith(f"{path}: its time jumps forward by 1.7e+09 s, from {end:.6f} s to "
                                  "1700000000.000000 s, between consecutive frames"), message
    else:
        # (the file reader names the frame whose time goes back, before the front-end sees the jump)
        assert message.startswith(f"{path}: frame 1 at line 2 goes back in time 1.7e+09 s, from 1700000000.000000 s "
                                  f"to {first:.6f} s"), message
    assert "\n" not in message


def test_a_minute_without_frames_or_more_than_12_hours_is_not_one_run(run):
    """The front-end's limits (frontend.MAX_GAP_S, MAX_SPAN_S), on both of its paths: a silence just over a minute
    is refused and one just under it is read; frames 50 s apart over 13 h are refused for the span alone; the
    tick grid itself refuses to grow past 12 h whoever asks for it."""
    from virtsensor.frontend import MAX_GAP_S, MAX_SPAN_S, tick_times

    t, sig = run
    frames = list(iter_frames(t, sig))
    names = ["ax_mps2", "steer_angle_rad"]

    def table(stamps, online=False):
        m = MATRIX.fresh()
        decoded = [m.decode(f.arbitration_id, f.data, f.timestamp) for f in _restamped(frames, stamps)]
        return to_table(decoded, names, 20.0, online=online, source="x.log")

    stamps = np.array([f.timestamp for f in frames])
    half = len(stamps) // 2
    for online in (False, True):
        assert table(np.where(np.arange(len(stamps)) >= half, stamps + MAX_GAP_S - 1.0, stamps), online).ticks > 0
        with pytest.raises(UserError, match=r"^x\.log: its time jumps forward by 6\d\.\d+ s, from "):
            table(np.where(np.arange(len(stamps)) >= half, stamps + MAX_GAP_S + 1.0, stamps), online)
        with pytest.raises(UserError, match=r"^x\.log: its frames span 46800 s \(from 0\.000000 s to 46800\.000000 "
                                            r"s\); one run lasts at most 12 h"):
            table(np.linspace(0.0, 13 * 3600.0, len(stamps)), online)
    with pytest.raises(UserError, match="longer than one run"):
        tick_times(0.0, 1e12, 20.0)
    assert len(tick_times(0.0, MAX_SPAN_S, 20.0)) == MAX_SPAN_S * 20 + 1


def test_a_log_whose_time_goes_back_is_refused_and_a_little_disorder_is_read(tmp_path, run):
    """A frame stamped more than one tick (frontend.MAX_BACK_S) before the latest before it: a clock set back, or
    two logs joined; the tables would interleave two stretches of driving. A merged logger's few ms of disorder
    are read, in time order, as the log in order is."""
    from virtsensor.frontend import MAX_BACK_S
    from virtsensor.recordings.canlog import read_log

    t, sig = run
    plain = tmp_path / "ok.log"
    write_log(plain, t, sig)
    lines = plain.read_text().splitlines(keepends=True)
    k = len(lines) // 2

    def variant(name: str, swap_s: float) -> Path:
        out = list(lines)
        stamp = float(out[k][1:].split(")", 1)[0])
        out[k] = f"({stamp + swap_s:.6f})" + out[k].split(")", 1)[1]  # frame k stamped later than frame k + 1
        path = tmp_path / name
        path.write_text("".join(out))
        return path

    little = variant("little.log", 0.004)
    assert read_log(little).table["time_s"].size == read_log(plain).table["time_s"].size
    far = variant("far.log", MAX_BACK_S + 0.2)
    with pytest.raises(UserError, match=rf"^{re.escape(str(far))}: frame {k + 1} at line {k + 2} goes back in time "):
        read_log(far)


@pytest.mark.parametrize("damage", ["gzip cut", "text cut", "not gzip", "corrupt"])
def test_a_gz_log_is_checked_whole_before_its_first_frame(tmp_path, run, damage):
    """A ``.asc.gz`` log gets the checks of a plain one, and its compressed data is read through first: a gzip
    stream cut short (``head -c``), a text cut mid-record and then compressed, plain text named ``.gz``, corrupt
    compressed data. Each is refused before any frame is yielded, naming the file and where."""
    import gzip
    import re
    import zlib

    t, sig = run
    plain = tmp_path / "run.asc"
    write_log(plain, t, sig)
    text = plain.read_bytes()
    packed = gzip.compress(text)
    path = tmp_path / "run.asc.gz"
    path.write_bytes({"gzip cut": packed[: len(packed) // 2], "text cut": gzip.compress(text[: len(text) // 2]),
                      "not gzip": text, "corrupt": packed[:200] + bytes(64) + packed[264:]}[damage])
    frames = iter_log(path)
    with pytest.raises(UserError) as e:
        next(frames)
    message = str(e.value)
    assert message.startswith(f"{path}: ") and "\n" not in message, message
    if damage in ("gzip cut", "text cut"):
        cut = r"the gzip stream is cut, its text ends inside line" if damage == "gzip cut" else r"line \d+ is cut"
        m = re.search(rf"truncated: {cut}.*; the last good frame is frame (\d+), timestamp (\d+\.\d+) s", message)
        assert m, message
        # every frame before the cut counts: the last good one is the last complete line's
        if damage == "gzip cut":
            readable = zlib.decompressobj(wbits=31).decompress(packed[: len(packed) // 2])
        else:
            readable = text[: len(text) // 2]
        complete = readable[: readable.rindex(b"\n")].decode().splitlines()
        stamps = [ln.split()[0] for ln in complete if " Rx " in ln]
        assert (int(m.group(1)), m.group(2)) == (len(stamps) - 1, stamps[-1]), message
    elif damage == "not gzip":
        assert "not a .asc.gz CAN log: not gzip-compressed" in message, message
    else:
        assert "not a .asc.gz CAN log: corrupt compressed data after line 0" in message, message


def test_a_hole_in_a_message_leaves_its_signals_stale_as_the_daemon_finds_them(tmp_path, run):
    """A message silent for 1 s (a logger gap, a sensor off): its signals are NaN at every tick where their latest
    frame is older than its timeout (INPUT_TIMEOUT_CYCLES cycles, the daemon's rule: fresh while age <= timeout),
    held before that; the other messages' signals are untouched; the vectorised and the online front-end agree."""
    t, sig = run
    imu = MATRIX.message_of("ax_mps2")
    imu_id, cycle = MATRIX.message(imu).frame_id, MATRIX.message(imu).cycle_s
    frames = [f for f in iter_frames(t, sig) if not (f.arbitration_id == imu_id and 1.5 <= f.timestamp < 2.5)]
    path = tmp_path / "hole.log"
    with can.Logger(str(path)) as out:
        for f in frames:
            out.on_message_received(f)
    rec = read_log(path, signals=["ax_mps2", "steer_angle_rad"])
    tt, ax = rec.table["time_s"], rec.table["ax_mps2"]
    sent = np.array(sorted(f.timestamp for f in frames if f.arbitration_id == imu_id))
    sent = np.delete(sent, np.searchsorted(sent, 2.5 - 1e-6))  # (the first frame after the hole fails the E2E
    # sequence check, 100 frames lost: not usable)
    latest = sent[np.searchsorted(sent, tt + 1e-6, side="right") - 1]  # (each tick's latest IMU frame)
    stale = tt - latest > cat.INPUT_TIMEOUT_CYCLES * cycle + 1e-6
    assert stale.sum() >= 18 and np.isnan(ax[stale]).all() and np.isfinite(ax[~stale]).all()
    assert np.isfinite(rec.table["steer_angle_rad"]).all()
    m = MATRIX.fresh()
    decoded = [m.decode(f.arbitration_id, f.data, f.timestamp) for f in frames]
    age = {"ax_mps2": cat.INPUT_TIMEOUT_CYCLES * cycle}
    a = to_table(decoded, ["ax_mps2", "steer_angle_rad"], 20.0, 0.0, max_age=age)
    b = to_table(decoded, ["ax_mps2", "steer_angle_rad"], 20.0, 0.0, online=True, max_age=age)
    for k in a.table:
        np.testing.assert_array_equal(a.table[k], b.table[k])
    assert np.isnan(a.table["ax_mps2"]).sum() == np.isnan(b.table["ax_mps2"]).sum() >= 18
    held = to_table(decoded, ["ax_mps2"], 20.0, 0.0)  # (without max_age: held however old)
    assert np.isfinite(held.table["ax_mps2"]).all()
