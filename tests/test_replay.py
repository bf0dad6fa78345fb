"""Replay of CAN logs onto a python-can bus (virtsensor.recordings.replay, ``virtsensor replay``).

Only the in-process ``virtual`` interface is used; every test has its own channel name.
"""

from __future__ import annotations

import os
import sys
import threading
import uuid

import can
import numpy as np
import pytest

from virtsensor import cli
from virtsensor import signals as cat
from virtsensor.canbus.codec import CanMatrix
from virtsensor.errors import UserError
from virtsensor.recordings.canlog import iter_frames, write_log
from virtsensor.recordings.replay import parse_rate, replay

MATRIX = CanMatrix.load()


def synthetic(duration: float, dt: float = 0.01):
    n = int(round(duration / dt)) + 1
    t = np.arange(n) * dt
    sig = {}
    for i, name in enumerate(cat.CAN_SIGNALS):
        s = cat.SIGNALS[name]
        sig[name] = 0.5 * (s.minimum + s.maximum) + 0.3 * (s.maximum - s.minimum) * np.sin(0.7 * t + i)
    return t, sig


class Receiver:
    """A second virtual bus on the same channel, collecting frames in a thread."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames: list[can.Message] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            m = self.bus.recv(0.05)
            if m is not None:
                self.frames.append(m)

    def close(self, expect: int | None = None, timeout: float = 5.0) -> list[can.Message]:
        if expect is not None:
            deadline = threading.Event()
            for _ in range(int(timeout / 0.01)):
                if len(self.frames) >= expect:
                    break
                deadline.wait(0.01)
        self._stop.set()
        self._thread.join()
        self.bus.shutdown()
        return self.frames


@pytest.fixture()
def channel():
    return f"virtsensor-test-{uuid.uuid4().hex}"


@pytest.fixture(scope="module")
def frames():
    t, sig = synthetic(10.0)
    return list(iter_frames(t, sig))


def _timed_run(frames, channel):
    rx = Receiver(channel)
    tx = can.Bus(interface="virtual", channel=channel)
    try:
        summary = replay(frames, tx, rate=1.0)
    finally:
        tx.shutdown()
    return summary, rx.close(expect=len(frames))


@pytest.mark.slow
@pytest.mark.realtime
def test_real_time_replay_timing(frames, channel):
    """p99 inter-frame timing error < 2 ms at the receiver, over 10 s of frames at rate 1.0.

    A shared (virtual) machine can stall a process for several milliseconds a
    few times in 10 s regardless of the player, and an overloaded one (CI beside
    a training job) for longer; a run hit by such stalls is repeated (at most 5
    runs: on 2026-11-28 three runs in a row read p99 3.4-6.1 ms with p50 0.01 ms,
    and the next invocation passed at once). Drift or a sleep-only player would
    fail every run.
    """
    if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
        pytest.skip("measures real-time timing, which the other workers' tests upset: run it with -n 0")
    ts = np.array([f.timestamp for f in frames])
    assert ts[-1] - ts[0] > 9.9
    runs: list[tuple[float, float]] = []
    for attempt in range(5):
        summary, got = _timed_run(frames, f"{channel}-{attempt}")
        assert summary.frames_sent == len(frames) == len(got)
        assert summary.unknown_frames == 0 and summary.rate == 1.0
        assert [m.arbitration_id for m in got] == [f.arbitration_id for f in frames]
        assert summary.duration_s == pytest.approx(ts[-1] - ts[0], abs=0.05)  # no accumulated drift
        rt = np.array([m.timestamp for m in got])  # stamped by the bus when the frame is sent
        err_ms = np.abs((rt - rt[0]) - (ts - ts[0])) * 1e3
        p50, p99 = float(np.percentile(err_ms, 50)), float(np.percentile(err_ms, 99))
        runs.append((round(p50, 3), round(p99, 3)))
        if p50 < 0.5 and p99 < 2.0:
            assert summary.timing_error_p50_ms < 0.5
            return
    pytest.fail(f"receiver timing error (p50, p99) >= (0.5, 2) ms in every run: {runs}")


def test_rate_max_sends_everything_unchanged(frames, channel):
    part = frames[:2000]
    rx = Receiver(channel)
    tx = can.Bus(interface="virtual", channel=channel)
    try:
        summary = replay(part, tx, rate="max")
    finally:
        tx.shutdown()
    got = rx.close(expect=len(part))
    assert summary.rate is None and summary.timing_error_p50_ms is None
    assert summary.frames_sent == len(part) == len(got)
    assert summary.duration_s < 0.5 * (part[-1].timestamp - part[0].timestamp)
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [
        (f.arbitration_id, bytes(f.data)) for f in part
    ]


def test_unknown_frames_pass_through_and_are_counted(frames, channel):
    extra = [
        can.Message(
            timestamp=0.0001 + 0.001 * i, arbitration_id=0x7AB, data=bytes([i, 2, 3]), is_extended_id=False
        )
        for i in range(5)
    ]
    ext = can.Message(timestamp=0.0002, arbitration_id=0x080, data=b"\x00" * 8, is_extended_id=True)
    mixed = sorted(frames[:300] + extra + [ext], key=lambda f: f.timestamp)
    rx = Receiver(channel)
    tx = can.Bus(interface="virtual", channel=channel)
    try:
        summary = replay(mixed, tx, rate=4.0)
    finally:
        tx.shutdown()
    got = rx.close(expect=len(mixed))
    assert summary.unknown_frames == 6
    assert summary.frames_sent == len(mixed) == len(got)
    unknown_rx = [m for m in got if m.arbitration_id == 0x7AB]
    assert [bytes(m.data) for m in unknown_rx] == [bytes(f.data) for f in extra]
    assert any(m.is_extended_id and m.arbitration_id == 0x080 for m in got)


def test_replay_from_file_with_loop(tmp_path, channel):
    t, sig = synthetic(0.3)
    path = tmp_path / "short.blf"
    written = write_log(path, t, sig)
    rx = Receiver(channel)
    tx = can.Bus(interface="virtual", channel=channel)
    try:
        summary = replay(path, tx, rate=2.0, loop=True, max_loops=2)
    finally:
        tx.shutdown()
    got = rx.close(expect=2 * written.frames)
    assert summary.loops == 2 and summary.frames_sent == 2 * written.frames == len(got)
    # the second pass follows the first on the same time line (0.3 s / 2 per pass)
    assert summary.duration_s == pytest.approx(2 * 0.3 / 2.0, abs=0.03)


def test_parse_rate():
    assert parse_rate("max") is None and parse_rate("MAX") is None
    assert parse_rate("2.5") == 2.5
    for bad in ("0", "-1", "fast", "nan"):
        with pytest.raises(UserError):
            parse_rate(bad)


def test_cli_replay_virtual(tmp_path, channel, capsys):
    t, sig = synthetic(0.5)
    path = tmp_path / "cli.asc"
    written = write_log(path, t, sig)
    rx = Receiver(channel)
    rc = cli.main(
        ["replay", str(path), "--interface", "virtual", "--channel", channel, "--rate", "max", "--quiet"]
    )
    got = rx.close(expect=written.frames)
    assert rc == 0
    assert len(got) == written.frames
    out = capsys.readouterr().out
    assert f"frames sent: {written.frames}" in out and "frames per second" in out


def test_cli_unknown_interface_lists_valid_ones(tmp_path, capsys):
    (tmp_path / "x.blf").write_bytes(b"")  # a log file is there: the interface is what is wrong
    rc = cli.main(["replay", str(tmp_path / "x.blf"), "--interface", "nosuchbus", "--channel", "c0"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "nosuchbus" in err and "socketcan" in err and "virtual" in err and "Traceback" not in err


def test_cli_bad_rate_and_missing_file(tmp_path, capsys, channel):
    assert (
        cli.main(["replay", "x.blf", "--interface", "virtual", "--channel", channel, "--rate", "fast"]) == 2
    )
    assert "--rate" in capsys.readouterr().err
    missing = tmp_path / "missing.blf"
    assert cli.main(["replay", str(missing), "--interface", "virtual", "--channel", channel]) == 2
    assert str(missing) in capsys.readouterr().err
    assert cli.main(["replay", "--interface", "virtual", "--channel", channel]) == 2


@pytest.mark.parametrize("suffix", [".log", ".trc", ".blf", ".asc"])
def test_cli_refuses_an_empty_log_in_one_line(tmp_path, capsys, channel, suffix):
    """A zero-byte log has no frame to play: one line, exit 2 (no "frames sent: 0"), no python-can warning."""
    path = tmp_path / f"empty{suffix}"
    path.write_bytes(b"")
    rc = cli.main(["replay", str(path), "--interface", "virtual", "--channel", channel, "--rate", "max", "-q"])
    out, err = capsys.readouterr()
    assert rc == 2 and out == ""
    assert err.count("\n") == 1 and str(path) in err and "Traceback" not in err, err
    assert "the file is empty" in err, err


def test_manoeuvre_without_simulator(monkeypatch, capsys, channel):
    monkeypatch.setitem(sys.modules, "sim.api", None)  # import fails
    rc = cli.main(["replay", "--manoeuvre", "steering-pulse", "--interface", "virtual", "--channel", channel])
    assert rc == 2
    assert "the simulator is not available" in capsys.readouterr().err
    monkeypatch.delitem(sys.modules, "sim.api")
    monkeypatch.setitem(sys.modules, "scipy", None)  # (the base install: the simulator's packages are absent)
    for name in [m for m in sys.modules if m == "sim" or m.startswith(("sim.", "scipy."))]:
        monkeypatch.delitem(sys.modules, name)
    rc = cli.main(["replay", "--manoeuvre", "steering-pulse", "--interface", "virtual", "--channel", channel])
    err = capsys.readouterr().err
    assert rc == 2 and "needs the optional extra 'train'" in err and err.count("\n") == 1, err


def test_replay_simulates_a_manoeuvre_on_the_fly(channel, capsys):
    rx = Receiver(channel)
    rc = cli.main(["replay", "--manoeuvre", "steering-pulse", "--speed", "50", "--mu", "0.4", "--seed", "7",
                   "--interface", "virtual", "--channel", channel, "--rate", "max", "--quiet"])
    got = rx.close(expect=1000)
    assert rc == 0
    assert len(got) > 1000 and {m.arbitration_id for m in got} >= {0x080, 0x0A0, 0x100, 0x600}
    # the steering pulse is on the bus: decode the EPAS frames and find the pulse
    matrix = CanMatrix.load()
    angles = [matrix.decode(m.arbitration_id, bytes(m.data), m.timestamp).values["steer_angle_rad"]
              for m in got if m.arbitration_id == 0x0A0]
    assert max(abs(a) for a in angles) > 0.05
    assert "frames sent" in capsys.readouterr().out


def test_replay_refuses_a_bad_manoeuvre(channel, capsys):
    rc = cli.main(["replay", "--manoeuvre", "moonwalk", "--interface", "virtual", "--channel", channel])
    assert rc == 2
    assert "unknown manoeuvre 'moonwalk'" in capsys.readouterr().err


def test_a_20hz_table_is_not_replayed_as_a_can_log(tmp_path, capsys):
    table = tmp_path / "run.csv"
    table.write_text("time_s,ax_mps2\n0.0,0.1\n0.05,0.2\n")
    rc = cli.main(["replay", str(table), "--interface", "virtual", "--channel", "x", "--rate", "max"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "a 20 Hz table" in err[0] and "not a CAN log" in err[0], err


def _bad_log(tmp_path, damage: str):
    """A log of 3 s of frames, bad past its middle as ``damage`` says."""
    import gzip

    t, sig = synthetic(3.0)
    suffix = ".log" if damage in ("garbage line", "garbage line .gz", "clock jump", "clock back") else ".asc"
    plain = tmp_path / f"run{suffix}"
    write_log(plain, t, sig)
    lines = plain.read_bytes().splitlines(keepends=True)
    if damage.startswith("garbage line"):
        lines.insert(len(lines) // 2, b"garbage line here\n")
    if damage == "clock jump":  # (a last frame stamped in Unix time: the replay would wait for 54 years)
        lines.append(b"(1700000000.000000)" + lines[-1].split(b")", 1)[1])
    if damage == "clock back":  # (the second half stamped 1 s earlier: a logger's clock set back mid-run)
        half = len(lines) // 2
        for i in range(half, len(lines)):
            stamp, rest = lines[i][1:].split(b")", 1)
            lines[i] = b"(%.6f)" % (float(stamp) - 1.0) + rest
    text = b"".join(lines)
    if damage in ("garbage line", "clock jump", "clock back"):
        plain.write_bytes(text)
        return plain
    path = tmp_path / f"run{suffix}.gz"
    packed = gzip.compress(text)
    path.write_bytes({"garbage line .gz": packed, "gzip cut": packed[: len(packed) // 2],
                      "text cut .gz": gzip.compress(text[: len(text) // 2])}[damage])
    return path


@pytest.mark.parametrize("damage", ["garbage line", "garbage line .gz", "gzip cut", "text cut .gz", "clock jump",
                                    "clock back"])
def test_a_log_bad_past_its_middle_sends_nothing(tmp_path, channel, capsys, damage):
    """The whole log is read before the bus is opened: a garbage line in the middle of a .log (599 frames went out
    before exit 2), a .asc.gz cut by ``head -c`` (502 frames, then an EOFError), a garbage line or a text cut
    mid-record inside a complete gzip stream, a clock set back 1 s half way (the rest of the log went out late in
    one burst): one line, exit 2, nothing on the bus; replay() itself sends nothing either."""
    path = _bad_log(tmp_path, damage)
    rx = can.Bus(interface="virtual", channel=channel)
    try:
        rc = cli.main(["replay", str(path), "--interface", "virtual", "--channel", channel, "--rate", "max", "-q"])
        out, err = capsys.readouterr()
        tx = can.Bus(interface="virtual", channel=channel)
        try:
            with pytest.raises(UserError) as e:
                replay(path, tx, rate=None)
        finally:
            tx.shutdown()
        got = iter(lambda: rx.recv(0.2), None)
        assert next(got, None) is None, "a frame of the bad log went onto the bus"
    finally:
        rx.shutdown()
    assert rc == 2 and out == "" and err.count("\n") == 1 and "Traceback" not in err, err
    assert f"{path}: " in err and str(e.value) in err, err
    want = {"garbage line": "unparsable line 'garbage line here'", "garbage line .gz": "unparsable line",
            "gzip cut": "truncated: the gzip stream is cut", "text cut .gz": "truncated: line",
            "clock jump": "a replay covers at most 12 h", "clock back": "goes back in time 0.99"}[damage]
    assert want in err, err


def test_a_checked_log_is_read_through_once_before_the_bus_and_played_whole(tmp_path, channel):
    """check_log counts a good .log.gz's frames, and replay plays the CheckedLog whole without reading it again."""
    import gzip

    from virtsensor.recordings.replay import check_log

    t, sig = synthetic(0.5)
    path = tmp_path / "ok.log.gz"
    plain = tmp_path / "ok.log"
    written = write_log(plain, t, sig)
    path.write_bytes(gzip.compress(plain.read_bytes()))
    checked = check_log(path)
    assert checked.frames == written.frames
    rx = Receiver(channel)
    tx = can.Bus(interface="virtual", channel=channel)
    try:
        summary = replay(checked, tx, rate=None)
    finally:
        tx.shutdown()
    assert summary.frames_sent == written.frames == len(rx.close(expect=written.frames))


