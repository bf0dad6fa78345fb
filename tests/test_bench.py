"""``virtsensor bench --quick`` on a tiny model built here (never models/): the JSON is complete and sane.

No timing thresholds: only keys, ordering of the percentiles, positivity and plausibility.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from runtime_support import card_inputs, synthetic_streams

from virtsensor import cli
from virtsensor import signals as cat
from virtsensor.features import HISTORY
from virtsensor.model.export import export_pipeline, pipeline_weights
from virtsensor.recordings.canlog import simulated_recording

PCT = ("p50", "p99", "p999", "max")


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> Path:
    """RobustScaler + MLP(8) on synthetic streams, exported with its plain weights in the card."""
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import RobustScaler

    spec = HISTORY
    table = simulated_recording(*synthetic_streams(20.0, seed=1)).table
    X = spec.transform(table)
    Y = np.column_stack([table[o] for o in cat.OUTPUTS])
    ok = np.isfinite(X).all(1) & np.isfinite(Y).all(1)
    X, Y = X[ok], Y[ok]
    pipe = Pipeline([("scaler", RobustScaler()),
                     ("mlp", MLPRegressor(hidden_layer_sizes=(8,), max_iter=50, random_state=0))])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        pipe.fit(X, Y)
    path = tmp_path_factory.mktemp("bench") / "tiny.onnx"
    export_pipeline(pipe, X.shape[1], path, parity_X=X[:100], card_extra={
        "model": "virtsensor-bench-test", "feature_spec": spec.to_json(), "inputs": card_inputs(spec),
        "signals": list(spec.signals), "weights": pipeline_weights(pipe)})
    return path


def _check_pct(name: str, p, *, strictly_positive: bool = True) -> None:
    assert isinstance(p, dict), (name, p)
    vals = [p[k] for k in PCT]
    assert all(isinstance(v, (int, float)) and np.isfinite(v) for v in vals), (name, p)
    assert vals == sorted(vals), (name, p)  # p50 <= p99 <= p999 <= max
    assert vals[0] > 0 if strictly_positive else vals[0] >= 0, (name, p)


def test_bench_quick_json_complete_and_sane(tiny_model, tmp_path):
    out = tmp_path / "bench.json"
    md = tmp_path / "bench.md"
    png = tmp_path / "bench.png"
    rc = cli.main(["bench", "--model", str(tiny_model), "--quick", "--soak-ticks", "600", "--json", str(out),
                   "--markdown", str(md), "--histogram", str(png), "--quiet"])
    assert rc == 0
    r = json.loads(out.read_text())
    for key in ("tick_compute_us", "e2e_latency_us", "stages_us", "inference_us", "jitter_us", "max_tick_rate_hz",
                "missed_ticks", "rss_mb_start", "rss_mb_end", "cpu_percent_at_20hz", "machine", "model"):
        assert key in r, key
    _check_pct("tick_compute_us", r["tick_compute_us"])
    _check_pct("e2e_latency_us", r["e2e_latency_us"])
    _check_pct("e2e in_process", r["e2e_latency_us"]["in_process"])
    xp = r["e2e_latency_us"]["cross_process"]
    if xp is None:
        assert r["e2e_latency_us"]["cross_process_skipped"]  # null only with a reason
    else:
        _check_pct("e2e cross_process", xp)
    assert set(r["stages_us"]) == set(r["stages_after_idle_us"]) == {
        "decode", "plausibility", "validity", "feature_vector", "inference", "envelope", "encode", "grip", "send",
        "tick"}
    for k, v in (*r["stages_us"].items(), *r["stages_after_idle_us"].items()):
        if k == "envelope":  # the tiny card states no envelope: the stage never runs
            assert v is None, v
            continue
        _check_pct(f"stage {k}", v)
    assert r["stages_after_idle_us"]["tick"]["n"] == 10  # the quick count
    for k in ("onnxruntime", "sklearn", "numpy"):  # the tiny card has weights: no back-end is skipped
        _check_pct(f"inference {k}", r["inference_us"][k])
    assert max(r["inference_us"]["max_abs_diff_vs_onnxruntime_nm"].values()) < 1e-2
    _check_pct("jitter_us", r["jitter_us"], strictly_positive=False)
    assert r["max_tick_rate_hz"] > 20
    assert isinstance(r["missed_ticks"], int)
    assert r["soak"]["missed_no_sat_front"] == 0 and r["soak"]["tick_errors"] == 0  # (every tick published)
    assert r["soak"]["ticks"] == 600 and r["soak"]["ticks_produced"] == 600
    # the replayed window loops seamlessly: E2E fails only on messages' first frames (their counters start mid-way)
    assert r["soak"]["e2e_errors"] == 0 and 0 < r["soak"]["e2e_errors_first_frames"] <= 9
    assert r["rss_mb_start"] > 0 and r["rss_mb_end"] > 0
    assert 0 < r["cpu_percent_at_20hz"] < 100 * (r["machine"]["cores"] or 1)
    assert 0 < r["cpu_percent_at_20hz_default_idle"] < 100 * (r["machine"]["cores"] or 1)
    _check_pct("jitter_us_default_idle", r["jitter_us_default_idle"], strictly_positive=False)
    req = r["cpu_latency_request"]  # the daemon asked for PM QoS latency 0: held, or refused with a reason
    assert req["us"] == 0 and (req["held"] or req["error"])
    assert r["free_running"]["cpu_latency"] == (req if req["held"] else None)
    assert r["free_running_default_idle"]["cpu_latency"] is None
    assert r["machine"]["python"] and r["machine"]["platform"] and r["machine"]["cores"] >= 1
    assert r["model"]["file"] == str(tiny_model) and len(r["model"]["sha256"]) == 64
    assert set(r["targets"]) >= {"tick_compute_p99_us", "e2e_in_process_p99_us", "max_tick_rate_hz"}
    fc = r["feature_cost"]
    assert set(fc["max_tick_rate_hz"]) == set(fc["tick_only_hz"]) == {
        "all", "without_grip", "without_envelope", "without_plausibility", "without_all"}
    assert all(v > 20 for v in (*fc["max_tick_rate_hz"].values(), *fc["tick_only_hz"].values()))
    assert set(fc["cost_us_per_tick"]) == {"grip", "envelope", "plausibility", "all"}
    assert fc["ticks"] == 500 and fc["rounds"] == 1  # the quick counts
    assert "max tick rate by feature" in md.read_text()
    assert md.read_text().startswith("# virtsensor bench") and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cross_process_run_takes_any_model_path_without_a_shell(tiny_model, tmp_path):
    """The cross-process run starts its subprocesses from argument lists: a model path with a double quote
    and a command substitution is a path, never shell code."""
    import shutil

    from virtsensor.daemon.xproc import measure_e2e_cross_process
    from virtsensor.model import card_path_for

    d = tmp_path / 'we"ird $(touch pwned) `touch pwned2`'
    d.mkdir()
    model = d / "tiny.onnx"
    shutil.copy(tiny_model, model)
    shutil.copy(card_path_for(tiny_model), card_path_for(model))
    res, reason = measure_e2e_cross_process(model, 30)
    assert not list(tmp_path.rglob("pwned*")) and not list(Path.cwd().glob("pwned*"))
    if res is None and reason and ("not permitted" in reason or "needs" in reason):
        pytest.skip(reason)
    assert res is not None, reason
    assert res["n"] >= 20 and res["p50"] > 0


def test_feature_cost_daemons_lack_exactly_what_is_switched_off(tiny_model):
    """The feature-cost soaks measure real configurations: without grip the daemon publishes no VS_Grip (as with an
    older DBC) but SAT_FRONT and VS_Health; without the envelope or the redundancy checks those stages answer
    "inside" and "plausible" and nothing else changes."""
    from virtsensor.canbus.codec import CanMatrix
    from virtsensor.daemon.bench import FEATURES, Inputs, _never_implausible, _never_outside, _sync_rig, _without
    from virtsensor.model.onnx import OnnxModel

    model = OnnxModel.load(tiny_model)
    full = CanMatrix.load()
    inputs = Inputs()
    ids = {n: full.messages[n].frame_id for n in ("SAT_FRONT", "VS_Health", "VS_Grip")}
    for feats in ((), *((f,) for f in FEATURES), FEATURES):
        m, hook = _without(full, feats)
        assert ("VS_Grip" in m.messages) == ("grip" not in feats)
        _, listener, vs, _ = _sync_rig(model, m, stage_hook=hook)
        try:
            for k in range(40):
                batch, sync = inputs.tick(k)
                for msg in (*batch, sync):
                    vs.process(msg)
            seen = set()
            while (f := listener.recv(0)) is not None:
                seen.add(f.arbitration_id)
            assert ids["SAT_FRONT"] in seen and ids["VS_Health"] in seen
            assert (ids["VS_Grip"] in seen) == ("grip" not in feats), feats
            assert vs.counters["ticks"] == 40
            assert (vs._plaus_update is _never_implausible) == ("plausibility" in feats)
            assert (vs._outside is _never_outside) == ("envelope" in feats)
        finally:
            vs.stop()
            listener.shutdown()


def test_the_shipped_bench_inputs_are_the_simulated_manoeuvres_frames():
    """The bench replays shipped frames (it runs on the base install, without the simulator): they are exactly the
    frames the simulator gives for the bench's manoeuvre in its window (``python tools/bench_inputs.py`` when not)."""
    from virtsensor import assets
    from virtsensor.daemon.bench import MANOEUVRE, load_frames, simulated_frames

    shipped, fresh = load_frames(assets.bench_inputs_path()), simulated_frames(MANOEUVRE)
    assert len(shipped) == len(fresh) > 1000
    for a, b in zip(shipped, fresh, strict=True):
        assert (a.timestamp, a.arbitration_id, a.is_extended_id, a.dlc, bytes(a.data)) == (
            b.timestamp, b.arbitration_id, b.is_extended_id, b.dlc, bytes(b.data))


def test_bench_inputs_that_are_not_frames_are_refused(tmp_path):
    from virtsensor.daemon.bench import load_frames
    from virtsensor.errors import UserError

    bad = tmp_path / "x.npz"
    bad.write_bytes(b"not an npz")
    with pytest.raises(UserError, match="not the bench's input frames"):
        load_frames(bad)
    uneven = tmp_path / "y.npz"
    np.savez(uneven, timestamp=np.zeros(3), arbitration_id=np.zeros(3, int), dlc=np.zeros(2, int),
             is_extended_id=np.zeros(3, bool), data=np.zeros((3, 8), np.uint8))
    with pytest.raises(UserError, match="differ in length"):
        load_frames(uneven)
