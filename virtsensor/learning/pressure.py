"""The pressure protocol (issue 17): whole held-out runs at tyre pressures away from nominal, where the
pressure-free model and the TPMS model are scored side by side, per wheel and for the axle.

Runs are grouped by their front tyres' pressure as their own TPMS reports it (the median over the run of the
two front pressures, to 0.1 bar): the protocol needs no metadata and works on any recording that carries the
TPMS. Both models are scored on exactly the same rows (every feature of the TPMS model and both reference SATs
finite). Beside them, the physics alternative: the pressure-free model's estimate scaled per wheel by a
quadratic in the relative pressure ``dpi = p / p_nom - 1`` (the MF 6.1 pneumatic trail scales with
``1 - PPZ1 dpi``, the cornering stiffness with ``1 + PPY1 dpi``), ``sat = P (c0 + c1 dpi + c2 dpi^2)``, its three
coefficients per wheel fitted by least squares on the TPMS model's training runs: what a trail correction on top
of the pressure-free model can reach, measured on the same rows.

Acceptance (issue 17): at each off-nominal pressure the TPMS model's MAE lies within 10 % of its own MAE at
nominal, and at least 25 % below the pressure-free model's MAE on the same runs. Each group also states the mean
|SAT| of its rows: an under-inflated tyre has a longer contact patch and trail, so the same manoeuvres give larger
SATs (and, at the same relative error, a larger MAE) at 1.8 bar than at 2.2.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.features import FeatureSpec
from virtsensor.learning.dataset import Run, build_dataset
from virtsensor.metrics import metrics

__all__ = ["NOMINAL_BAR", "check_models", "fit_trail_correction", "pressure_protocol", "pressure_markdown",
           "run_pressure_bar"]

#: the catalogue car's placard pressure (gauge, bar): the pressure-free model's training pressure
NOMINAL_BAR = 2.2
#: acceptance: TPMS MAE off nominal <= (1 + this) x its MAE at nominal
WITHIN_NOMINAL = 0.10
#: acceptance: TPMS MAE <= (1 - this) x the pressure-free model's MAE on the same runs
GAIN_OVER_FREE = 0.25


def run_pressure_bar(run: Run) -> float:
    """The run's front tyre pressure (gauge, bar, to 0.1): the median of both front TPMS pressures over the run.

    Raises:
        UserError: the run carries no front TPMS pressure.
    """
    vals = np.concatenate([np.asarray(run.table.get(s, []), dtype=np.float64) for s in cat.TPMS_FRONT])
    vals = vals[np.isfinite(vals)]
    if vals.size == 0:
        raise UserError(f"{run.path or run.name}: no front TPMS pressure in this run (the pressure protocol needs it)")
    return round(float(np.median(vals)) / 1e5, 1)


def _dpi(X: np.ndarray, n_free: int) -> np.ndarray:
    return X[:, n_free:n_free + 2] / (NOMINAL_BAR * 1e5) - 1.0


def fit_trail_correction(free_model: Any, runs: Sequence[Run], spec: FeatureSpec) -> np.ndarray:
    """Coefficients (2 wheels, 3) of ``sat = P (c0 + c1 dpi + c2 dpi^2)`` fitted by least squares on ``runs``
    (rows where every feature of ``spec``, the TPMS spec, is finite), P the pressure-free model's estimate."""
    ds = build_dataset(runs, spec)
    n = free_model.n_features
    P = free_model.predict(ds.X[:, :n])
    d = _dpi(ds.X, n)
    coef = np.zeros((2, 3))
    for w in range(2):
        A = np.column_stack([P[:, w], P[:, w] * d[:, w], P[:, w] * d[:, w] ** 2])
        coef[w], *_ = np.linalg.lstsq(A, ds.Y[:, w], rcond=None)
    return coef


def _corrected(P: np.ndarray, d: np.ndarray, coef: np.ndarray) -> np.ndarray:
    return np.column_stack([P[:, w] * (coef[w, 0] + coef[w, 1] * d[:, w] + coef[w, 2] * d[:, w] ** 2)
                            for w in range(2)])


def _scores(Y: np.ndarray, P: np.ndarray) -> dict[str, Any]:
    m = metrics(Y, P)
    return {"mae_nm": m["mae_nm"], "r2": m["r2"], "n": m["n"],
            **{k: {"mae_nm": m[k]["mae_nm"], "r2": m[k]["r2"]} for k in ("fl", "fr", "axle")}}


def check_models(free_model: Any, tpms_model: Any) -> FeatureSpec:
    """The TPMS model's feature spec, once both models fit the protocol: the TPMS model's features are the
    pressure-free model's, then the two front tyre pressures (:data:`virtsensor.signals.TPMS_FRONT`), which
    is what :func:`pressure_protocol` reads. Cheap: call it before any work.

    Raises:
        UserError: the TPMS model's card names no usable feature spec, its inputs carry no front tyre pressure
            (a model of the paper or improved recipe, say), or its features are not the pressure-free model's
            followed by the two front pressures.
    """
    where = getattr(tpms_model, "path", "the TPMS model")
    try:
        spec = FeatureSpec.from_json(tpms_model.card["feature_spec"])
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{where}: no usable feature_spec in its model card ({exc})") from None
    if not set(cat.TPMS_FRONT) <= set(spec.signals):
        recipe = (tpms_model.card.get("recipe") or {}).get("features", spec.name)
        raise UserError(f"{where}: not a TPMS model: its card's inputs (features {recipe!r}) carry no front tyre "
                        f"pressure ({', '.join(cat.TPMS_FRONT)}); give a model trained with --recipe tpms")
    n = free_model.n_features
    if tuple(free_model.input_names) != spec.names[:n] or spec.names[n:] != tuple(cat.TPMS_FRONT):
        raise UserError(f"{getattr(free_model, 'path', 'model')}: its features are not the first ones of the TPMS "
                        f"model {where} (the rest being the two front tyre pressures)")
    return spec


