"""`virtsensor demo`: the daemon on the bundled wet-road run, its figures, and bad input."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import json
import math
import subprocess
import sys
import time

import cantools
import numpy as np
import pytest

from virtsensor.assets import dbc_path
from virtsensor.cli import main
from virtsensor.demo import DEMO_RUN, default_model, default_recording

HAVE_MPL = importlib.util.find_spec("matplotlib") is not None


def run_demo_cli(*args: str) -> tuple[int, str]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["demo", *args])
    return rc, buf.getvalue()


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    d = tmp_path_factory.mktemp("demo")
    plot, js = d / "figs" / "demo.png", d / "demo.json"
    t0 = time.monotonic()
    rc, text = run_demo_cli("--rate", "20", "--no-live", "--json", str(js), "--plot", str(plot))
    wall = time.monotonic() - t0
    return {"rc": rc, "text": text, "json": json.loads(js.read_text()), "plot": plot, "wall": wall}


def test_the_bundled_recording_is_there_with_its_reference():
    rec = default_recording()
    assert rec.is_file() and rec.parent.name == "recordings"
    info = json.loads(rec.with_suffix(".json").read_text())
    name, speed, mu, seed = DEMO_RUN
    assert (info["manoeuvre"], info["speed_kmh"], info["mu"], info["seed"]) == (name, speed, mu, seed)
    assert mu <= 0.8  # a wet road
    assert default_model().is_file()


def test_demo_runs_on_the_bundled_defaults_and_its_figures_are_sane(demo):
    assert demo["rc"] == 0, demo["text"]
    r = demo["json"]
    assert r["has_reference"] and not r["interrupted"]
    assert r["rate"] == 20.0
    # 20 s at 20 Hz: one tick per sync frame, every one answered by the daemon
    assert r["sync_frames_planned"] == r["sync_frames"] == 401
    assert r["ticks"] == 401 and r["daemon_ticks"] == 401
    assert r["daemon_counters"]["tick_errors"] == 0 and r["daemon_counters"]["crc_errors"] == 0
    for w in ("fl", "fr"):
        st = r["statuses"][w]
        assert sum(st.values()) == 401
        assert st["VALID"] >= 390 and st["INVALID"] == 0
    m = r["metrics"]
    for w in ("fl", "fr", "mean"):
        assert math.isfinite(m[w]["mae_nm"]) and 0 < m[w]["mae_nm"] < 6.0, m
        assert m[w]["r2"] > 0.9, m
    assert m["fl"]["peak_true_nm"] > 40  # a manoeuvre with something to estimate
    lat = r["latency_ms"]
    assert lat["n"] == 401 and 0 < lat["p50"] <= lat["p99"] <= lat["max"]
    assert r["daemon_tick_latency_us"]["p99"] > 0
    # 20 s at 20x, plus start-up: well under the 2-minute budget of the default run
    assert demo["wall"] < 30
    text = demo["text"]
    for word in ("MAE", "R2", "latency p99", "ticks: 401", "VALID"):
        assert word in text, text


def test_the_bundled_defaults_also_show_the_grip_warning_on_a_run_that_reaches_the_limit(demo):
    """The main run stays below the limit; the bundled wet fishhook (DEMO_LIMIT_RUN) follows it at full speed and
    shows the warning and the friction estimate against the road's."""
    from virtsensor.demo import DEMO_LIMIT_RUN, limit_recording

    assert demo["json"]["grip"]["warning_ticks"] == 0  # (why the limit run is there)
    lim = demo["json"]["limit_run"]
    assert lim["recording"] == str(limit_recording()) and DEMO_LIMIT_RUN[0] in lim["recording_description"]
    g = lim["grip"]
    assert g["road_mu"] == DEMO_LIMIT_RUN[2] and g["util_max"] > 0.8 and g["warning_ticks"] >= 20
    assert g["mu_given_ticks"] >= 20 and g["mu_within_0_1_share"] >= 0.9
    assert "at the limit: fishhook" in demo["text"] and "warning on" in demo["text"]
    st = lim["statuses"]["fl"]
    assert sum(st.values()) == lim["ticks"] and st["INVALID"] == 0 and st["VALID"] >= 0.8 * lim["ticks"]
    assert f"statuses (FL) VALID {st['VALID']}" in demo["text"]
    if HAVE_MPL:
        assert lim["plot"] == str(demo["plot"].with_name("demo_limit.png"))
        assert demo["plot"].with_name("demo_limit.png").read_bytes()[:4] == b"\x89PNG"


