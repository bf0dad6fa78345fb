"""The validity envelope: fitted from the training rows into the model card, checked by the daemon (DEGRADED,
VS_Health, one log event per excursion), split by ``score``, rows in ``evaluate`` and shading in ``explain``."""

from __future__ import annotations

import numpy as np
import pytest
from runtime_support import SYNC_ID, CaptureBus, daemon_events, synthetic_streams, train_model, with_sync

from virtsensor import signals as cat
from virtsensor.canbus.codec import CanMatrix
from virtsensor.daemon import DEGRADED, INIT, INVALID, VALID, VirtualSensor
from virtsensor.daemon.validity import EnvelopeRules, envelope_status, outside_envelope
from virtsensor.errors import UserError
from virtsensor.features import HISTORY
from virtsensor.model import ModelCard
from virtsensor.model.envelope import Envelope
from virtsensor.recordings.canlog import iter_frames, simulated_recording

MATRIX = CanMatrix.load()
SAT_ID = MATRIX.messages["SAT_FRONT"].frame_id
HEALTH_ID = MATRIX.messages["VS_Health"].frame_id
#: the excursion of the daemon test: vx held at 70 m/s (the training rows reach about 52)
EXCURSION_S = (5.0, 7.0)


def _training_rows(seed: int = 11, duration: float = 60.0) -> tuple[dict, np.ndarray]:
    t, sig = synthetic_streams(duration, seed=seed)
    table = simulated_recording(t, sig).table
    X = HISTORY.transform(table)
    return table, X[np.isfinite(X).all(axis=1)]


@pytest.fixture(scope="module")
def rows() -> np.ndarray:
    return _training_rows()[1]


@pytest.fixture(scope="module")
def env(rows) -> Envelope:
    return Envelope.fit(rows, HISTORY.names)


