"""Score the grip estimate (:mod:`virtsensor.grip`) against the simulator's truth (issue 19).

A run is scored when its table carries the grip truth: ``road_mu`` and each front tyre's friction utilisation
``util_fl_1``/``util_fr_1`` (``sqrt(Fx^2 + Fy^2) / (mu Fz)``); the front axle's true utilisation is the larger
of the two (the tyre that reaches the limit first). The SATs the estimate starts from are the model's, one per
row where every feature is finite (nan elsewhere, as the daemon publishes INIT), and the estimate runs tick by
tick with the daemon's code (:func:`virtsensor.grip.estimate_run`).

Figures (keys of :func:`grip_metrics` and of the pooled :func:`pool`):

* ``mu_within_0_1_share``: of the samples where the friction is given, the share within +-0.1 of the true mu
  (``mu_given`` samples given, ``mu_scored`` of them with a finite true mu: only those are scored);
* ``mu_abs_err_p90``: the 90th percentile of the friction's absolute error where given (and the truth known);
* ``mu_interval_cover_share``: of the samples where the friction is given, the share whose published interval
  (``mu +- halfwidth``, meant to hold the truth in 9 of 10 samples) holds the true mu (null without half-widths);
* ``mu_given_share_above_0_6``: of the samples whose true front utilisation exceeds 0.6, the share where the
  friction is given;
* ``warning_lead_s``: for a run whose true front utilisation first reaches 0.95 after its first
  :data:`STARTUP_S` (a run that reaches it first in that time, or starts there, is not scored for the lead: the
  estimator has no history of its inputs yet, and a later corner is not the run's first limit), the time from
  the onset of the warning episode that is on at that first instant to that instant (s; negative: the warning
  came that late after it; a run never warned after reaching it scores minus the time from then to one tick
  after the run's end, so always below 0); a warning held on through calm driving earns no lead for it:
  where the true utilisation stayed below 0.7 for :data:`FALSE_WINDOW_S` or longer within the episode, the
  lead counts from the end of the latest such stretch (so a warning that is simply kept on, or held for long
  after an earlier corner, scores as if it came on when the driving left the calm); ``warning_lead_s_median``
  pools the runs' leads (null where no run reaches 0.95; ``runs_reaching_limit`` counts the runs scored,
  ``runs_limit_in_startup`` those first at the limit in their start-up; per run ``reaches_limit`` says whether it
  reaches 0.95 at all, ``limit_in_startup`` whether first in the start-up); ``limit_warned_share`` (pooled only)
  is the share of those runs whose warning was on by that instant (a lead >= 0: the limit was not reached
  unwarned);
* ``false_warnings_per_10min``: warning onsets while the true utilisation stays below 0.7 from
  :data:`FALSE_WINDOW_S` before to as long after the onset, per 10 minutes of driving below 0.7.

Every share is null (None) where its denominator is empty.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from virtsensor.grip import GRIP_INPUTS, GripParams, estimate_run, reads_pressure

__all__ = ["GRIP_TRUTH", "FALSE_WINDOW_S", "LIMIT_UTIL", "EXCITED_UTIL", "CALM_UTIL", "has_grip_truth",
           "true_front_util", "grip_metrics", "pool", "public", "grip_of_run", "model_reads_pressure", "model_sats",
           "model_outside",
           "grip_runs", "score_grip", "grip_markdown"]

#: the truth columns a run needs to be scored for grip
GRIP_TRUTH = ("road_mu", "util_fl_1", "util_fr_1")
#: utilisation of the limit the warning must anticipate, of "excited" samples, and below which a warning is false
LIMIT_UTIL, EXCITED_UTIL, CALM_UTIL = 0.95, 0.6, 0.7
#: a warning onset is false when the true utilisation stays below CALM_UTIL this long before and after it (s)
FALSE_WINDOW_S = 1.0
MU_TOLERANCE = 0.1
#: a limit reached in a run's first second is not counted for the lead (the estimator is still starting: the
#: daemon publishes INIT until its features have their history, and its filters settle)
STARTUP_S = 1.0


def has_grip_truth(table: Mapping[str, Any]) -> bool:
    """Whether a run's table carries the grip truth columns."""
    return all(k in table for k in GRIP_TRUTH)