def test_a_recording_given_is_replayed_alone(tmp_path):
    from virtsensor.demo import limit_recording

    js = tmp_path / "d.json"
    rc, text = run_demo_cli("--recording", str(limit_recording()), "--rate", "max", "--no-live", "--json", str(js),
                            "--plot", str(tmp_path / "p.png"))
    assert rc == 0, text
    r = json.loads(js.read_text())
    assert r["limit_run"] is None and "at the limit" not in text and r["grip"]["warning_ticks"] > 0


@pytest.mark.skipif(not HAVE_MPL, reason="matplotlib is not installed")
def test_the_limit_run_is_at_full_speed_and_its_plot_follows_the_plot_name(tmp_path):
    js = tmp_path / "d.json"
    rc, text = run_demo_cli("--rate", "1000", "--no-live", "--json", str(js), "--plot", str(tmp_path / "x.png"))
    assert rc == 0, text
    lim = json.loads(js.read_text())["limit_run"]
    assert lim["rate"] == "max" and lim["complete"] and not lim["interrupted"]
    assert lim["plot"] == str(tmp_path / "x_limit.png") and (tmp_path / "x_limit.png").is_file()


@pytest.mark.parametrize("clash", ["json", "directory"])
def test_the_limit_plot_is_refused_before_any_work_where_it_cannot_go(tmp_path, clash):
    js = tmp_path / ("c_limit.png" if clash == "json" else "c.json")
    if clash == "directory":
        (tmp_path / "c_limit.png").mkdir()
    before = sorted(tmp_path.iterdir())
    r = subprocess.run([sys.executable, "-m", "virtsensor.cli", "demo", "--rate", "max", "--no-live", "--json",
                        str(js), "--plot", str(tmp_path / "c.png")], capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "c_limit.png" in r.stderr, r.stderr
    assert r.stdout == "" and sorted(tmp_path.iterdir()) == before


def test_a_limit_run_interrupted_or_failing_is_said_so_and_the_main_figures_stay(tmp_path, monkeypatch):
    import virtsensor.demo as d

    real_listen, real_plan = d._listen, d._plan
    calls = {"listen": 0, "plan": 0}

    def listen(*a, **k):  # Ctrl-C in the second run (the limit run), after it started
        calls["listen"] += 1
        if calls["listen"] == 2:
            raise KeyboardInterrupt
        return real_listen(*a, **k)

    monkeypatch.setattr(d, "_listen", listen)
    js = tmp_path / "i.json"
    rc, text = run_demo_cli("--rate", "max", "--no-live", "--json", str(js), "--plot", str(tmp_path / "i.png"))
    r = json.loads(js.read_text())
    assert rc == 130 and r["interrupted"] and r["limit_run"]["interrupted"], text
    assert "at the limit (interrupted)" in text and r["metrics"]["mean"]["r2"] > 0.9

    monkeypatch.setattr(d, "_listen", real_listen)

    def plan(path):  # the limit recording unreadable
        calls["plan"] += 1
        if calls["plan"] == 2:
            raise d.UserError(f"{path}: cut mid-record")
        return real_plan(path)

    monkeypatch.setattr(d, "_plan", plan)
    js = tmp_path / "f.json"
    rc, text = run_demo_cli("--rate", "max", "--no-live", "--json", str(js), "--plot", str(tmp_path / "f.png"))
    r = json.loads(js.read_text())
    assert rc == 0 and "cut mid-record" in r["limit_run"]["error"], text
    assert "the bundled limit run failed" in text and r["metrics"]["mean"]["r2"] > 0.9


@pytest.mark.skipif(not HAVE_MPL, reason="matplotlib is not installed")
def test_outputs_are_all_or_none_a_figures_file_that_cannot_be_written_leaves_no_plot(tmp_path, monkeypatch, capsys):
    import errno

    import virtsensor.demo as d

    def full(path, obj):  # the disk fills up as the figures are written, after both plots
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(d, "write_json", full)
    rc, text = run_demo_cli("--rate", "max", "--no-live", "--json", str(tmp_path / "o.json"), "--plot",
                            str(tmp_path / "o.png"))
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]  # (after the daemon's log lines, where a test set them up)
    assert rc == 1 and last.startswith("virtsensor demo: error: No space left on device") and "o.json" in last, err
    assert "Traceback" not in err
    assert "ticks:" not in text and "figures:" not in text  # no summary (the lines of what it replays came first)
    assert sorted(tmp_path.iterdir()) == []  # no plot, no limit plot, no staged file


