"""Score a shipped model on recordings, without retraining.

The model file itself (:class:`virtsensor.onnx_model.OnnxModel`) runs on the
features its card names (:class:`virtsensor.features.FeatureSpec`), built by the
same code the daemon and the trainer use from each run's 20 Hz table (a CSV
table, or a CAN log decoded and sampled by the runtime's front-end). Rows whose
features or reference SATs are not finite are left out and counted.

Metrics are computed here with numpy (no scikit-learn): R^2 is
``1 - sum (y - p)^2 / sum (y - mean y)^2`` (1 for a perfect fit of a constant
target, 0 for an imperfect one, as scikit-learn's ``r2_score``), MAE is the mean
absolute error in Nm. "r2" and "mae_nm" without a wheel are the means over the two
front wheels; "axle" scores the sum of the two SATs.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.dataset import Run, build_dataset
from virtsensor.errors import UserError
from virtsensor.features import FeatureSpec

__all__ = ["r2", "mae", "wheel_metrics", "needed_signals", "score_runs", "markdown"]


def r2(y: np.ndarray, p: np.ndarray) -> float:
    """Coefficient of determination of predictions ``p`` for targets ``y`` (1-D, same length >= 1)."""
    y, p = np.asarray(y, dtype=np.float64), np.asarray(p, dtype=np.float64)
    ss_res = float(np.sum((y - p) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    if ss_tot == 0.0:
        return 1.0 if ss_res == 0.0 else 0.0
    return 1.0 - ss_res / ss_tot


def mae(y: np.ndarray, p: np.ndarray) -> float:
    """Mean absolute error (unit of ``y``)."""
    return float(np.mean(np.abs(np.asarray(y, dtype=np.float64) - np.asarray(p, dtype=np.float64))))


def wheel_metrics(Y: np.ndarray, P: np.ndarray, names: tuple[str, ...] = ("fl", "fr")) -> dict[str, Any]:
    """R^2 and MAE (Nm) per wheel, their means over the wheels, the axle sum's, and the row count.

    ``Y`` and ``P`` are (n, len(names)), n >= 1: the same layout and keys as
    :func:`virtsensor.training.metrics`.
    """
    out: dict[str, Any] = {}
    for j, name in enumerate(names):
        out[name] = {"r2": r2(Y[:, j], P[:, j]), "mae_nm": mae(Y[:, j], P[:, j])}
    out["r2"] = float(np.mean([out[n]["r2"] for n in names]))
    out["mae_nm"] = float(np.mean([out[n]["mae_nm"] for n in names]))
    out["axle"] = {"r2": r2(Y.sum(axis=1), P.sum(axis=1)), "mae_nm": mae(Y.sum(axis=1), P.sum(axis=1))}
    out["n"] = int(len(Y))
    return out


def needed_signals(card: Any) -> list[str]:
    """The catalogue signals a run needs to be scored by a model of this card: its inputs and the SATs."""
    spec = _spec(card)
    return sorted(set(spec.signals) | set(cat.OUTPUTS))


def _spec(card: Any) -> FeatureSpec:
    try:
        return FeatureSpec.from_json(card["feature_spec"])
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"model card has no usable feature_spec ({exc})") from None


def score_runs(model: Any, runs: Sequence[Run]) -> dict[str, Any]:
    """Score ``model`` (an :class:`~virtsensor.onnx_model.OnnxModel`) on each run and on all together.

    Returns:
        ``{"model": {"file", "sha256"}, "overall": wheel_metrics + {"dropped_nonfinite"},
        "runs": [{"file", "r2", "mae_nm", "n", "fl", "fr", "axle", "dropped_nonfinite"}, ...]}``
        in the order of ``runs``.

    Raises:
        UserError: a run lacking a needed signal, or with no row where every feature and
            both SATs are finite (naming the file).
    """
    spec = _spec(model.card)
    if tuple(spec.names) != tuple(model.input_names):
        raise UserError(f"{getattr(model, 'path', 'model')}: its card's feature_spec does not give its inputs "
                        f"{', '.join(model.input_names)}")
    if tuple(model.outputs) != tuple(cat.OUTPUTS):
        raise UserError(f"{getattr(model, 'path', 'model')}: it estimates {', '.join(model.outputs)}, "
                        f"not {', '.join(cat.OUTPUTS)}")
    per_run, ys, ps = [], [], []
    dropped = 0
    for run in runs:
        ds = build_dataset([run], spec, cat.OUTPUTS)
        where = str(run.path or run.name)
        if len(ds.Y) == 0:
            raise UserError(f"{where}: no sample with every input of the model and both reference SATs finite")
        pred = model.predict(ds.X)
        m = wheel_metrics(ds.Y, pred)
        per_run.append({"file": where, "r2": m["r2"], "mae_nm": m["mae_nm"], "n": m["n"], "fl": m["fl"],
                        "fr": m["fr"], "axle": m["axle"], "dropped_nonfinite": ds.dropped_nonfinite})
        ys.append(ds.Y)
        ps.append(pred)
        dropped += ds.dropped_nonfinite
    overall = wheel_metrics(np.concatenate(ys), np.concatenate(ps))
    overall["dropped_nonfinite"] = dropped
    return {"model": {"file": str(getattr(model, "path", "")), "sha256": model.card.get("sha256")},
            "overall": overall, "runs": per_run}


def markdown(result: dict[str, Any]) -> str:
    """The score as a Markdown table: one row per run, then all runs together."""
    lines = [f"Model `{result['model']['file']}` (sha256 {str(result['model']['sha256'])[:12]}...)", "",
             "| run | samples | R2 | MAE (Nm) | R2 FL / FR | axle R2 / MAE (Nm) |", "|---|---|---|---|---|---|"]

    def row(name: str, m: dict[str, Any]) -> str:
        return (f"| {name} | {m['n']} | {m['r2']:.3f} | {m['mae_nm']:.2f} | {m['fl']['r2']:.3f} / "
                f"{m['fr']['r2']:.3f} | {m['axle']['r2']:.3f} / {m['axle']['mae_nm']:.2f} |")

    lines += [row(r["file"], r) for r in result["runs"]]
    lines.append(row("**all runs**", result["overall"]))
    return "\n".join(lines) + "\n"