def true_front_util(table: Mapping[str, Any]) -> np.ndarray:
    """The front axle's true friction utilisation per row: the larger of the two front tyres'."""
    return np.maximum(np.asarray(table["util_fl_1"], float), np.asarray(table["util_fr_1"], float))


def _onsets(warning: np.ndarray) -> np.ndarray:
    w = np.asarray(warning, dtype=bool)
    return np.flatnonzero(w & ~np.concatenate(([False], w[:-1])))


def _lead(time_s: np.ndarray, util: np.ndarray, warning: np.ndarray) -> float | None:
    hit = np.flatnonzero(util >= LIMIT_UTIL)
    if not len(hit) or time_s[hit[0]] < time_s[0] + STARTUP_S:  # (never, or first in the start-up: not scored)
        return None
    i = int(hit[0])
    on = _onsets(warning)
    if warning[i]:
        start = int(on[on <= i][-1]) if np.any(on <= i) else 0
        return float(time_s[i] - time_s[start + _calm_end(time_s[start:i + 1], util[start:i + 1])])
    later = on[on > i]
    if len(later):
        return float(time_s[i] - time_s[int(later[0])])
    tick = float(np.median(np.diff(time_s))) if len(time_s) > 1 else 0.0
    return float(time_s[i] - time_s[-1]) - tick  # (never warned: as if at the first tick after the run, < 0)


def _calm_end(time_s: np.ndarray, util: np.ndarray) -> int:
    """The index just after the latest stretch of at least FALSE_WINDOW_S with the utilisation below CALM_UTIL
    (0 when there is none): a warning held on through it anticipated nothing there."""
    calm = np.concatenate(([False], util < CALM_UTIL, [False])).astype(np.int8)
    edges = np.diff(calm)
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)  # calm is [start, end)
    long = [e for a, e in zip(starts, ends, strict=True) if time_s[e - 1] - time_s[a] >= FALSE_WINDOW_S]
    return int(long[-1]) if long else 0


def _false_warnings(time_s: np.ndarray, util: np.ndarray, warning: np.ndarray) -> tuple[int, float]:
    """(false onsets, seconds of driving below CALM_UTIL)."""
    dt = float(np.median(np.diff(time_s))) if len(time_s) > 1 else 0.0
    calm = util < CALM_UTIL
    n = 0
    for i in _onsets(warning):
        win = (time_s >= time_s[i] - FALSE_WINDOW_S) & (time_s <= time_s[i] + FALSE_WINDOW_S)
        n += bool(np.all(calm[win]))
    return n, float(calm.sum()) * dt


def grip_metrics(time_s: np.ndarray, util_true: np.ndarray, mu_true: np.ndarray, mu_est: np.ndarray,
                 warning: np.ndarray, halfwidth: np.ndarray | None = None) -> dict[str, Any]:
    """One run's grip figures (see the module docstring), plus the counts :func:`pool` needs. ``halfwidth``: the
    published interval's half-width per sample (None: the coverage is not scored)."""
    given = np.isfinite(mu_est)
    scored = given & np.isfinite(mu_true)  # (a sample without the true friction is not scored: no error there)
    err = np.abs(mu_est[scored] - mu_true[scored])
    covered = None if halfwidth is None else err <= np.asarray(halfwidth, float)[scored]
    excited = util_true > EXCITED_UTIL  # (an unknown true utilisation is neither excited nor calm)
    lead = _lead(time_s, util_true, warning)
    reaches = bool(np.any(util_true >= LIMIT_UTIL))
    n_false, calm_s = _false_warnings(time_s, util_true, warning)
    return {
        "n": int(len(time_s)), "mu_given": int(given.sum()), "mu_scored": int(scored.sum()),
        "mu_within_0_1_share": float(np.mean(err <= MU_TOLERANCE)) if len(err) else None,
        "mu_abs_err_p90": float(np.percentile(err, 90)) if len(err) else None,
        "mu_interval_cover_share": float(np.mean(covered)) if covered is not None and len(err) else None,
        "mu_given_share_above_0_6": float(given[excited].mean()) if excited.any() else None,
        "excited": int(excited.sum()), "excited_given": int((given & excited).sum()),
        "reaches_limit": reaches,
        "limit_in_startup": reaches and lead is None,  # (first there: not scored)
        "warning_lead_s": lead,
        "warning_lead_s_median": lead,
        "false_warnings": n_false, "calm_s": calm_s,
        "false_warnings_per_10min": 600.0 * n_false / calm_s if calm_s > 0 else None,
        "_err": err, "_covered": covered,
    }