@pytest.mark.skipif(not HAVE_MPL, reason="matplotlib is not installed")
def test_demo_writes_the_plot(demo):
    assert demo["json"]["plot"] == str(demo["plot"])
    assert demo["plot"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    from virtsensor.fileio import PARTIAL_PREFIX

    assert not list(demo["plot"].parent.glob(f"{PARTIAL_PREFIX}*"))  # written atomically, nothing left behind


def test_demo_figures_equal_the_offline_pipeline(demo):
    """The daemon's estimates on the bus, paired by the demo, score what the offline table and model score
    (up to SAT_FRONT's 0.02 Nm resolution): a tick paired with the wrong instant would show."""
    from virtsensor.features import FeatureSpec
    from virtsensor.model.onnx import OnnxModel
    from virtsensor.recordings.canlog import read_log

    model = OnnxModel.load(default_model())
    table = read_log(default_recording()).table
    x = FeatureSpec.from_json(model.card["feature_spec"]).transform(table)
    ok = np.isfinite(x).all(1)
    est = model.predict(x[ok])
    m = demo["json"]["metrics"]
    for k, w in enumerate(("fl", "fr")):
        y = table[f"sat_{w}_nm"][ok]
        err = est[:, k] - y
        r2 = 1 - (err ** 2).sum() / ((y - y.mean()) ** 2).sum()
        assert abs(m[w]["r2"] - r2) < 5e-4, (w, m[w], r2)
        assert abs(m[w]["mae_nm"] - np.abs(err).mean()) < 0.01, (w, m[w], np.abs(err).mean())  # 0.02 Nm steps


def test_demo_live_lines_and_max_rate(tmp_path):
    rc, text = run_demo_cli("--rate", "max", "--plot", str(tmp_path / "p.png"))
    assert rc == 0, text
    live = [ln for ln in text.splitlines() if ln.strip()[:1].isdigit() and "/" in ln]
    assert live, text  # at least the first tick's line (INIT)
    assert "INIT" in live[0]
    assert "mean" in text and "latency p99" in text


def test_demo_without_matplotlib_still_prints_its_figures(tmp_path, monkeypatch, capsys):
    """Without matplotlib the default plot is skipped with a note and the figures still print; a plot asked for
    with ``--plot`` is refused in one line (exit 2) before any work, nothing written."""
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    monkeypatch.chdir(tmp_path)
    js = tmp_path / "d.json"
    rc, text = run_demo_cli("--rate", "max", "--no-live", "--json", str(js))
    assert rc == 0, text
    assert "plot skipped: matplotlib is not installed" in text and "pip install" in text
    assert "MAE" in text
    r = json.loads(js.read_text())
    assert r["plot"] is None and "matplotlib" in r["plot_skipped"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.json"]  # (no figures/ folder, no plot)
    assert r["limit_run"]["plot"] is None and r["limit_run"]["grip"]["warning_ticks"] > 0
    js.unlink()
    capsys.readouterr()
    rc, text = run_demo_cli("--rate", "max", "--no-live", "--json", str(js), "--plot", str(tmp_path / "p.png"))
    err = capsys.readouterr().err
    assert rc == 2 and text == "" and err.count("\n") == 1, (text, err)
    assert err.startswith("virtsensor demo: error: --plot needs the optional extra 'plots'"), err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "args, words",
    [
        (["--recording", "{tmp}/missing.blf"], ["missing.blf", "no such log file"]),
        (["--recording", "{tmp}/notalog.txt"], ["notalog.txt", "unsupported CAN log format"]),
        (["--model", "{tmp}/missing.onnx"], ["--model", "missing.onnx"]),
        (["--model", "{tmp}/notalog.txt"], ["--model", "notalog.txt", "expected a .onnx file"]),
        (["--plot", "{tmp}/notalog.txt/demo.png"], ["--plot", "not a directory"]),
        (["--plot", "{tmp}"], ["--plot", "is a directory"]),
        (["--json", "{tmp}/notalog.txt/d.json"], ["--json", "not a directory"]),
        (["--rate", "0"], ["--rate"]),
        (["--rate", "fast"], ["--rate"]),
    ],
)
def test_demo_bad_input_is_one_line_and_exit_2(tmp_path, capsys, args, words):
    (tmp_path / "notalog.txt").write_text("hello\n")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in args]
    t0 = time.monotonic()
    rc = main(["demo", "--no-live", *argv])
    assert rc == 2
    assert time.monotonic() - t0 < 10  # refused before any replay
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("virtsensor demo: error:"), err
    for w in words:
        assert w in err, err
    assert "Traceback" not in err
    assert not (tmp_path / "demo.png").exists()


def test_demo_bad_input_from_the_shell_has_no_traceback(tmp_path):
    res = subprocess.run([sys.executable, "-m", "virtsensor.cli", "demo", "--recording", str(tmp_path / "x.blf")],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert res.returncode == 2
    assert res.stderr.count("\n") == 1 and "no such log file" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "figures").exists()  # nothing written


