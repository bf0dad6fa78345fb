"""Accuracy figures of SAT estimates, in numpy (no scikit-learn: the runtime and ``score`` use them).

Conventions (as Table IV of the paper and ``evaluate``): ``Y`` and ``P`` are (N, 2) arrays of the true
and estimated SATs of the front left and right wheels (Nm). R2 is the coefficient of determination
``1 - SS_res / SS_tot`` per wheel (the same number as ``sklearn.metrics.r2_score``); MAE is in Nm.
``r2`` and ``mae_nm`` at the top level are the means over both wheels; ``axle`` scores the sum of both.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["mae", "metrics", "r2"]


def r2(y: np.ndarray, p: np.ndarray) -> float:
    """Coefficient of determination of ``p`` against ``y``; for a constant ``y``: 1 for a perfect fit, else 0;
    NaN for fewer than two samples (scikit-learn's conventions)."""
    y = np.asarray(y, dtype=float)
    p = np.asarray(p, dtype=float)
    if y.size < 2:
        return math.nan
    ss_tot = float(((y - y.mean()) ** 2).sum())
    ss_res = float(((y - p) ** 2).sum())
    if ss_tot == 0.0:
        return 1.0 if ss_res == 0.0 else 0.0
    return 1.0 - ss_res / ss_tot


def mae(y: np.ndarray, p: np.ndarray) -> float:
    """Mean absolute error of ``p`` against ``y`` (same unit)."""
    return float(np.mean(np.abs(np.asarray(y, dtype=float) - np.asarray(p, dtype=float))))


def metrics(Y: np.ndarray, P: np.ndarray, names: tuple[str, ...] = ("fl", "fr")) -> dict[str, Any]:
    """R2 and MAE (Nm) per wheel, their mean over both wheels, and for the axle sum; ``n`` rows."""
    Y = np.asarray(Y, dtype=float)
    P = np.asarray(P, dtype=float)
    if Y.shape != P.shape or Y.ndim != 2 or Y.shape[1] != len(names):
        raise ValueError(f"metrics: Y {Y.shape} and P {P.shape} must both be (N, {len(names)})")
    out: dict[str, Any] = {}
    for j, name in enumerate(names):
        out[name] = {"r2": r2(Y[:, j], P[:, j]), "mae_nm": mae(Y[:, j], P[:, j])}
    out["r2"] = float(np.mean([out[n]["r2"] for n in names]))
    out["mae_nm"] = float(np.mean([out[n]["mae_nm"] for n in names]))
    out["axle"] = {"r2": r2(Y.sum(axis=1), P.sum(axis=1)), "mae_nm": mae(Y.sum(axis=1), P.sum(axis=1))}
    out["n"] = int(len(Y))
    return out
