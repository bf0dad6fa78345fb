"""Table IV, reproduced and made honest.

Protocols, for each recipe (the paper's model, the improved one) and for the
baselines (the eq. (1) steering observer, a linear regression):

* ``train`` / ``test``: the paper's protocol, a random 70/30 split of the 20 Hz
  rows. Neighbouring samples 50 ms apart land on both sides of the split, so
  the test rows are nearly copies of training rows: this flatters R2.
* ``grouped``: whole runs held out (30 % of the runs, seeded): the honest
  figure for a manoeuvre the model has not seen.
* ``track_dry`` / ``track_wet``: the Magny-Cours laps (mu 1, then 0.7), never
  seen in training, with a model trained on all the Table I runs.
* ``circuit_<name>``: each recording given as a circuit never trained on (``circuits``),
  with the same model trained on all the runs.

R2 and MAE per wheel, their mean (``r2``, ``mae_nm``) and for the axle sum.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from virtsensor.features import PAPER, SPECS
from virtsensor.interrupt import fitted
from virtsensor.learning.dataset import Dataset, Run, build_dataset, split_track_laps
from virtsensor.learning.gripscore import grip_markdown
from virtsensor.learning.training import SteeringObserver, linear_pipeline, make_pipeline
from virtsensor.metrics import metrics

TEST_FRACTION = 0.3
#: fewest runs with usable rows evaluate works on: one held out, one to train on
MIN_RUNS = 2


def random_split(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The paper's split: 70/30 of the rows at random."""
    idx = np.random.default_rng(seed).permutation(n)
    k = int(round(n * (1 - TEST_FRACTION)))
    return np.sort(idx[:k]), np.sort(idx[k:])