def _write_log(path, frames):
    import can

    writer = can.Logger(str(path))
    try:
        for m in frames:
            writer.on_message_received(m)
    finally:
        writer.stop()


@pytest.fixture(scope="module")
def single_sine(tmp_path_factory):
    """A run as ``simulate`` writes it, as ``single-sine.blf`` and ``single-sine-log.log``, each with its metadata
    ``<stem>.json`` beside it."""
    d = tmp_path_factory.mktemp("single")
    for name in ("single-sine.blf", "single-sine-log.log"):
        assert main(["simulate", "single-sine", "--speed", "60", "--mu", "0.6", "--out", str(d / name)]) == 0
    return d


def test_a_recording_is_described_by_its_own_metadata_only(single_sine, tmp_path):
    """A ``.json`` beside the recording that names another file is another run's metadata: never this run's
    description nor its road friction; the demo says it ignored it."""
    rec = tmp_path / "single-sine.blf"
    rec.write_bytes((single_sine / "single-sine.blf").read_bytes())
    own = json.loads((single_sine / "single-sine.json").read_text())
    js = tmp_path / "d.json"
    argv = ["--recording", str(rec), "--rate", "max", "--no-live", "--json", str(js), "--plot", str(tmp_path / "d.png")]
    (tmp_path / "single-sine.json").write_text(json.dumps(own))  # its own: used
    rc, text = run_demo_cli(*argv)
    r = json.loads(js.read_text())
    assert rc == 0 and r["recording_description"].startswith("single-sine at 60 km/h on a wet road (mu 0.6)"), text
    assert r["grip"]["road_mu"] == 0.6 and r.get("recording_metadata_ignored") is None and "ignored" not in text
    other = {**own, "file": "random-steer.blf", "manoeuvre": "random-steer", "speed_kmh": 70.0, "mu": 0.7}
    (tmp_path / "single-sine.json").write_text(json.dumps(other))  # another run's, copied beside it
    rc, text = run_demo_cli(*argv)
    r = json.loads(js.read_text())
    assert rc == 0, text
    assert r["recording_description"] == "single-sine.blf" and "random-steer" not in text.splitlines()[0], text
    assert r["grip"]["road_mu"] is None  # no friction to compare the estimate with, rather than another run's
    note = (f"{tmp_path / 'single-sine.json'} ignored: its \"file\" is 'random-steer.blf', not single-sine.blf, "
            "so it is the metadata of another run")
    assert r["recording_metadata_ignored"] == note and f"note: {note}" in text, text