def pressure_protocol(free_model: Any, tpms_model: Any, runs: Sequence[Run],
                      correction: np.ndarray | None = None) -> dict[str, Any]:
    """Score both models (and the trail correction, when given) per pressure group of ``runs``.

    Returns ``{"groups": {"1.8": {"runs", "free", "tpms", "trail_correction"?, "tpms_vs_nominal",
    "tpms_vs_free"}, ...}, "nominal_bar", "acceptance": {...}}``; each model entry has MAE/R2 over both wheels,
    per wheel (``fl``, ``fr``) and for the axle (sum of the two SATs).

    Raises:
        UserError: no run at the nominal pressure, a run without TPMS, or models that do not fit the protocol
            (:func:`check_models`).
    """
    spec = check_models(free_model, tpms_model)
    n = free_model.n_features
    by_p: dict[float, list[Run]] = {}
    for r in runs:
        by_p.setdefault(run_pressure_bar(r), []).append(r)
    if NOMINAL_BAR not in by_p:
        raise UserError(f"pressure protocol: no held-out run at the nominal {NOMINAL_BAR} bar "
                        f"(runs at {', '.join(f'{p:g}' for p in sorted(by_p))} bar)")
    groups: dict[str, Any] = {}
    for p in sorted(by_p):
        ds = build_dataset(by_p[p], spec)
        P_free = free_model.predict(ds.X[:, :n])
        g: dict[str, Any] = {"runs": len(by_p[p]), "mean_abs_sat_nm": float(np.mean(np.abs(ds.Y))),
                             "free": _scores(ds.Y, P_free),
                             "tpms": _scores(ds.Y, tpms_model.predict(ds.X))}
        if correction is not None:
            g["trail_correction"] = _scores(ds.Y, _corrected(P_free, _dpi(ds.X, n), correction))
        groups[f"{p:.1f}"] = g
    nominal = groups[f"{NOMINAL_BAR:.1f}"]["tpms"]["mae_nm"]
    verdicts = {}
    for key, g in groups.items():
        g["tpms_vs_nominal"] = g["tpms"]["mae_nm"] / nominal - 1.0
        g["tpms_vs_free"] = g["tpms"]["mae_nm"] / g["free"]["mae_nm"] - 1.0
        if key != f"{NOMINAL_BAR:.1f}":
            verdicts[key] = bool(g["tpms_vs_nominal"] <= WITHIN_NOMINAL and g["tpms_vs_free"] <= -GAIN_OVER_FREE)
    return {"nominal_bar": NOMINAL_BAR, "free_model": {"file": str(getattr(free_model, "path", "")),
                                                       "sha256": free_model.card.get("sha256")},
            "tpms_model": {"file": str(getattr(tpms_model, "path", "")), "sha256": tpms_model.card.get("sha256")},
            "correction": None if correction is None else correction.tolist(), "groups": groups,
            "acceptance": {"within_nominal": WITHIN_NOMINAL, "gain_over_free": GAIN_OVER_FREE, "passed": verdicts}}


def pressure_markdown(result: dict[str, Any]) -> str:
    """The protocol as Markdown: per pressure, MAE (Nm) of each model per wheel and for the axle."""
    corr = result["correction"] is not None
    head = ("| front pressure | runs, mean \\|SAT\\| (Nm) | model | MAE (Nm) | MAE FL / FR | axle MAE (Nm) | R2 "
            "| TPMS vs nominal | TPMS vs pressure-free | accepted |")
    lines = ["### Pressure protocol (issue 17): held-out runs away from nominal",
             "",
             f"Whole runs never trained on (their seeds unused in training), grouped by the front tyres' pressure as "
             f"their TPMS reports it; the nominal is {result['nominal_bar']:g} bar. Pressure-free model "
             f"`{result['free_model']['file']}`, TPMS model `{result['tpms_model']['file']}`"
             + (", and the pressure-free model with a trail correction by pressure fitted on the TPMS model's "
                "training runs" if corr else "") + ". Acceptance: the TPMS model's MAE within "
             f"{100 * result['acceptance']['within_nominal']:.0f} % of its own at nominal and at least "
             f"{100 * result['acceptance']['gain_over_free']:.0f} % below the pressure-free model's.",
             "", head, "|---" * head.count(" | ") + "|---|"]
    names = (("free", "pressure-free"), ("trail_correction", "pressure-free + trail correction"), ("tpms", "TPMS"))
    for key, g in result["groups"].items():
        verdict = result["acceptance"]["passed"].get(key)
        for m_key, label in names:
            if m_key not in g:
                continue
            m = g[m_key]
            extra = (f" {100 * g['tpms_vs_nominal']:+.1f} % | {100 * g['tpms_vs_free']:+.1f} % | "
                     f"{'—' if verdict is None else ('yes' if verdict else 'NO')} |") if m_key == "tpms" else " | | |"
            lines.append(f"| {key} bar | {g['runs']}, {g['mean_abs_sat_nm']:.1f} | {label} "
                         f"| {m['mae_nm']:.2f} | {m['fl']['mae_nm']:.2f} / "
                         f"{m['fr']['mae_nm']:.2f} | {m['axle']['mae_nm']:.2f} | {m['r2']:.3f} |{extra}")
    return "\n".join(lines) + "\n"
