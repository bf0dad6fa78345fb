"""Show what the simulation gets wrong: measured against re-simulated, signal by signal.

For each compared signal (the 12 inputs and the reference SATs), over the rows
the identification used:

* ``bias``: mean residual (measured - simulated), in the signal's unit;
* ``gain``: slope of measured on simulated about their means (1: right amplitude);
* ``lag_s``: delay of the measured signal behind the simulated one at the peak of
  their cross-correlation (parabolic sub-sample interpolation; > 0: measured later);
* ``rms``, ``nrmse`` (rms over the measured signal's standard deviation) and ``r2``.

Then the SAT residual's dependence on the operating point of the re-simulated
car (slip angle, vertical load, speed, lateral acceleration) in bins, and the
spectra (Welch) of the measured and simulated SAT and steering torque. The same
statistics are given for the calibrated simulator when a cause was named.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.diagnose.resim import segment_mask
from virtsensor.recordings.measured import MeasuredRun
from virtsensor.signals import TABLE_TICK_S as TICK_S

MAX_LAG_S = 1.0
SPECTRA = ("sat_fl_nm", "steer_torque_nm", "yaw_rate_radps")
#: operating-point variables of the SAT residual's dependence: name -> (source, unit)
DEPENDENCE = {
    "abs_slip_angle_fl_deg": ("alpha_fl", "deg"),
    "load_fl_kn": ("fz_fl", "kN"),
    "speed_mps": ("vx_mps", "m/s"),
    "abs_ay_mps2": ("ay_mps2", "m/s^2"),
}


def signal_stats(y: np.ndarray, p: np.ndarray, segs: Sequence[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """Residual statistics of measured ``y`` against simulated ``p`` (compared rows,
    concatenated); ``segs`` holds each segment's (measured, simulated) with NaN
    outside the compared rows, for the lag."""
    e = y - p
    sd = float(np.std(y))
    yc, pc = y - y.mean(), p - p.mean()
    den = float(np.sum(pc * pc))
    ss = float(np.sum(yc * yc))
    return {
        "bias": float(np.mean(e)),
        "gain": float(np.sum(yc * pc) / den) if den > 0 else float("nan"),
        "lag_s": _lag(segs),
        "rms": float(np.sqrt(np.mean(e * e))),
        "nrmse": float(np.sqrt(np.mean(e * e)) / sd) if sd > 0 else float("nan"),
        "r2": float(1.0 - np.sum(e * e) / ss) if ss > 0 else float("nan"),
    }


def _lag(segs: Sequence[tuple[np.ndarray, np.ndarray]]) -> float:
    """Lag (s) maximising the cross-correlation summed over segments (measured later: > 0)."""
    k = int(MAX_LAG_S / TICK_S)
    lags = np.arange(-k, k + 1)
    cc = np.zeros(len(lags))
    for y, p in segs:
        ok = np.isfinite(y) & np.isfinite(p)
        if ok.sum() < 2 * k + 10:
            continue
        yc = np.where(ok, y - np.mean(y[ok]), 0.0)
        pc = np.where(ok, p - np.mean(p[ok]), 0.0)
        n = len(yc)
        for i, L in enumerate(lags):
            if L >= 0:
                cc[i] += float(np.dot(yc[L:], pc[:n - L]))
            else:
                cc[i] += float(np.dot(yc[:n + L], pc[-L:]))
    if not np.any(cc):
        return float("nan")
    i = int(np.argmax(cc))
    frac = 0.0
    if 0 < i < len(cc) - 1:
        a, b, c = cc[i - 1], cc[i], cc[i + 1]
        d = a - 2 * b + c
        frac = 0.5 * (a - c) / d if d != 0 else 0.0
    return float((lags[i] + frac) * TICK_S)


@dataclass
class Comparison:
    """Signal-by-signal comparison; see the module docstring."""

    nominal: dict[str, dict[str, float]]
    calibrated: dict[str, dict[str, float]] | None
    dependence: dict[str, dict[str, list[float]]]
    spectra: dict[str, dict[str, list[float]]]
    series: list[dict[str, Any]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return {"nominal": self.nominal, "calibrated": self.calibrated, "sat_residual_dependence": self.dependence,
                "spectra": self.spectra}


def _stacked(runs, sims, name):
    ys, ps, segs = [], [], []
    for r, run in enumerate(runs):
        for s, seg in enumerate(run.segments):
            m = segment_mask(run, s, name)
            y = run.table[name][seg.start:seg.stop]
            p = sims[r][s]["pred"][name]
            ys.append(y[m])
            ps.append(p[m])
            segs.append((np.where(m, y, np.nan), np.where(m, p, np.nan)))
    return np.concatenate(ys), np.concatenate(ps), segs


def _stats(runs, sims, names) -> dict[str, dict[str, float]]:
    out = {}
    for n in names:
        y, p, segs = _stacked(runs, sims, n)
        out[n] = signal_stats(y, p, segs)
    return out


def _dependence(runs: Sequence[MeasuredRun], sims) -> dict[str, dict[str, list[float]]]:
    """SAT (FL) residual binned on the re-simulated operating point."""
    cols: dict[str, list[np.ndarray]] = {k: [] for k in DEPENDENCE}
    res: list[np.ndarray] = []
    for r, run in enumerate(runs):
        for s, seg in enumerate(run.segments):
            item = sims[r][s]
            m = segment_mask(run, s, "sat_fl_nm")
            res.append((run.table["sat_fl_nm"][seg.start:seg.stop] - item["pred"]["sat_fl_nm"])[m])
            truth = item.get("truth", {})
            for k, (src, _) in DEPENDENCE.items():
                if src in truth:
                    v = truth[src]
                else:
                    v = item["pred"][src]
                v = v[m]
                if k.startswith("abs_slip"):
                    v = np.degrees(np.abs(v))
                elif k.startswith("abs_"):
                    v = np.abs(v)
                elif k.startswith("load"):
                    v = v / 1000.0
                cols[k].append(v)
    e = np.concatenate(res) if res else np.zeros(0)
    out: dict[str, dict[str, list[float]]] = {}
    for k, parts in cols.items():
        x = np.concatenate(parts) if parts else np.zeros(0)
        if x.size < 20:
            continue
        edges = np.unique(np.quantile(x, np.linspace(0, 1, 9)))
        idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
        centre, mean, mabs, count = [], [], [], []
        for b in range(len(edges) - 1):
            sel = idx == b
            if sel.sum() < 5:
                continue
            centre.append(float(np.mean(x[sel])))
            mean.append(float(np.mean(e[sel])))
            mabs.append(float(np.mean(np.abs(e[sel]))))
            count.append(int(sel.sum()))
        out[k] = {"unit": DEPENDENCE[k][1], "centre": centre, "mean_residual_nm": mean,
                  "mean_abs_residual_nm": mabs, "count": count}
    return out


def _spectra(runs: Sequence[MeasuredRun], sims) -> dict[str, dict[str, list[float]]]:
    from scipy.signal import welch

    out = {}
    for n in SPECTRA:
        pm, ps, f = [], [], None
        for r, run in enumerate(runs):
            for s, seg in enumerate(run.segments):
                y = run.table[n][seg.start:seg.stop]
                p = sims[r][s]["pred"][n]
                if len(y) < 64:
                    continue
                f, a = welch(y - y.mean(), fs=1.0 / TICK_S, nperseg=64)
                _, b = welch(p - p.mean(), fs=1.0 / TICK_S, nperseg=64)
                pm.append(a * len(y))
                ps.append(b * len(y))
        if f is None:
            continue
        w = sum(len(run.table[n]) for run in runs)
        out[n] = {"f_hz": f.tolist(), "psd_measured": (np.sum(pm, axis=0) / w).tolist(),
                  "psd_simulated": (np.sum(ps, axis=0) / w).tolist(), "unit": f"{cat.SIGNALS[n].unit}^2/Hz"}
    return out


def _series(runs: Sequence[MeasuredRun], nominal, best, names) -> list[dict[str, Any]]:
    out = []
    for r, run in enumerate(runs):
        for s, seg in enumerate(run.segments):
            t = run.table["time_s"][seg.start:seg.stop]
            out.append({"run": run.name, "segment": s, "time_s": t,
                        "measured": {n: run.table[n][seg.start:seg.stop] for n in names},
                        "nominal": nominal[r][s]["pred"],
                        "calibrated": best[r][s]["pred"] if best is not None else None})
    return out


def compare(runs: Sequence[MeasuredRun], idn, names: Sequence[str]) -> Comparison:
    """Compare the measured runs with their nominal (and calibrated) re-simulation.

    The statistics, the SAT residual's dependence and the spectra cover the runs the identification compared:
    a run it left out (``idn.excluded``, by name: not reproduced at its identified conditions) would dominate
    them with residuals it was left out for. Its series stay, marked ``excluded``. (Were every run left out,
    which the identification never does, the statistics would cover them all rather than none.)"""
    best = idn.best_sims if idn.best is not None else None
    left_out = idn.excluded
    keep = [r for r, run in enumerate(runs) if run.name not in left_out] or list(range(len(runs)))
    kr, nom = [runs[r] for r in keep], [idn.nominal_sims[r] for r in keep]
    kb = [best[r] for r in keep] if best is not None else None
    series = _series(runs, idn.nominal_sims, best, names)
    for item in series:
        item["excluded"] = item["run"] in left_out
    return Comparison(
        nominal=_stats(kr, nom, names),
        calibrated=_stats(kr, kb, names) if kb is not None else None,
        dependence=_dependence(kr, nom),
        spectra=_spectra(kr, nom),
        series=series,
    )