def test_a_log_cut_at_a_line_boundary_is_refused_by_its_metadatas_samples(single_sine, tmp_path, capsys):
    """A ``.log`` has no trailer: cut at a line boundary, only its metadata's ``samples`` shows it is not whole."""
    rec = tmp_path / "cut.log"
    lines = (single_sine / "single-sine-log.log").read_text().splitlines(keepends=True)
    rec.write_text("".join(lines[: len(lines) // 2]))
    meta = json.loads((single_sine / "single-sine-log.json").read_text())
    (tmp_path / "cut.json").write_text(json.dumps({**meta, "file": "cut.log"}))
    js = tmp_path / "d.json"
    capsys.readouterr()
    rc, text = run_demo_cli("--recording", str(rec), "--rate", "max", "--no-live", "--json", str(js),
                            "--plot", str(tmp_path / "d.png"))
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert f"{rec}: " in err and f"rows read, its metadata cut.json lists {meta['samples']} samples" in err, err
    assert not js.exists() and "ticks:" not in text


def test_demo_on_a_recording_without_reference_gives_estimates_only(tmp_path):
    from virtsensor.canbus.codec import CanMatrix
    from virtsensor.demo import run_demo
    from virtsensor.recordings.canlog import iter_log

    te = CanMatrix.load().messages["TE_WheelForceTransducer"].frame_id
    frames = [m for m in iter_log(default_recording()) if m.arbitration_id != te and m.timestamp < 5.0]
    _write_log(tmp_path / "noref.blf", frames)
    buf = io.StringIO()
    r = run_demo(recording=tmp_path / "noref.blf", rate="max", live=False, plot=None, out=buf)
    assert not r["has_reference"] and r["metrics"] is None
    assert r["ticks"] == r["sync_frames"] == 100 and r["statuses"]["fl"]["VALID"] > 90
    assert "no reference" in buf.getvalue() and "MAE / R2: n/a" in buf.getvalue()


def test_demo_refuses_a_recording_without_the_models_inputs(tmp_path, capsys):
    from virtsensor.canbus.codec import CanMatrix
    from virtsensor.recordings.canlog import iter_log

    te = CanMatrix.load().messages["TE_WheelForceTransducer"].frame_id
    _write_log(tmp_path / "te_only.blf", [m for m in iter_log(default_recording()) if m.arbitration_id == te][:200])
    assert main(["demo", "--no-live", "--recording", str(tmp_path / "te_only.blf"),
                 "--plot", str(tmp_path / "p.png")]) == 2
    err = capsys.readouterr().err
    assert "none of the model's input messages" in err and len(err.strip().splitlines()) == 1


def test_metrics_give_the_error_over_the_valid_ticks_alone():
    """``mae_valid_nm``: the error a consumer that trusts VALID only sees (a DEGRADED tick's error is left out);
    ``valid_share``: over all ticks, INIT and INVALID included."""
    from virtsensor.demo import _metrics

    true = np.zeros((6, 2))
    est = np.array([[1.0, 2.0], [1.0, 2.0], [9.0, 9.0], [9.0, 9.0], [np.nan, np.nan], [np.nan, np.nan]])
    status = np.array([[0, 0], [0, 0], [1, 1], [1, 1], [2, 2], [3, 3]])
    m = _metrics(est, true, status)
    assert m["fl"]["mae_valid_nm"] == 1.0 and m["fr"]["mae_valid_nm"] == 2.0
    assert m["fl"]["mae_nm"] == 5.0  # VALID and DEGRADED
    assert m["fl"]["valid_share"] == pytest.approx(2 / 6, abs=1e-4)
    status[:2] = 1  # no VALID tick at all
    assert _metrics(est, true, status)["fl"]["mae_valid_nm"] is None


@pytest.mark.slow
@pytest.mark.parametrize("which", ["DEMO_RUN", "DEMO_LIMIT_RUN"])
def test_the_bundled_recordings_are_what_the_simulator_makes_today(tmp_path, which):
    """Each bundled recording against a fresh simulation of its run (what ``tools/make_demo_recording.py --check``
    compares byte for byte): the same frames, ids and stamps, and the same data but for a rare last-bit rounding of
    another machine's floating point (a change of the simulator or the CAN matrix that leaves them stale shows)."""
    from virtsensor import demo as d
    from virtsensor.recordings.canlog import iter_log

    run = getattr(d, which)
    name, speed, mu, seed = run
    fresh = tmp_path / d.demo_recording_name(run)
    assert main(["simulate", name, "--speed", f"{speed:g}", "--mu", f"{mu:g}", "--seed", str(seed),
                 "--out", str(fresh)]) == 0
    old, new = list(iter_log(d.recording_path(fresh.name))), list(iter_log(fresh))
    assert [(m.arbitration_id, m.timestamp) for m in old] == [(m.arbitration_id, m.timestamp) for m in new]
    db = cantools.database.load_file(str(dbc_path()))
    differ = [(a, b) for a, b in zip(old, new, strict=True) if bytes(a.data) != bytes(b.data)]
    assert len(differ) <= len(old) // 100, f"{len(differ)} of {len(old)} frames differ"
    for a, b in differ:  # (a differing frame: every signal within one raw step; its CRC follows the data)
        msg = db.get_message_by_frame_id(a.arbitration_id)
        va, vb = (msg.decode(bytes(m.data), decode_choices=False) for m in (a, b))
        for sig in msg.signals:
            if not sig.name.endswith("CRC"):
                assert abs(va[sig.name] - vb[sig.name]) <= abs(sig.scale) * (1 + 1e-9), (msg.name, sig.name)


def test_the_default_plot_is_skipped_where_it_cannot_be_written_but_an_asked_one_is_refused(tmp_path, monkeypatch):
    """``virtsensor demo`` in a read-only directory refused to run (its default figures/demo.png), though the user
    had asked for no plot; the base install, without matplotlib, ran there. A --plot asked for is still refused."""
    from virtsensor import demo as d
    from virtsensor.errors import UserError

    monkeypatch.chdir(tmp_path)
    (tmp_path / "figures").write_text("a file where the folder would go\n")
    monkeypatch.setattr(d, "_matplotlib_missing", lambda: None)  # (as with the plots extra installed)
    opts = d._options(None, None, 1.0, d.DEFAULT_PLOT, None, plot_optional=True)
    assert opts.plot_skip is not None and "figures" in opts.plot_skip and opts.limit_plot is None
    with pytest.raises(UserError, match="--plot"):
        d._options(None, None, 1.0, d.DEFAULT_PLOT, None)
