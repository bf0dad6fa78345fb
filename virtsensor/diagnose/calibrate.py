"""Extend the model and measure the gain.

The identified effect is added to the simulator (the same parameter overrides
the identification used), a training campaign is regenerated with it, the
estimator is retrained with the same recipe and seed, and both estimators (the
one trained on the nominal simulator and the calibrated one) are scored on
held-out measured runs that played no part in the diagnosis or the
calibration. Because recipe, campaign and seed are the same, the difference
between the two is the calibration's doing.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.features import SPECS
from virtsensor.interrupt import fitted
from virtsensor.learning.dataset import Run, build_dataset
from virtsensor.learning.training import RECIPES, make_pipeline
from virtsensor.metrics import metrics
from virtsensor.recordings.measured import MeasuredRun


def campaign_runs(params: Mapping[str, Any], preset: str, seed: int, n_jobs: int) -> list[Run]:
    """The canonical tables of a campaign preset simulated with ``params``."""
    from sim.campaign import PRESETS, run_campaign
    from virtsensor.recordings.simulated import run_table

    requests = PRESETS[preset](seed)
    tables = run_campaign(requests, params, n_jobs=n_jobs, writer=run_table, progress=False)
    return [Run(f"{r.manoeuvre}-{r.speed_kmh:g}-{r.mu:g}-{r.seed}", t, {"manoeuvre": r.manoeuvre, "mu": r.mu})
            for r, t in zip(requests, tables, strict=True)]


@dataclass
class Estimator:
    """A trained estimator with what it was trained on."""

    pipeline: Any
    recipe: dict[str, Any]
    fingerprint: str
    samples: int


def train(params: Mapping[str, Any], *, preset: str = "wide", recipe: str = "improved", seed: int = 0,
          n_jobs: int = 1, max_iter: int | None = None, ensemble: int = 3) -> Estimator:
    """Simulate the campaign with ``params`` and train the recipe on it.

    ``ensemble`` networks are trained from different initial weights (seeds
    ``seed ... seed + ensemble - 1``) and merged into one wider network that
    outputs their mean (:func:`merge_ensemble`): on a small campaign one network's
    error depends on its initialisation by as much as a calibration changes it, and
    the mean of a few is a steadier yardstick before and after.
    """
    import warnings

    from sklearn.exceptions import ConvergenceWarning

    rec = {**RECIPES[recipe], "params": dict(RECIPES[recipe]["params"])}
    if max_iter is not None:
        rec["params"]["max_iter"] = int(max_iter)
    runs = campaign_runs(params, preset, seed, n_jobs)
    ds = build_dataset(runs, SPECS[rec["features"]])
    members = []
    for k in range(max(1, ensemble)):
        model = make_pipeline(rec["params"], random_state=seed + k)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            fitted(partial(model.fit, ds.X, ds.Y))
        members.append(model)
    rec["ensemble"] = len(members)
    rec["trained_on"] = {"recipe": recipe, "preset": preset, "seed": int(seed)}
    return Estimator(merge_ensemble(members), rec, ds.fingerprint(), len(ds.Y))


def retrain_like(est: Estimator, params: Mapping[str, Any], *, n_jobs: int = 1) -> Estimator:
    """``est``'s training (:func:`train`: recipe, campaign preset, seed, epochs, ensemble size) redone on the
    simulator ``params``: the same recipe, the same runs' randomness and the same initial weights, so that
    the two estimators differ by the simulator alone (like for like). ``est`` must come from :func:`train`."""
    on = est.recipe.get("trained_on")
    if on is None:
        raise ValueError("the estimator does not say how it was trained (not from calibrate.train)")
    return train(params, preset=on["preset"], recipe=on["recipe"], seed=on["seed"], n_jobs=n_jobs,
                 max_iter=int(est.recipe["params"]["max_iter"]), ensemble=int(est.recipe["ensemble"]))


def merge_ensemble(pipelines: Sequence[Any]) -> Any:
    """One ``Pipeline(scaler, MLPRegressor)`` computing the mean of several that share
    their (fitted) scaler: hidden layers side by side (block-diagonal weights), the
    output layer's weights divided by their number. Exact, and exported to ONNX like
    any other network."""
    import copy

    if len(pipelines) == 1:
        return pipelines[0]
    s0 = pipelines[0][0]
    for p in pipelines[1:]:
        for attr in ("center_", "scale_", "mean_", "var_", "min_"):
            a, b = getattr(s0, attr, None), getattr(p[0], attr, None)
            if (a is None) != (b is None) or (a is not None and not np.array_equal(a, b)):
                raise ValueError("ensemble members must share their scaler")
    mlps = [p[-1] for p in pipelines]
    k = len(mlps)
    merged = copy.deepcopy(mlps[0])
    n_layers = len(mlps[0].coefs_)
    coefs, inter = [], []
    for layer in range(n_layers):
        ws = [m.coefs_[layer] for m in mlps]
        bs = [m.intercepts_[layer] for m in mlps]
        if layer == 0:
            coefs.append(np.hstack(ws))
            inter.append(np.concatenate(bs))
        elif layer == n_layers - 1:
            coefs.append(np.vstack(ws) / k)
            inter.append(np.mean(bs, axis=0))
        else:
            rows = sum(w.shape[0] for w in ws)
            cols = sum(w.shape[1] for w in ws)
            w = np.zeros((rows, cols))
            r = c = 0
            for wi in ws:
                w[r:r + wi.shape[0], c:c + wi.shape[1]] = wi
                r, c = r + wi.shape[0], c + wi.shape[1]
            coefs.append(w)
            inter.append(np.concatenate(bs))
    merged.coefs_, merged.intercepts_ = coefs, inter
    merged.hidden_layer_sizes = tuple(int(w.shape[1]) for w in coefs[:-1])
    out = copy.deepcopy(pipelines[0])
    out.steps[-1] = (out.steps[-1][0], merged)
    return out


def measured_matrix(runs: Sequence[MeasuredRun], spec_name: str) -> tuple[np.ndarray, np.ndarray]:
    """Feature vectors and reference SATs of measured runs, segment by segment (the
    history never spans a gap); rows that are not finite are dropped."""
    segments = [Run(f"{run.name}#{s}", run.segment_table(seg), path=run.path)
                for run in runs for s, seg in enumerate(run.segments)]
    ds = build_dataset(segments, SPECS[spec_name], cat.OUTPUTS)
    return ds.X, ds.Y


def score(est: Estimator, runs: Sequence[MeasuredRun]) -> dict[str, Any]:
    """R2 and MAE (Nm) of an estimator on measured runs (mean of both wheels, and per wheel)."""
    return scores([est], runs)[0]


def scores(ests: Sequence[Estimator], runs: Sequence[MeasuredRun]) -> list[dict[str, Any]]:
    """:func:`score` of each estimator on the same runs; the feature matrix is built
    once per distinct feature spec."""
    matrices: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    out = []
    for est in ests:
        spec_name = est.recipe["features"]
        if spec_name not in matrices:
            matrices[spec_name] = measured_matrix(runs, spec_name)
        X, Y = matrices[spec_name]
        out.append(metrics(Y, est.pipeline.predict(X)))
    return out


#: rows per block of the held-out gain's bootstrap (5 s at 20 Hz: longer than the errors' correlation)
GAIN_BLOCK = 100


def paired_gain(before: Estimator, after: Estimator, runs: Sequence[MeasuredRun], *, seed: int = 0,
                n_boot: int = 1000) -> dict[str, Any]:
    """The held-out SAT MAE gain of ``after`` over ``before`` (Nm, > 0: after is better) with its 95 % interval
    from a block bootstrap over 5 s stretches of the held-out rows (both estimators on the same rows:
    paired); ``better`` when the interval lies above 0 (the gain is more than noise)."""
    X, Y = measured_matrix(runs, before.recipe["features"])
    ea = np.mean(np.abs(before.pipeline.predict(X) - Y), axis=1)
    Xa, Ya = (X, Y) if after.recipe["features"] == before.recipe["features"] else \
        measured_matrix(runs, after.recipe["features"])
    eb = np.mean(np.abs(after.pipeline.predict(Xa) - Ya), axis=1)
    d = ea - eb
    nb = max(1, len(d) // GAIN_BLOCK)
    blocks = np.array([np.sum(x) for x in np.array_split(d, nb)])
    sizes = np.array([len(x) for x in np.array_split(d, nb)])
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, nb, size=(n_boot, nb))
    boot = blocks[idx].sum(axis=1) / sizes[idx].sum(axis=1)
    lo, hi = (float(v) for v in np.quantile(boot, [0.025, 0.975]))
    mean = float(np.mean(d)) if len(d) else 0.0
    return {"mae_gain_nm": mean, "relative": mean / float(np.mean(ea)) if len(ea) and np.mean(ea) > 0 else 0.0,
            "ci95_nm": [lo, hi], "better": bool(lo > 0.0), "blocks": int(nb)}


def undo_sensor_errors(est: Estimator, errors: Sequence[tuple[str, float, float]]) -> Estimator:
    """``est`` with identified sensor errors of its inputs undone at its input, folded into its scaler.

    ``errors``: ``(signal, offset, gain)`` per faulty input, in the sensor model of :mod:`sim.sensors`
    (``measured = gain * right + offset``, the signal's unit). The estimator then computes its features
    from ``(measured - offset) / gain``: a ``value`` or ``lag`` feature of the signal becomes
    ``(x - offset) / gain``, a ``rate`` or ``accel`` one ``x / gain`` (every feature is linear in its signal,
    :mod:`virtsensor.features`), which the scaler's centre and scale absorb exactly. The network is
    untouched, so the result exports to ONNX and runs in the daemon like any other estimator. A delay cannot
    be undone at the input in real time (it would need the future): it is not one of these.
    """
    import copy

    from sklearn.preprocessing import MinMaxScaler, RobustScaler, StandardScaler

    by_signal = {s: (float(o), float(g)) for s, o, g in errors}
    for s, (_, g) in by_signal.items():
        if s not in cat.INPUTS or not g > 0.0:
            raise ValueError(f"cannot undo a sensor error of {s!r} with gain {g} at the input")
    feats = SPECS[est.recipe["features"]].features
    off = np.array([by_signal.get(f.signal, (0.0, 1.0))[0] if f.op in ("value", "lag") else 0.0 for f in feats])
    gain = np.array([by_signal.get(f.signal, (0.0, 1.0))[1] for f in feats])
    pipe = copy.deepcopy(est.pipeline)
    scaler = pipe.steps[0][1]
    if isinstance(scaler, MinMaxScaler):  # x * k + m, with x -> (x - off) / gain
        k = np.asarray(scaler.scale_, float)
        scaler.scale_, scaler.min_ = k / gain, np.asarray(scaler.min_, float) - off * k / gain
    elif isinstance(scaler, (RobustScaler, StandardScaler)):  # (x - c) / s, with x -> (x - off) / gain
        robust = isinstance(scaler, RobustScaler)
        c_attr = "center_" if robust else "mean_"
        c = getattr(scaler, c_attr)
        s = scaler.scale_
        setattr(scaler, c_attr, off + gain * (np.zeros(len(feats)) if c is None else np.asarray(c, float)))
        scaler.scale_ = gain * (np.ones(len(feats)) if s is None else np.asarray(s, float))
        if robust:
            scaler.with_centering = scaler.with_scaling = True
        else:
            scaler.with_mean = scaler.with_std = True
    else:
        raise TypeError(f"cannot fold an input correction into {type(scaler).__name__}")
    recipe = {**est.recipe, "inputs_corrected": {s: {"offset": o, "gain": g} for s, (o, g) in by_signal.items()}}
    return Estimator(pipe, recipe, est.fingerprint, est.samples)