def pool(per_run: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """All runs' grip figures together (shares over the pooled samples, the median lead over the runs)."""
    err = np.concatenate([r["_err"] for r in per_run]) if per_run else np.zeros(0)
    cov: list[np.ndarray] = [c for r in per_run if (c := r.get("_covered")) is not None]
    covered: np.ndarray | None = np.concatenate(cov) if cov and len(cov) == len(per_run) else None
    excited = sum(r["excited"] for r in per_run)
    leads = [r["warning_lead_s"] for r in per_run if r["warning_lead_s"] is not None]
    n_false = sum(r["false_warnings"] for r in per_run)
    calm_s = sum(r["calm_s"] for r in per_run)
    return {
        "runs": len(per_run), "n": sum(r["n"] for r in per_run), "mu_given": sum(r["mu_given"] for r in per_run),
        "mu_scored": int(len(err)),
        "mu_within_0_1_share": float(np.mean(err <= MU_TOLERANCE)) if len(err) else None,
        "mu_abs_err_p90": float(np.percentile(err, 90)) if len(err) else None,
        "mu_interval_cover_share": float(np.mean(covered)) if covered is not None and len(covered) else None,
        "mu_given_share_above_0_6": sum(r["excited_given"] for r in per_run) / excited if excited else None,
        "excited": excited,
        "runs_reaching_limit": len(leads),
        "runs_limit_in_startup": sum(bool(r.get("limit_in_startup")) for r in per_run),
        "warning_lead_s_median": float(np.median(leads)) if leads else None,
        "limit_warned_share": float(np.mean([x >= 0.0 for x in leads])) if leads else None,
        "warning_lead_s_min": float(np.min(leads)) if leads else None,
        "false_warnings": n_false, "calm_s": calm_s,
        "false_warnings_per_10min": 600.0 * n_false / calm_s if calm_s > 0 else None,
    }


def public(m: Mapping[str, Any]) -> dict[str, Any]:
    """The figures without the private per-sample arrays (for JSON)."""
    return {k: v for k, v in m.items() if not k.startswith("_")}


def grip_of_run(table: Mapping[str, Any], sat_fl: np.ndarray, sat_fr: np.ndarray,
                params: GripParams | None = None, sat_reads_pressure: bool = False,
                outside: np.ndarray | None = None) -> tuple[dict[str, Any], dict[str, np.ndarray]] | None:
    """The grip estimate of one run and its figures, or None when the run lacks the grip truth.
    ``sat_reads_pressure``: the SATs are of a model that reads the front TPMS pressures (:func:`model_reads_pressure`;
    :func:`virtsensor.grip.estimate_run`); ``outside``: per row, the SATs are outside the model's validity envelope
    (:func:`model_outside`; None: never)."""
    if not has_grip_truth(table):
        return None
    est = estimate_run(table, sat_fl, sat_fr, params, sat_reads_pressure, outside)
    t = np.asarray(table["time_s"], float)
    m = grip_metrics(t, true_front_util(table), np.asarray(table["road_mu"], float), est["mu"], est["warning"],
                     est["halfwidth"])
    return m, est


def model_reads_pressure(model: Any) -> bool:
    """Whether ``model`` (an :class:`~virtsensor.model.onnx.OnnxModel`) reads both front TPMS pressures."""
    from virtsensor.features import FeatureSpec

    return reads_pressure(FeatureSpec.from_json(model.card["feature_spec"]).signals)


def model_sats(model: Any, table: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The model's front SATs (Nm) on every row of a run's table: nan where a feature is not finite (the
    first rows lack history), as the daemon publishes none there."""
    from virtsensor.features import FeatureSpec
    from virtsensor.model.fallback import load_fallback

    spec = FeatureSpec.from_json(model.card["feature_spec"])
    X = spec.transform(table)
    fb = load_fallback(model)  # a TPMS model: its pressure-free fallback where a pressure is unknown, as published
    ok = np.isfinite(X[:, : fb.n] if fb is not None else X).all(axis=1)
    P = np.full((len(X), 2), np.nan)
    if ok.any():
        P[ok] = model.predict(X[ok]) if fb is None else fb.predict(model, X[ok])[0]
    return P[:, 0], P[:, 1]


def model_outside(model: Any, table: Mapping[str, Any]) -> np.ndarray | None:
    """Per row of a run's table, whether the daemon judges ``model``'s inputs outside its card's validity envelope:
    the row's, or one of the rows before it that the features' history reads
    (:class:`~virtsensor.daemon.validity.EnvelopeMemory`); rows without finite features are inside, as the daemon
    judges none there. None when the card states no envelope."""
    from virtsensor.features import FeatureSpec
    from virtsensor.model.envelope import Envelope

    doc = model.card.get("envelope")
    if doc is None:
        return None
    spec = FeatureSpec.from_json(model.card["feature_spec"])
    X = spec.transform(table)
    ok = np.isfinite(X).all(axis=1)
    rows = Envelope.from_json(doc).outside_rows(np.where(ok[:, None], X, 0.0), spec.names) & ok
    out = rows.copy()
    for k in range(1, max((f.history for f in spec.features), default=0) + 1):
        out[k:] |= rows[:-k]
    return out


def score_grip(model: Any, runs: Sequence[Any], params: GripParams | None = None) -> dict[str, Any] | None:
    """The grip estimate of ``model``'s SATs on each run that carries the grip truth, and all together.

    Args:
        model: an :class:`~virtsensor.model.onnx.OnnxModel` (its card's feature spec gives the SATs' features).
        runs: :class:`~virtsensor.learning.dataset.Run` objects (``table``, ``path``, ``name``).

    Returns:
        ``{"overall": pooled figures, "runs": {file: figures | None}}`` (None for a run without the grip truth
        or without an input the estimate reads), or None when no run can be scored.
    """
    per = grip_runs(model, runs, params)
    scored = [m for m in per.values() if m is not None]
    if not scored:
        return None
    return {"overall": pool(scored), "runs": {k: None if m is None else public(m) for k, m in per.items()}}


def grip_runs(model: Any, runs: Sequence[Any], params: GripParams | None = None) -> dict[str, dict[str, Any] | None]:
    """Each run's grip figures (:func:`grip_metrics`, with the private arrays :func:`pool` needs), by its file (or
    name); None for a run without the grip truth or an input the estimate reads (see :func:`score_grip`)."""
    per: dict[str, dict[str, Any] | None] = {}
    reads = model_reads_pressure(model)
    for run in runs:
        where = str(run.path or run.name)
        if not has_grip_truth(run.table) or any(k not in run.table for k in GRIP_INPUTS):
            per[where] = None
            continue
        fl, fr = model_sats(model, run.table)
        res = grip_of_run(run.table, fl, fr, params, reads, model_outside(model, run.table))
        assert res is not None
        per[where] = res[0]
    return per


def _startup_note(o: Mapping[str, Any]) -> str:
    n = o.get("runs_limit_in_startup") or 0
    return f" ({n} more first at it in their first {STARTUP_S:g} s, not scored)" if n else ""


def grip_markdown(result: Mapping[str, Any] | None, label: str = "") -> str:
    """One Markdown line of the pooled grip figures (empty without any); ``label`` says which runs they are."""
    if not result:
        return ""
    o = result["overall"]
    which = f"{label}: " if label else ""

    def f(v: Any, fmt: str) -> str:
        return "—" if v is None else format(v, fmt)

    return (f"Grip ({which}{o['runs']} runs with the truth): mu within +-0.1 {f(o['mu_within_0_1_share'], '.3f')} of "
            f"{o['mu_scored']} samples given (with a known true mu), p90 |error| {f(o['mu_abs_err_p90'], '.3f')}, "
            f"interval holds the truth in "
            f"{f(o.get('mu_interval_cover_share'), '.3f')}; given in "
            f"{f(o['mu_given_share_above_0_6'], '.3f')} of samples above 0.6 utilisation; warning lead median "
            f"{f(o['warning_lead_s_median'], '.2f')} s over {o['runs_reaching_limit']} runs reaching 0.95 after their "
            f"start-up{_startup_note(o)}; "
            f"{f(o['false_warnings_per_10min'], '.2f')} false warnings per 10 min below 0.7.\n")