def test_open_bus_folds_what_python_can_logs_into_its_one_line_or_hands_it_on(monkeypatch, caplog):
    """A driver that cannot load logs why before it raises: that note joins the one error line, nothing else is
    printed; when the bus opens, what it logged is handed on to logging as before."""
    import logging
    import warnings

    import can

    from virtsensor.errors import UserError
    from virtsensor.recordings.replay import open_bus

    def failing(**kw):
        logging.getLogger("can.fake").warning("fake driver library is unavailable.")
        raise can.CanInterfaceNotImplementedError("name 'fakeOpen' is not defined")

    monkeypatch.setattr(can, "Bus", failing)
    with caplog.at_level(logging.WARNING, logger="can"):
        with pytest.raises(UserError) as info:
            open_bus("virtual", "x")
    assert str(info.value) == ("cannot open virtual channel 'x': name 'fakeOpen' is not defined "
                               "(python-can: fake driver library is unavailable.)"), info.value
    assert caplog.records == []  # (held back: it is in the line)
    with caplog.at_level(logging.WARNING, logger="can"):  # (the daemon's reconnects: logging left as it is)
        with pytest.raises(UserError, match=r"^cannot open virtual channel 'x': name 'fakeOpen' is not defined$"):
            open_bus("virtual", "x", fold_notes=False)
    assert [r.getMessage() for r in caplog.records] == ["fake driver library is unavailable."]
    caplog.clear()

    opened = object()

    def noisy(**kw):
        logging.getLogger("can.fake").warning("timestamps are relative to boot time")
        warnings.warn("old option", DeprecationWarning, stacklevel=1)
        return opened

    monkeypatch.setattr(can, "Bus", noisy)
    with caplog.at_level(logging.WARNING, logger="can"), pytest.warns(DeprecationWarning, match="old option"):
        assert open_bus("virtual", "x") is opened
    assert [r.getMessage() for r in caplog.records] == ["timestamps are relative to boot time"]
    assert logging.getLogger("can").propagate and not any(
        type(h).__name__ == "Held" for h in logging.getLogger("can").handlers)
