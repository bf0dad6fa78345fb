"""Per-run nuisance parameters: what the engineer gave as a range (the road friction above all).

Each ranged quantity of each run is identified from that run alone, since it acts
on that run alone: every run with the quantity unknown is re-simulated together
at :data:`GRID` values spread over its own range (one batch per grid point), its
misfit ``J_r(v) = sum_s RSS_rs(v) / sigma_s^2`` (``sigma_s^2``: each signal's
residual variance over the whole day at the runs' best grid points) is profiled,
and the estimate is the parabolic vertex around the grid's best point. The 95 %
interval is where ``f_eff (J_r(v) - min J_r) <= 3.84`` (``f_eff``: the effective
share of independent samples from the residuals' autocorrelation), read off
the grid by linear interpolation of the profile's square root. A run whose
interval spans its whole range does not excite the quantity, and is said to; a
run below its grip limit bounds the friction from
below only (its interval reaches the top of the range).

The interval is then widened (in quadrature) by the simulator's own error on the
quantity, the catalogue's stated accuracy of the matching day-wide cause
(:data:`MODEL_ERROR`). The runs go on into the search for the day's cause at their estimates
(``sim.day``; the caller re-simulates the nominal car there: at the nearest grid point, up to
half a grid step off, a sine with dwell at the grip limit left residuals several times a
control day's). :func:`fit` returns the items of the nearest grid point meanwhile.

The quantities are first identified on the car with no effect, then the day's cause with each
run at its value; :func:`virtsensor.diagnose.identify._joint_passes` alternates the two until
the quantities are read at the cause's estimate, and widens their intervals by what the cause's
own interval leaves unknown (a pressure or a payload also acts on grip).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

#: grid points per ranged quantity and run
GRID = 7
#: chi-square(1) 95 % quantile
CHI2_95 = 3.84
#: 95 % bound of the simulator's own error on each quantity: the accuracy sim.effects states for the cause
#: acting on the same parameter (road_friction, tyre_pressure, vehicle_mass), absolute part
MODEL_ERROR = {"mu": 0.05, "pressure_bar": 0.12, "mass_kg": 40.0}


def initial_day(conds: Sequence[Any]) -> list[dict[str, float]]:
    """Each run's condition values before any identification: exact values, ranged ones at their top (a run
    that does not reach the grip limit behaves as on the grippiest road it may be on)."""
    return [{k: hi for k, (lo, hi) in rc.values.items()} for rc in conds]


def _per_run_rss(data, sims, r: int) -> dict[str, float]:
    out = {}
    for n in data.names:
        tot = 0.0
        for s, item in enumerate(sims[r]):
            m = data.masks[n][r][s]
            seg = data.runs[r].segments[s]
            e = data.runs[r].table[n][seg.start:seg.stop][m] - item["pred"][n][m]
            tot += float(np.sum(e * e))
        out[n] = tot
    return out


def _interval(grid: np.ndarray, j: np.ndarray, feff: float) -> tuple[float, float, float]:
    """(estimate, lo, hi) of a profile ``j`` on ``grid``."""
    i = int(np.argmin(j))
    est = float(grid[i])
    if 0 < i < len(grid) - 1:
        x, f = grid[i - 1:i + 2], j[i - 1:i + 2]
        a, b, _ = np.polyfit(x, f, 2)
        if a > 0:
            est = float(np.clip(-b / (2 * a), x[0], x[2]))
    # the crossing of the 95 % level, interpolated on the square root of the profile (linear in the distance
    # from the vertex for a parabola: no narrowing by the grid)
    d = np.sqrt(np.maximum(feff * (j - j[i]), 0.0)) - np.sqrt(CHI2_95)
    lo, hi = float(grid[0]), float(grid[-1])
    for k in range(i, 0, -1):
        if d[k - 1] > 0 >= d[k]:
            lo = float(grid[k - 1] + (grid[k] - grid[k - 1]) * d[k - 1] / (d[k - 1] - d[k]))
            break
    for k in range(i, len(grid) - 1):
        if d[k + 1] > 0 >= d[k]:
            hi = float(grid[k] + (grid[k + 1] - grid[k]) * (-d[k]) / (d[k + 1] - d[k]))
            break
    return est, min(lo, est), max(hi, est)


def widened(est: float, lo: float, hi: float, rng: Sequence[float], extra: float) -> dict[str, Any]:
    """An interval ``lo .. hi`` about ``est`` with ``extra`` (the quantity's units) added in quadrature to each side,
    within the range ``rng``; a side already at the range's end stays there (the grid could not bound it). Returns
    ``ci95``, ``excited`` (either side inside the range: the run bounds its value) and ``bounded_above``."""
    g0, g1 = rng
    if lo > g0 + 1e-9:
        lo = max(g0, est - float(np.hypot(est - lo, extra)))
    if hi < g1 - 1e-9:
        hi = min(g1, est + float(np.hypot(hi - est, extra)))
    return {"ci95": [lo, hi], "excited": bool(lo > g0 + 1e-9 or hi < g1 - 1e-9), "bounded_above": bool(hi < g1 - 1e-9)}


def grid(conds: Sequence[Any]) -> dict[str, list[Any]]:
    """Per ranged quantity, the :data:`GRID` hypotheses that re-simulate every run with it unknown at its
    own grid points (the others keep their values)."""
    from virtsensor.diagnose.resim import Hypothesis

    out = {}
    for q in sorted({q for rc in conds for q in rc.unknown()}):
        who = [r for r, rc in enumerate(conds) if q in rc.unknown()]
        grids = {r: np.linspace(*conds[r].unknown()[q], GRID) for r in who}
        out[q] = [Hypothesis(runs=tuple((r, q, float(grids[r][k])) for r in who), only=tuple(who))
                  for k in range(GRID)]
    return out


def fit(data, sim, conds: Sequence[Any], nominal: Any, log, hyps_of: dict[str, list[Any]],
        outs_all: Sequence[Any]) -> tuple[Any, list[dict[str, Any]]]:
    """Identify every run's ranged quantities (see the module docstring) from the re-simulations ``outs_all``
    of the hypotheses :func:`grid` gave (``hyps_of``, in order); ``sim.day`` is updated.

    Returns the re-simulation at the identified values (runs with nothing unknown keep their
    ``nominal`` items) and, per run, ``{quantity: {"estimate", "ci95", "range", "excited"}}``."""
    per_run: list[dict[str, Any]] = [{} for _ in conds]
    current = [list(r) for r in nominal]
    at = 0
    for q, hyps in hyps_of.items():
        who = [r for r, rc in enumerate(conds) if q in rc.unknown()]
        grids = {r: np.linspace(*conds[r].unknown()[q], GRID) for r in who}
        log(f"identifying {q} of {len(who)} run(s) on a {GRID}-point grid each")
        outs = list(outs_all[at:at + len(hyps)])
        at += len(hyps)
        rss = {r: [_per_run_rss(data, outs[k], r) for k in range(GRID)] for r in who}
        # each signal's variance over the day, at each run's best grid point (others: current items)
        best_k = {r: int(np.argmin([sum(v.values()) / max(sum(data.n.values()), 1) for v in rss[r]])) for r in who}
        for _ in range(2):
            total = {n: 0.0 for n in data.names}
            for r in range(len(conds)):
                src = rss[r][best_k[r]] if r in who else _per_run_rss(data, current, r)
                for n in data.names:
                    total[n] += src[n]
            var = {n: max(total[n] / max(data.n[n], 1), data.floor[n]) for n in data.names}
            prof = {r: np.array([sum(v[n] / var[n] for n in data.names) for v in rss[r]]) for r in who}
            best_k = {r: int(np.argmin(prof[r])) for r in who}
        rho = data.rho([[outs[best_k[r]][r][s] if r in who else current[r][s] for s in range(len(current[r]))]
                        for r in range(len(conds))])
        feff = (1.0 - rho) / (1.0 + rho)
        for r in who:
            est, lo, hi = _interval(grids[r], prof[r], feff)
            g0, g1 = conds[r].unknown()[q]
            per_run[r][q] = {"estimate": est, "range": [g0, g1],
                             **widened(est, lo, hi, (g0, g1), MODEL_ERROR.get(q, 0.0))}
            k = int(np.argmin(np.abs(grids[r] - est)))
            sim.day[r][q] = float(est)
            current[r] = outs[k][r]
    return current, per_run