# ------------------------------------------------------------------------------------------------ the envelope
def test_training_rows_are_inside_and_moved_rows_outside(env, rows):
    names = HISTORY.names
    assert not env.outside_rows(rows, names).any()
    assert set(env.signals) == set(cat.INPUTS)  # every input read as a value is bounded; rates are not
    i_vx, i_ay, i_ax = (names.index(s) for s in ("vx_mps", "ay_mps2", "ax_mps2"))
    fast = rows[:50].copy()
    fast[:, i_vx] = 70.0
    assert env.outside_rows(fast, names).all()
    # in every signal's range, but more grip than the band ever used: outside through the band ceiling only
    k = int((30.0 - env.band_start) // env.band_width)
    row = rows[:1].copy()
    row[:, i_vx], row[:, i_ax] = 30.0, 0.0
    row[:, i_ay] = min(env.ay_max[k] * 1.02, env.hi[env.signals.index("ay_mps2")] * 0.999)
    if row[0, i_ay] > env.ay_max[k]:
        assert env.outside_rows(row, names).all()
        assert any("|ay|" in r for r in env.reasons(dict(zip(names, row[0], strict=True))))
    row[:, i_ay] = 0.5 * env.ay_max[k]
    assert not env.outside_rows(row, names).any()
    assert env.reasons(dict(zip(names, row[0], strict=True))) == []
    assert any(r.startswith("vx_mps=70") for r in env.reasons(dict(zip(names, fast[0], strict=True))))


def test_a_speed_band_without_training_rows_is_outside():
    rng = np.random.default_rng(0)
    n = 400
    vx = np.concatenate([rng.uniform(10, 15, n), rng.uniform(25, 30, n)])  # nothing at 15-25 m/s
    X = np.column_stack([vx, rng.uniform(-3, 3, 2 * n), rng.uniform(-2, 2, 2 * n)])
    names = ("vx_mps", "ay_mps2", "ax_mps2")
    env = Envelope.fit(X, names)
    probe = np.array([[12.0, 1.0, 0.5], [20.0, 1.0, 0.5], [27.0, 1.0, 0.5]])
    assert env.outside_rows(probe, names).tolist() == [False, True, False]
    assert env.reasons(dict(zip(names, probe[1], strict=True))) == ["no training rows at vx 20-25 m/s"]


def test_json_round_trip_and_refusals(env, rows):
    back = Envelope.from_json(env.to_json())
    assert back.signals == env.signals
    np.testing.assert_array_equal(back.lo, env.lo)
    np.testing.assert_array_equal(back.ay_max, env.ay_max)
    assert np.array_equal(back.outside_rows(rows[:500] * 1.3, HISTORY.names),
                          env.outside_rows(rows[:500] * 1.3, HISTORY.names))
    doc = env.to_json()
    for bad in ({"signals": {"no_such_signal": [0, 1]}}, {"signals": {"vx_mps": [2, 1]}}, [],
                {**doc, "speed_bands": {**doc["speed_bands"], "width_mps": 0}},
                {**doc, "speed_bands": {**doc["speed_bands"], "ay_abs_max_mps2": [1.0]}}):
        with pytest.raises(UserError, match="card.json: envelope"):
            Envelope.from_json(bad, "m.card.json")


# ------------------------------------------------------------------------------------------------ the card
def _card(envelope: Envelope | None) -> ModelCard:
    fields = ModelCard.trainer_fields(model="t", spec=HISTORY, envelope=envelope)
    return ModelCard({**fields, "sha256": "0" * 64, "feature_names": list(HISTORY.names),
                      "n_features": len(HISTORY.names), "outputs": list(cat.OUTPUTS)}).sealed()


def test_the_card_carries_the_envelope_under_its_digest(env, tmp_path):
    card = _card(env)
    card.write(tmp_path / "m.card.json")
    back = ModelCard.read(tmp_path / "m.card.json")
    assert back.envelope is not None and back.envelope.signals == env.signals
    data = back.to_dict()
    data["envelope"]["signals"]["vx_mps"][1] = 90.0  # widen it: the digest no longer matches
    (tmp_path / "m.card.json").write_text(ModelCard(data).text())
    with pytest.raises(UserError, match="edited after export"):
        ModelCard.read(tmp_path / "m.card.json")
    data["envelope"] = {"signals": {"vx_mps": "fast"}}
    with pytest.raises(UserError, match="envelope"):
        ModelCard(data).sealed()
    assert _card(None).envelope is None and "envelope" not in _card(None)  # old cards: no envelope check


# ------------------------------------------------------------------------------------------------ the pure check
def test_the_daemon_check_agrees_with_the_rows_check(env, rows):
    sigs = HISTORY.signals
    rules = EnvelopeRules.from_envelope(env, sigs)
    idx = [HISTORY.names.index(s) for s in sigs]
    moved = rows[::7] * np.random.default_rng(1).uniform(0.8, 1.3, rows[::7].shape)
    want = env.outside_rows(moved, HISTORY.names)
    got = [outside_envelope(x[idx].tolist(), rules) for x in moved]
    assert 0.1 < want.mean() < 0.9
    assert got == want.tolist()
    # an envelope without speed bands: ranges only
    plain = EnvelopeRules.from_envelope(Envelope(env.signals, env.lo, env.hi), sigs)
    assert [outside_envelope(x[idx].tolist(), plain) for x in moved] == \
        Envelope(env.signals, env.lo, env.hi).outside_rows(moved, HISTORY.names).tolist()


def test_outside_degrades_only_valid():
    assert [envelope_status(s, True) for s in (VALID, DEGRADED, INVALID, INIT)] == [DEGRADED, DEGRADED, INVALID, INIT]
    assert [envelope_status(s, False) for s in (VALID, DEGRADED, INVALID, INIT)] == [VALID, DEGRADED, INVALID, INIT]


# ------------------------------------------------------------------------------------------------ the daemon

@pytest.fixture(scope="module")
def models(tmp_path_factory):
    from virtsensor.model.onnx import OnnxModel

    table = _training_rows()[0]
    d = tmp_path_factory.mktemp("env")
    train_model([table], d / "with.onnx", hidden=(6,), max_iter=60, envelope=True)
    train_model([table], d / "without.onnx", hidden=(6,), max_iter=60)
    return OnnxModel.load(d / "with.onnx"), OnnxModel.load(d / "without.onnx")


def _fast(t, sig) -> None:
    """vx at 70 m/s during EXCURSION_S."""
    inside = (t >= EXCURSION_S[0]) & (t < EXCURSION_S[1])
    sig["vx_mps"] = np.where(inside, 70.0, sig["vx_mps"])
    for w in ("fl", "fr"):  # the wheels roll at that speed: plausible, just never trained on
        sig[f"wheel_speed_{w}_radps"] = sig["vx_mps"] / cat.ROLLING_RADIUS_M


def _drive(model, excursion=_fast):
    """The 12 s stream (the training stream's start) with an ``excursion`` (default: :func:`_fast`), in sync mode."""
    t, sig = synthetic_streams(12.0, seed=11)
    excursion(t, sig)
    frames = list(iter_frames(t, sig))
    merged, _ = with_sync(frames, frames[0].timestamp, frames[-1].timestamp)
    vs = VirtualSensor(CaptureBus(), model, MATRIX, sync_id=SYNC_ID, freeze_gc=False)
    ticks = []
    with daemon_events() as handler:
        for m in merged:
            n = vs.counters["ticks"]
            vs.process(m)
            if vs.counters["ticks"] > n:
                ticks.append((m.timestamp, vs.last_statuses, vs.outside_envelope))
    assert vs.counters["tick_errors"] == 0
    health = [MATRIX.fresh().decode(HEALTH_ID, f.data, 0.0).other for f in vs.bus.sent if f.arbitration_id == HEALTH_ID]
    return vs, ticks, health, handler.events


def test_the_daemon_degrades_counts_and_logs_each_excursion_once(models):
    vs, ticks, health, events = _drive(models[0])
    lo, hi = EXCURSION_S
    during = [(tk, s, o) for tk, s, o in ticks if lo + 0.1 <= tk <= hi - 0.05]
    clear = [(tk, s, o) for tk, s, o in ticks if 1.0 <= tk <= lo - 0.05 or tk >= hi + 0.2]
    assert during and clear
    assert all(o and s == (DEGRADED, DEGRADED) for _, s, o in during)
    assert all(not o and s == (VALID, VALID) for _, s, o in clear)
    assert vs.counters["envelope_exits"] == 1
    n_out = sum(o for _, _, o in ticks)
    assert vs.counters["envelope_ticks"] == n_out and abs(n_out - 40) <= 2  # 2 s at 20 Hz
    exits = [e for e in events if e["event"] == "envelope_exit"]
    returns = [e for e in events if e["event"] == "envelope_return"]
    assert len(exits) == 1 and len(returns) == 1
    # (back inside, the features read rows of the excursion for 2 more ticks: the steering angle's lag of 2)
    assert lo - 0.06 <= exits[0]["t"] <= lo + 0.06 and hi + 0.1 <= returns[0]["t"] <= hi + 0.16
    assert any(r.startswith("vx_mps=70") for r in exits[0]["outside"])
    # VS_Health: the flag follows the excursion, the excursion count stays at 1 after it
    flags = [int(h["VS_OutOfEnvelope"]) for h in health]
    assert flags == [int(o) for _, _, o in ticks]
    assert int(health[-1]["VS_EnvelopeExits"]) == 1 and int(health[0]["VS_EnvelopeExits"]) == 0
    assert vs.stats()["envelope_exits"] == 1


def test_the_ticks_whose_features_still_read_an_excursion_are_degraded(models):
    """A kerb strike: one front deflection far beyond the training rows for 60 ms (one tick sees it), back in range
    after. The two ticks after it are inside by their inputs, but their features read the strike's row (the
    deflection's rate, from the previous tick; the history reaches 2 ticks back): DEGRADED and flagged, then
    VALID again. Before, they were VALID on a deflection rate some 30 times the training rows' largest."""
    def kerb(t, sig) -> None:
        sig["susp_defl_fl_m"] = np.where((t >= 5.98) & (t < 6.04), 0.14, sig["susp_defl_fl_m"])

    vs, ticks, health, events = _drive(models[0], kerb)
    k = next(i for i, (tk, _, o) in enumerate(ticks) if o)
    assert 5.95 <= ticks[k][0] <= 6.1 and vs.counters["envelope_exits"] == 1
    assert [(s, o) for _, s, o in ticks[k:k + 3]] == [((DEGRADED, DEGRADED), True)] * 3
    assert all(s == (VALID, VALID) and not o for _, s, o in ticks[k + 3:k + 40])
    assert all(s == (VALID, VALID) and not o for _, s, o in ticks[k - 40:k])
    assert [int(h["VS_OutOfEnvelope"]) for h in health] == [int(o) for _, _, o in ticks]
    assert sum(e["event"] == "envelope_return" for e in events) == 1


def test_a_card_without_an_envelope_checks_none(models):
    vs, ticks, health, events = _drive(models[1])
    assert vs.envelope is None and vs.counters["envelope_exits"] == 0
    assert not any(o for _, _, o in ticks)
    assert not any(e["event"].startswith("envelope_") for e in events)
    assert all(int(h["VS_OutOfEnvelope"]) == 0 for h in health)
    assert ticks[-1][1] == (VALID, VALID)


# ------------------------------------------------------------------------------------------------ score
def test_score_splits_the_error_at_the_envelope(models):
    from virtsensor.learning.dataset import Run
    from virtsensor.learning.scoring import markdown, score_runs

    t, sig = synthetic_streams(12.0, seed=11)
    plain = simulated_recording(t, sig).table
    sig["vx_mps"] = np.where((t >= EXCURSION_S[0]) & (t < EXCURSION_S[1]), 70.0, sig["vx_mps"])
    for w in ("fl", "fr"):
        sig[f"wheel_speed_{w}_radps"] = sig["vx_mps"] / cat.ROLLING_RADIUS_M
    moved = simulated_recording(t, sig).table
    runs = [Run("plain", plain), Run("moved", moved)]
    res = score_runs(models[0], runs)
    inside_only, out = res["runs"][0]["envelope"], res["runs"][1]["envelope"]
    assert inside_only["outside_share"] == 0.0 and inside_only["outside"] is None
    assert inside_only["inside"]["n"] == res["runs"][0]["n"]
    assert out["outside_share"] == pytest.approx(2.0 / 12.0, abs=0.02)
    assert out["inside"]["n"] + out["outside"]["n"] == res["runs"][1]["n"]
    overall = res["overall"]["envelope"]
    assert overall["outside"]["n"] == out["outside"]["n"]
    assert overall["outside_share"] == pytest.approx(out["outside"]["n"] / res["overall"]["n"])
    assert out["outside"]["mae_nm"] > out["inside"]["mae_nm"]  # the model extrapolates there
    assert "outside envelope" in markdown(res) and "| — |" in markdown(res)
    none = score_runs(models[1], runs)
    assert none["overall"]["envelope"] is None and none["runs"][1]["envelope"] is None
    assert "outside envelope" not in markdown(none)


# ------------------------------------------------------------------------------------------------ evaluate, explain
def test_evaluate_gives_a_row_per_unseen_circuit():
    from test_features_dataset import synthetic_table

    from virtsensor.learning.dataset import Run
    from virtsensor.learning.evaluation import evaluate, held_out_runs, markdown_table
    from virtsensor.learning.training import RECIPES

    runs = [Run(f"r{i}", synthetic_table(300, 10 + i)) for i in range(6)]
    circuits = [Run("spa", synthetic_table(200, 97)), Run("monza", synthetic_table(200, 96, mu=0.6))]
    recipe = {"paper": {"features": "paper", "params": {**RECIPES["paper"]["params"], "max_iter": 200}}}
    res = evaluate(runs, None, recipe, circuits=circuits, seed=0)
    assert res["meta"]["circuits"] == {"spa": 200, "monza": 200}
    for col in (res["paper"], res["baselines"]["linear"], res["baselines"]["eq1_observer"]):
        assert {"circuit_spa", "circuit_monza"} <= set(col)
    table = markdown_table(res)
    m = res["paper"]["circuit_monza"]
    assert f"| Circuit monza (never trained on) | — | {m['r2']:.3f} / {m['mae_nm']:.2f} |" in table
    res["shipped_model"] = {"file": "m.onnx", "circuit_spa": {"envelope": {
        "outside_share": 0.25, "inside": {"r2": 0.9, "mae_nm": 1.0, "n": 150}, "outside": None}}}
    assert "| circuit_spa | 150 | 25.0 % | 0.900 / 1.00 | — |" in markdown_table(res)
    with pytest.raises(UserError, match="spa"):
        held_out_runs({}, [circuits[0], Run("spa", circuits[1].table)])


def test_shading_marks_each_out_of_envelope_stretch():
    pytest.importorskip("matplotlib")
    from virtsensor import plotting

    fig = plotting.figure(4.0, 3.0)
    ax = fig.add_subplot()
    t = np.arange(20) * 0.05
    mask = np.zeros(20, dtype=bool)
    mask[3:6] = mask[10] = mask[18:] = True
    assert plotting.shade(ax, t, mask, label="outside") == 3
    spans = sorted(p.get_x() for p in ax.patches)
    assert spans == pytest.approx([0.125, 0.475, 0.875])
    assert plotting.shade(ax, t, np.zeros(20, dtype=bool)) == 0


@pytest.mark.slow
def test_evaluate_command_scores_unseen_circuits_with_the_shipped_model(tmp_path, monkeypatch):
    import json

    from test_explain import _table

    from virtsensor.cli import main
    from virtsensor.learning import gripscore as gs
    from virtsensor.recordings.canlog import write_csv

    scored: list[list[str]] = []  # (the grip margin was pooled over --data too: mostly the model's training runs)
    t = np.arange(200) * 0.05

    def fake_grip(model, runs, params=None):
        scored.append(sorted(r.name for r in runs))
        m = gs.grip_metrics(t, np.full(200, 0.5), np.full(200, 0.5), np.full(200, 0.5), np.zeros(200, bool))
        return {"overall": gs.pool([m]), "runs": {}}

    monkeypatch.setattr(gs, "score_grip", fake_grip)

    rng = np.random.default_rng(7)
    (tmp_path / "data").mkdir()
    for i in range(4):
        write_csv(tmp_path / "data" / f"run{i}.csv", _table(rng, 300))
    far = _table(rng, 300)
    far["vx_mps"] = far["vx_mps"] * 1.2  # partly faster than any training row
    write_csv(tmp_path / "spa.csv", far)
    write_csv(tmp_path / "monza.csv", _table(rng, 300))
    model = tmp_path / "m.onnx"
    assert main(["train", "--data", str(tmp_path / "data"), "--out", str(model), "--quiet"]) == 0
    assert ModelCard.read(tmp_path / "m.card.json").envelope is not None  # train writes it
    out, md = tmp_path / "ev.json", tmp_path / "ev.md"
    assert main(["evaluate", "--model", str(model), "--data", str(tmp_path / "data"), "--circuits",
                 str(tmp_path / "spa.csv"), str(tmp_path / "monza.csv"), "--json", str(out), "--markdown", str(md),
                 "--quiet"]) == 0
    res = json.loads(out.read_text())
    shipped = res["shipped_model"]
    assert {"circuit_spa", "circuit_monza"} <= set(shipped) and "circuit_spa" in res["paper"]
    assert shipped["circuit_spa"]["envelope"]["outside_share"] > shipped["circuit_monza"]["envelope"]["outside_share"]
    text = md.read_text()
    assert "| Circuit spa (never trained on) |" in text and "| circuit_monza | 300 |" in text
    assert scored == [["monza", "spa"], ["run0", "run1", "run2", "run3"]]
    assert "Grip (the track's laps and the circuits, never trained on: 1 runs" in text
    assert "Grip (the --data runs, which the shipped model was likely trained on: in-sample, not a test: 1 runs" in text
    assert res["grip"]["overall"]["runs"] == 1 and res["grip_data"]["overall"]["runs"] == 1