def grouped_split(groups: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Whole runs held out: 30 % of the runs (at least one) go to the test side."""
    runs = np.unique(groups)
    rng = np.random.default_rng(seed + 1)
    n_test = max(1, int(round(len(runs) * TEST_FRACTION)))
    test_runs = rng.choice(runs, n_test, replace=False)
    test = np.isin(groups, test_runs)
    return np.flatnonzero(~test), np.flatnonzero(test)


def _observer_fit_predict(ds_train: Dataset, parts: Mapping[str, Dataset],
                          rows: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The eq. (1) observer differentiates within runs: fit and predict run by run. ``rows``: the rows of
    ``ds_train`` the least squares fits on (indices or a boolean mask; default all); the column torque is
    computed on its whole runs first (a run with rows taken out is not 50 ms apart between its remaining rows)."""
    obs = SteeringObserver(ds_train.feature_names)
    tau_all = np.empty(len(ds_train.X))
    for g in np.unique(ds_train.groups):
        m = ds_train.groups == g
        tau_all[m] = obs.column_torque(ds_train.X[m])
    tau, Y = (tau_all, ds_train.Y) if rows is None else (tau_all[rows], ds_train.Y[rows])
    obs.coef_, *_ = np.linalg.lstsq(np.column_stack([tau, np.ones_like(tau)]), Y, rcond=None)
    out = {}
    for name, ds in parts.items():
        P = np.empty_like(ds.Y)
        for g in np.unique(ds.groups):
            m = ds.groups == g
            P[m] = obs.predict(ds.X[m])
        out[name] = P
    return out


def evaluate(
    runs: Sequence[Run],
    track: Run | None,
    recipes: Mapping[str, Mapping[str, Any]],
    *,
    circuits: Sequence[Run] = (),
    seed: int = 0,
    baselines: bool = True,
    train_extra: Mapping[str, Sequence[Run]] | None = None,
    log: Callable[[str], None] = lambda s: None,
) -> dict[str, Any]:
    """All protocols for every recipe (and the baselines). See the module docstring.

    ``train_extra``: recipe name -> runs added to the *training* side of every protocol of that recipe
    (e.g. track driving); the test rows, the held-out runs, the laps and the circuits still come from
    ``runs``, ``track`` and ``circuits`` only, so the protocols stay comparable across recipes.

    Raises:
        UserError: two ``circuits`` with the same name (file stem); a run, lap or circuit with no usable row for a
            recipe's features (naming it); fewer than :data:`MIN_RUNS` runs (checked before any fit).
    """
    datasets = _datasets(runs, {*(r["features"] for r in recipes.values()), *([PAPER.name] if baselines else [])})
    extra_of = dict(train_extra or {})
    track_laps = split_track_laps(track) if track is not None else {}
    laps = held_out_runs(track_laps, circuits)
    result: dict[str, Any] = {}
    timing: dict[str, float] = {}
    sizes: dict[str, Any] = {}

    def protocols(name: str, spec_name: str, make: Callable[[], Any]) -> dict[str, Any]:
        spec = SPECS[spec_name]
        ds = datasets[spec_name]
        lap_ds = {k: build_dataset([r], spec) for k, r in laps.items()}
        for k, d in lap_ds.items():
            require_rows(d, [laps[k]], spec_name)
        sizes[name] = {"rows": int(len(ds.X)), "runs": len(ds.runs), "dropped_nonfinite": ds.dropped_nonfinite,
                       "features": list(ds.feature_names)}
        extra = build_dataset(extra_of[name], spec) if extra_of.get(name) else None
        if extra is not None:
            require_rows(extra, extra_of[name], spec_name)
            sizes[name]["train_extra"] = {"rows": int(len(extra.X)), "runs": len(extra.runs)}

        def fit(X: np.ndarray, Y: np.ndarray) -> Any:
            if extra is not None:
                X, Y = np.concatenate([X, extra.X]), np.concatenate([Y, extra.Y])
            return fitted(lambda: make().fit(X, Y))

        out: dict[str, Any] = {}
        tr, te = random_split(len(ds.X), seed)
        t0 = time.perf_counter()
        model = fit(ds.X[tr], ds.Y[tr])
        timing[f"{name}_fit_s"] = time.perf_counter() - t0
        out["train"] = metrics(ds.Y[tr], model.predict(ds.X[tr]))
        out["test"] = metrics(ds.Y[te], model.predict(ds.X[te]))
        log(f"{name}: random split test R2 {out['test']['r2']:.3f}, MAE {out['test']['mae_nm']:.2f} Nm")
        gtr, gte = grouped_split(ds.groups, seed)
        model = fit(ds.X[gtr], ds.Y[gtr])
        out["grouped"] = metrics(ds.Y[gte], model.predict(ds.X[gte]))
        log(f"{name}: runs held out R2 {out['grouped']['r2']:.3f}, MAE {out['grouped']['mae_nm']:.2f} Nm")
        if lap_ds:
            model = fit(ds.X, ds.Y)
            for k, d in lap_ds.items():
                out[k] = metrics(d.Y, model.predict(d.X))
                log(f"{name}: {k} R2 {out[k]['r2']:.3f}, MAE {out[k]['mae_nm']:.2f} Nm")
        return out

    for name, recipe in recipes.items():
        params = recipe["params"]
        result[name] = protocols(name, recipe["features"], lambda p=params: make_pipeline(p, seed))
    if baselines:
        result["baselines"] = {"linear": protocols("linear", PAPER.name, linear_pipeline)}
        result["baselines"]["eq1_observer"] = _observer_protocols(datasets[PAPER.name], laps, seed)
        log(f"eq1_observer: runs held out R2 {result['baselines']['eq1_observer']['grouped']['r2']:.3f}")
    result["meta"] = {"seed": seed, "timing_s": timing, "data": sizes, "test_fraction": TEST_FRACTION,
                      "track_laps": {k: int(len(r.table["time_s"])) for k, r in track_laps.items()},
                      "circuits": {r.name: int(len(r.table["time_s"])) for r in circuits}}
    return result


def _datasets(runs: Sequence[Run], spec_names: set[str]) -> dict[str, Dataset]:
    """The runs' dataset of each feature spec named, each with at least :data:`MIN_RUNS` runs with usable rows."""
    from virtsensor.errors import UserError

    out = {}
    for name in sorted(spec_names):
        ds = out[name] = build_dataset(runs, SPECS[name])
        require_rows(ds, runs, name)
        n = len(np.unique(ds.groups))
        if n < MIN_RUNS:
            raise UserError(f"--data: {n} run(s) with usable rows for the {name!r} features; evaluate holds "
                            f"whole runs out ({TEST_FRACTION * 100:g} % of them, at least one) and trains on the "
                            f"others, so it needs at least {MIN_RUNS}")
        require_variation(ds, name)
    return out


def require_rows(ds: Dataset, runs: Sequence[Run], spec_name: str) -> None:
    """Refuse a run of ``ds`` (built from ``runs``) that gave it no row, naming its file (as ``score`` does); a
    run whose TPMS pressures are unknown gives a pressure model none by design and is not refused."""
    from virtsensor.errors import UserError

    given = set(np.unique(ds.groups).tolist())
    empty = [i for i in range(len(runs)) if i not in given and not runs[i].meta.get("pressure_unknown")]
    if empty:
        run = runs[empty[0]]
        raise UserError(f"{run.path or run.name}: no sample with every input of the {spec_name!r} features and both "
                        "reference SATs finite")


def require_variation(ds: Dataset, spec_name: str) -> None:
    """Refuse a data set in which a feature takes one value in every row (a signal that never varied in any run):
    a model cannot learn what it does, its scaler has no spread to scale it by (scikit-learn then scales by 1) and
    the card's validity envelope would mark any other value outside. NaN rows (an optional feature) are left out.
    (A feature that varies in few rows passes: the check is for a signal that never moved.)

    Raises:
        UserError: ``--data: feature <name> of the <spec> features is <value> in every one of the <n> rows...``.
    """
    from virtsensor.errors import UserError

    if not len(ds.X):
        return
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (an all-NaN optional column: no value, not constant)
        lo, hi = np.nanmin(ds.X, axis=0), np.nanmax(ds.X, axis=0)
    same = np.flatnonzero(lo == hi)
    if same.size:
        j = int(same[0])
        also = f" (and {same.size - 1} more feature(s))" if same.size > 1 else ""
        raise UserError(f"--data: feature {ds.feature_names[j]} of the {spec_name!r} features is {lo[j]:.6g} in every "
                        f"one of the {len(ds.X)} rows of {len(np.unique(ds.groups))} run(s){also}: a model cannot "
                        "learn what it does; give runs where it varies")


def held_out_runs(track_laps: Mapping[str, Run], circuits: Sequence[Run]) -> dict[str, Run]:
    """The runs scored with a model trained on all the runs: ``track_<lap>`` and ``circuit_<name>``.

    Raises:
        UserError: two circuits with the same name.
    """
    from virtsensor.errors import UserError

    out = {f"track_{k}": r for k, r in track_laps.items()}
    for r in circuits:
        key = f"circuit_{r.name}"
        if key in out:
            raise UserError(f"--circuits {r.path or r.name}: another circuit has the name {r.name!r} (file stem)")
        out[key] = r
    return out


def _observer_protocols(ds: Dataset, laps: Mapping[str, Run], seed: int) -> dict[str, Any]:
    """The eq. (1) observer's protocols on ``ds``, the runs' dataset of the paper's features."""
    out: dict[str, Any] = {}
    tr, te = random_split(len(ds.X), seed)
    # the observer needs whole runs (it differentiates in time): its column torque is computed on whole runs,
    # then fitted on the training rows, and the random split applied to rows of runs predicted whole
    pred = _observer_fit_predict(ds, {"all": ds}, rows=tr)["all"]
    out["train"] = metrics(ds.Y[tr], pred[tr])
    out["test"] = metrics(ds.Y[te], pred[te])
    gtr, gte = grouped_split(ds.groups, seed)
    pred = _observer_fit_predict(ds.subset(gtr), {"test": ds.subset(gte)})["test"]
    out["grouped"] = metrics(ds.Y[gte], pred)
    if laps:
        lap_ds = {k: build_dataset([r], PAPER) for k, r in laps.items()}
        preds = _observer_fit_predict(ds, lap_ds)
        for k, d in lap_ds.items():
            out[k] = metrics(d.Y, preds[k])
    return out


PAPER_TABLE_IV = {"train": (0.986, 2.4), "test": (0.982, 2.59), "track_dry": (0.971, 3.1), "track_wet": (0.931, 8.1)}
ROWS = (("train", "Training phase"), ("test", "Test phase (random 30 % of rows)"),
        ("grouped", "Runs held out (30 % of runs)"), ("track_dry", "Magny-Cours dry asphalt"),
        ("track_wet", "Magny-Cours wet asphalt"))


def markdown_table(result: Mapping[str, Any]) -> str:
    """A Table IV with the paper's figures beside ours (R2 / MAE Nm, mean of both wheels), one row per circuit
    never trained on; then, when the shipped model has an envelope split (:func:`envelope_table`), that; then the
    shipped model's grip margin (:func:`virtsensor.learning.gripscore.grip_markdown`) on the runs it never trained
    on (``result["grip"]``: the track's laps and the circuits) and, apart, on ``--data`` (``result["grip_data"]``,
    in-sample for a model trained on them)."""
    cols = [("paper", result.get("paper")), ("improved", result.get("improved"))]
    base = result.get("baselines", {})
    cols += [("linear", base.get("linear")), ("eq. (1) observer", base.get("eq1_observer"))]
    cols = [(n, c) for n, c in cols if c]
    head = "| simulation test | paper (Table IV) | " + " | ".join(f"{n} R2 / MAE" for n, _ in cols) + " |"
    sep = "|---|---|" + "---|" * len(cols)
    lines = [head, sep]
    circuits = tuple((f"circuit_{c}", f"Circuit {c} (never trained on)")
                     for c in result.get("meta", {}).get("circuits", {}))
    for key, label in ROWS + circuits:
        ref = PAPER_TABLE_IV.get(key)
        cells = [f"{ref[0]:.3f} / {ref[1]:.2f}" if ref else "—"]
        for _, c in cols:
            m = c.get(key)
            cells.append(f"{m['r2']:.3f} / {m['mae_nm']:.2f}" if m else "—")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    env = envelope_table(result)
    # (the shipped model's grip margin, where runs carry its truth: held out, then --data apart)
    held = grip_markdown(result.get("grip"), "the track's laps and the circuits, never trained on")
    data = grip_markdown(result.get("grip_data"), "the --data runs, which the shipped model was likely trained on: "
                                                  "in-sample, not a test")
    grip = "\n".join(g for g in (held, data) if g)  # (two paragraphs)
    return "\n".join(lines) + "\n" + ("\n" + env if env else "") + ("\n" + grip if grip else "")


def envelope_table(result: Mapping[str, Any]) -> str:
    """The shipped model file on the laps and circuits, inside and outside its card's validity envelope
    (Markdown; empty when it has no envelope split)."""
    shipped = result.get("shipped_model") or {}
    rows = [(k, m["envelope"]) for k, m in shipped.items() if isinstance(m, Mapping) and m.get("envelope")]
    if not rows:
        return ""
    lines = [f"Shipped model `{shipped.get('file')}` against its validity envelope (R2 / MAE Nm):", "",
             "| run | samples | outside envelope | inside | outside |", "|---|---|---|---|---|"]
    for key, e in rows:
        side = ["—" if e[k] is None else f"{e[k]['r2']:.3f} / {e[k]['mae_nm']:.2f}" for k in ("inside", "outside")]
        n = sum(e[k]["n"] for k in ("inside", "outside") if e[k] is not None)
        lines.append(f"| {key} | {n} | {100 * e['outside_share']:.1f} % | {side[0]} | {side[1]} |")
    return "\n".join(lines) + "\n"
