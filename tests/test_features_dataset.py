"""Feature front-end (offline == online), data set building, and evaluation on a known function."""

from __future__ import annotations

import numpy as np
import pytest

from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.features import HISTORY, PAPER, Feature, FeatureBuilder, FeatureSpec
from virtsensor.learning.dataset import Run, build_dataset, load_runs, split_track_laps
from virtsensor.learning.evaluation import evaluate, grouped_split, markdown_table, random_split
from virtsensor.learning.training import RECIPES
from virtsensor.recordings.canlog import write_csv


def synthetic_table(n: int, seed: int, mu: float = 1.0) -> dict[str, np.ndarray]:
    """A run whose SATs are a known smooth function of its inputs (``mu`` only labels it)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.05
    table = {"time_s": t}
    for k, name in enumerate(cat.INPUTS):
        f = 0.1 + 0.07 * k
        table[name] = np.sin(2 * np.pi * f * t + rng.uniform(0, 6)) * (1 + k % 3) + rng.normal(0, 0.01, n)
        if name.startswith("susp_defl"):
            table[name] *= 0.03  # inside the catalogue's +-0.15 m
    ay, assist = table["ay_mps2"], table["assist_torque_nm"]
    table["sat_fl_nm"] = -12.0 * np.tanh(ay / 2) + 3.0 * assist
    table["sat_fr_nm"] = -10.0 * np.tanh(ay / 2) + 2.0 * assist - 0.5 * table["steer_torque_nm"]
    table["road_mu"] = np.full(n, mu)
    return table


def test_offline_and_online_feature_vectors_are_identical():
    table = synthetic_table(200, 1)
    X = HISTORY.transform(table)
    ok = np.isfinite(X).all(axis=1)
    assert np.isnan(X[: HISTORY.history]).any(axis=1).all()
    assert ok.sum() == 200 - HISTORY.history
    for as_list in (False, True):  # the daemon pushes its list of held values; tests and tools push arrays
        builder = FeatureBuilder(HISTORY)
        rows = []
        for i in range(200):
            vals = [float(table[s][i]) for s in HISTORY.signals]
            v = builder.push(vals if as_list else np.array(vals))
            rows.append(np.full(len(HISTORY.features), np.nan) if v is None else np.array(v))
        online = np.array(rows)
        np.testing.assert_array_equal(online[ok], X[ok])
        builder.reset()
        assert builder.push(vals) is None and not builder.ready


def test_rate_and_accel_features_are_derivatives():
    t = np.arange(100) * 0.05
    table = {s: np.zeros(100) for s in cat.INPUTS}
    table["steer_angle_rad"] = 0.5 * t**2  # rate t, accel 1
    spec = FeatureSpec("d", (Feature("steer_angle_rad", "rate"), Feature("steer_angle_rad", "accel"),
                             Feature("steer_angle_rad", "lag", 2)))
    X = spec.transform(table)
    assert np.allclose(X[2:, 1], 1.0)
    assert np.allclose(X[1:, 0], t[1:] - 0.025)  # backward difference: rate half a tick earlier
    assert np.allclose(X[2:, 2], table["steer_angle_rad"][:-2])


def test_spec_round_trips_through_json_and_rejects_nonsense():
    assert FeatureSpec.from_json(HISTORY.to_json()) == HISTORY
    with pytest.raises(ValueError):
        FeatureSpec("bad", (Feature("sat_fl_nm"),))  # an output is not an input
    with pytest.raises(ValueError):
        FeatureSpec("bad", (Feature("ay_mps2", "lag", 0),))


def test_nonfinite_rows_are_dropped_and_counted():
    table = synthetic_table(100, 2)
    table["ay_mps2"][10] = np.nan
    table["sat_fr_nm"][20] = np.inf
    ds = build_dataset([Run("r", table)], PAPER)
    assert ds.dropped_nonfinite == 2 and len(ds.X) == 98
    assert np.isfinite(ds.X).all() and np.isfinite(ds.Y).all()
    ds_h = build_dataset([Run("a", synthetic_table(100, 3)), Run("b", synthetic_table(100, 4))], HISTORY)
    # history does not cross the run boundary: each run loses its own first ticks
    assert ds_h.dropped_nonfinite == 2 * HISTORY.history


def test_a_recording_lacking_a_needed_signal_is_refused(tmp_path):
    table = synthetic_table(50, 5)
    del table["wheel_speed_fr_radps"]
    path = tmp_path / "run.csv"
    write_csv(path, table)
    with pytest.raises(UserError, match=r"run\.csv.*wheel_speed_fr_radps"):
        load_runs([tmp_path], needed=PAPER.signals)
    runs = load_runs([path])
    with pytest.raises(UserError, match="wheel_speed_fr_radps"):
        build_dataset(runs, PAPER)


def test_splits():
    tr, te = random_split(1000, 0)
    assert len(te) == 300 and not set(tr) & set(te)
    groups = np.repeat(np.arange(10), 50)
    tr, te = grouped_split(groups, 0)
    assert not set(groups[tr]) & set(groups[te]) and len(set(groups[te])) == 3


def test_evaluation_recovers_a_known_function():
    runs = [Run(f"r{i}", synthetic_table(300, 10 + i, mu=(1.0, 0.6)[i % 2]), {"mu": (1.0, 0.6)[i % 2]})
            for i in range(10)]
    track = Run("track", {k: np.concatenate([a, b]) for (k, a), b in
                          zip(synthetic_table(200, 99).items(), synthetic_table(200, 98, mu=0.6).values(),
                              strict=True)})
    track.table["time_s"] = np.arange(400) * 0.05
    assert set(split_track_laps(track)) == {"dry", "wet"}
    recipe = {"paper": {"features": "paper", "params": {**RECIPES["paper"]["params"], "max_iter": 300}}}
    res = evaluate(runs, track, recipe, seed=0)
    assert res["paper"]["test"]["r2"] > 0.99
    assert res["paper"]["grouped"]["r2"] > 0.98
    assert res["baselines"]["linear"]["grouped"]["r2"] > 0.5
    assert res["paper"]["track_dry"]["mae_nm"] < res["baselines"]["linear"]["track_dry"]["mae_nm"]
    for key in ("train", "test", "grouped", "track_dry", "track_wet"):
        m = res["paper"][key]
        assert {"r2", "mae_nm", "fl", "fr", "axle"} <= set(m)
        assert m["r2"] == pytest.approx((m["fl"]["r2"] + m["fr"]["r2"]) / 2)
    assert "| Magny-Cours wet asphalt | 0.931 / 8.10 |" in markdown_table(res)


def test_evaluation_of_one_run_is_refused_before_any_fit():
    recipe = {"paper": {"features": "paper", "params": {**RECIPES["paper"]["params"], "max_iter": 5}}}
    with pytest.raises(UserError, match=r"^--data: 1 run\(s\) with usable rows for the 'paper' features; evaluate "
                                        r"holds whole runs out \(30 % of them, at least one\) and trains on the "
                                        r"others, so it needs at least 2$"):
        evaluate([Run("r0", synthetic_table(100, 1))], None, recipe, seed=0)


def _write_runs(d, n_runs=8, n=240):
    d.mkdir()
    for i in range(n_runs):
        write_csv(d / f"run{i}.csv", synthetic_table(n, 40 + i))
    return d


@pytest.mark.slow
def test_train_and_evaluate_from_the_command_line(tmp_path, capsys):
    import json

    from virtsensor.cli import main
    from virtsensor.model.onnx import OnnxModel

    data = _write_runs(tmp_path / "data")
    track = tmp_path / "track.csv"
    both = {k: np.concatenate([a, b]) for (k, a), b in
            zip(synthetic_table(200, 1).items(), synthetic_table(200, 2, mu=0.7).values(), strict=True)}
    both["time_s"] = np.arange(400) * 0.05
    write_csv(track, both)
    model = tmp_path / "m.onnx"
    assert main(["train", "--data", str(data), "--recipe", "improved", "--out", str(model), "--quiet"]) == 0
    loaded = OnnxModel.load(model)
    card = loaded.card
    assert card["recipe"]["features"] == "history" and card["training_data"]["runs"] == 8
    assert [i["name"] for i in card["inputs"]] == list(loaded.input_names)
    assert card["metrics"]["grouped_holdout"]["r2"] > 0.9
    out = tmp_path / "eval.json"
    assert main(["evaluate", "--model", str(model), "--data", str(data), "--track", str(track),
                 "--json", str(out), "--quiet"]) == 0
    res = json.loads(out.read_text())
    for key in ("paper", "improved"):
        assert set(res[key]) == {"train", "test", "grouped", "track_dry", "track_wet"}
    assert set(res["baselines"]) == {"linear", "eq1_observer"}
    assert {"track_dry", "track_wet"} <= set(res["shipped_model"])
    assert res["grip"] is None  # (synthetic tables carry no grip truth: no grip figures)
    assert "Magny-Cours dry asphalt" in capsys.readouterr().out
    # a recording without a needed signal is refused, naming it (one line, exit 2)
    bad = _write_runs(tmp_path / "bad", n_runs=1)
    table = synthetic_table(100, 3)
    del table["motor_torque_nm"]
    write_csv(bad / "run0.csv", table)
    assert main(["train", "--data", str(bad), "--out", str(tmp_path / "x.onnx"), "--quiet"]) == 2
    assert "motor_torque_nm" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists()


@pytest.mark.parametrize("copied", [False, True])
def test_evaluate_refuses_a_run_both_held_out_and_trained_on(tmp_path, capsys, copied):
    """--train-extra runs are trained on in every protocol: a --data run among them (the same file, or a copy of
    it under another name) would be tested on after training on it."""
    import shutil
    from pathlib import Path

    from virtsensor.cli import main

    data = _write_runs(tmp_path / "data", n_runs=3, n=60)
    extra = data
    if copied:
        extra = tmp_path / "extra"
        extra.mkdir()
        shutil.copy(data / "run1.csv", extra / "renamed.csv")
    out = tmp_path / "e.json"
    model = Path(__file__).resolve().parents[1] / "models" / "improved.onnx"
    assert main(["evaluate", "--model", str(model), "--data", str(data), "--train-extra", str(extra),
                 "--json", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "given both as --data and as --train-extra" in err, err
    assert ("the same content" in err) == copied
    assert not out.exists()


def test_grid_search_scores_candidates_on_held_out_runs_and_ranks_them():
    """Section III.B: every candidate is scored by R2 on runs it never saw; a network too
    small for the function must rank below one that can fit it."""
    from virtsensor.learning.training import PAPER_PARAMS, grid_search

    rng = np.random.default_rng(0)
    X = rng.uniform(-2.0, 2.0, size=(1200, 3))
    Y = 10.0 * np.column_stack([np.sin(X[:, 0]) * X[:, 1], X[:, 2] ** 2])
    groups = np.repeat(np.arange(12), 100)
    res = grid_search(X, Y, groups, grid={"hidden_layer_sizes": [(1,), (16, 8)]}, folds=3, n_jobs=1,
                      progress=False, base_params={**PAPER_PARAMS, "early_stopping": False, "max_iter": 400,
                                                        "learning_rate_init": 1e-2})
    assert [c["params"]["hidden_layer_sizes"] for c in res.candidates] == [(16, 8), (1,)]
    assert res.best_params["hidden_layer_sizes"] == (16, 8) and res.best_r2 == res.candidates[0]["r2_mean"]
    assert res.candidates[0]["r2_mean"] > 0.5 > res.candidates[1]["r2_mean"]
    assert (res.rows, res.folds) == (1200, 3)
    with pytest.raises(ValueError, match="at least 3 runs"):
        grid_search(X, Y, np.zeros(len(X), dtype=int), folds=3, n_jobs=1, progress=False)


def test_a_grid_candidate_with_a_nonfinite_fold_ranks_last_and_the_result_is_json(monkeypatch):
    """A candidate that diverges (or meets a flat fold) scores a non-finite R2: it is ranked last with null scores
    (the model card is JSON, which has no NaN), and a grid where every candidate does so is refused."""
    import json

    import virtsensor.learning.training as tr

    rng = np.random.default_rng(1)
    X, Y, groups = rng.normal(size=(90, 2)), rng.normal(size=(90, 2)), np.repeat(np.arange(3), 30)
    monkeypatch.setattr(tr, "_score_candidate", lambda params, *a: np.nan if params["alpha"] < 1e-3 else 0.25)
    res = tr.grid_search(X, Y, groups, grid={"alpha": [1e-4, 1e-2]}, folds=3, n_jobs=1, progress=False)
    assert [c["params"]["alpha"] for c in res.candidates] == [1e-2, 1e-4] and res.best_r2 == 0.25
    assert res.candidates[1]["r2_mean"] is None and res.candidates[1]["nonfinite_folds"] == 3
    json.dumps(res.candidates, allow_nan=False)
    monkeypatch.setattr(tr, "_score_candidate", lambda *a: -np.inf)
    with pytest.raises(ValueError, match="no candidate has a finite R2"):
        tr.grid_search(X, Y, groups, grid={"alpha": [1e-4, 1e-2]}, folds=3, n_jobs=1, progress=False)


def test_evaluate_refuses_a_run_without_a_usable_sample(tmp_path, capsys):
    """A run whose every row lacks an input (ay all NaN) is refused in one line naming it, as ``score`` does,
    instead of counting as a run that gave nothing."""
    from pathlib import Path

    from virtsensor.cli import main

    data = _write_runs(tmp_path / "data", n_runs=3, n=60)
    table = synthetic_table(60, 9)
    table["ay_mps2"] = np.full(60, np.nan)
    write_csv(data / "allnan.csv", table)
    out = tmp_path / "e.json"
    model = Path(__file__).resolve().parents[1] / "models" / "improved.onnx"
    assert main(["evaluate", "--model", str(model), "--data", str(data), "--json", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "allnan.csv: no sample with every input" in err, err
    assert not out.exists()


def test_an_unreadable_run_in_a_data_directory_is_one_line_exit_2(tmp_path, capsys, monkeypatch):
    """A run file that cannot be read (no permission) inside a directory given as --data is the request's mistake,
    as the same file given itself is: exit 2 naming it (it was exit 1, the machine's error)."""
    from pathlib import Path

    import virtsensor.recordings.canlog as canlog
    from virtsensor.cli import main

    data = _write_runs(tmp_path / "data", n_runs=3, n=60)
    real = canlog.read_csv

    def denied(path, *a, **k):  # (the suite runs as root, whom file modes do not stop)
        if Path(path).name == "run1.csv":
            raise PermissionError(13, "Permission denied", str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(canlog, "read_csv", denied)
    model = Path(__file__).resolve().parents[1] / "models" / "improved.onnx"
    out = tmp_path / "s.json"
    assert main(["score", "--model", str(model), "--data", str(data), "--json", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "run1.csv: not readable (Permission denied)" in err, err
    assert not out.exists()


def test_the_eq1_observer_is_fitted_on_column_torques_of_whole_runs():
    """Targets that are exactly the observer's model (a share of the column torque plus a constant): fitted on the
    random split's training rows, it recovers them, because the column torque (the steering angle's derivatives)
    is computed on whole runs before the rows are taken (on the rows alone, 50 ms apart no longer, it was not)."""
    from virtsensor.learning.dataset import Dataset
    from virtsensor.learning.evaluation import _observer_fit_predict
    from virtsensor.learning.training import SteeringObserver

    names = ("steer_angle_rad", "steer_torque_nm", "assist_torque_nm")
    rng = np.random.default_rng(3)
    Xs, groups = [], []
    for g in range(4):
        t = np.arange(400) * cat.TABLE_TICK_S
        delta = 0.3 * np.sin(2 * np.pi * (0.3 + 0.4 * g) * t) + 0.05 * np.sin(2 * np.pi * 1.7 * t + g)
        Xs.append(np.column_stack([delta, rng.normal(0, 2, len(t)), rng.normal(0, 5, len(t))]))
        groups.append(np.full(len(t), g))
    X, grp = np.vstack(Xs), np.concatenate(groups)
    obs = SteeringObserver(names)
    tau = np.concatenate([obs.column_torque(X[grp == g]) for g in range(4)])
    Y = np.column_stack([-0.45 * tau + 1.0, -0.45 * tau - 1.0])
    ds = Dataset(X, Y, grp, [f"r{g}" for g in range(4)], [{}] * 4, names, ("sat_fl_nm", "sat_fr_nm"), 0,
                 np.zeros(len(X)))
    tr, te = random_split(len(X), 0)
    pred = _observer_fit_predict(ds, {"all": ds}, rows=tr)["all"]
    np.testing.assert_allclose(pred[te], Y[te], atol=1e-6)


def test_the_track_laps_come_only_from_a_magny_cours_recording(tmp_path):
    """``--track`` takes the Magny-Cours recording: a run whose metadata (manifest entry or its own sidecar) names
    another manoeuvre is refused in one line; one without metadata (measured) is split as given."""
    import json

    from virtsensor.errors import UserError

    table = synthetic_table(200, 5)
    table["time_s"] = np.arange(200) * 0.05
    table.pop("road_mu", None)  # (no truth: the two halves in time)
    with pytest.raises(UserError, match=r"a steering-pulse run \(its metadata\), not a Magny-Cours recording"):
        split_track_laps(Run("sp", table, {"manoeuvre": "steering-pulse"}))
    path = tmp_path / "sp.csv"
    path.write_text("")
    (tmp_path / "sp.json").write_text(json.dumps({"file": "sp.csv", "manoeuvre": "fishhook"}))
    with pytest.raises(UserError, match=r"sp\.csv: a fishhook run"):
        split_track_laps(Run("sp", table, {}, path))
    (tmp_path / "sp.json").write_text(json.dumps({"file": "other.csv", "manoeuvre": "fishhook"}))  # (another's)
    assert set(split_track_laps(Run("sp", table, {}, path))) == {"dry", "wet"}
    assert set(split_track_laps(Run("mc", table, {"manoeuvre": "magny-cours"}))) == {"dry", "wet"}


def test_a_paper_card_s_recipe_is_the_paper_recipe():
    """evaluate takes a paper-recipe model's 'improved' column from the improved recipe; comparing the card's
    recipe (JSON: lists) with the one in memory (tuples) never matched, so it evaluated the paper recipe twice,
    once labelled 'improved'."""
    import json

    from virtsensor.assets import model_path
    from virtsensor.learning.training import RECIPES, same_recipe

    card = json.loads(model_path("paper").with_suffix(".card.json").read_text())
    assert card["recipe"] != RECIPES["paper"] and same_recipe(card["recipe"], RECIPES["paper"])
    assert not same_recipe(card["recipe"], RECIPES["improved"])
