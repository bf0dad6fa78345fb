"""Sim-to-real: what the simulation gets wrong about measured data, why, and the gain of fixing it.

:func:`diagnose` is the whole procedure behind ``virtsensor diagnose``:

1. load and check the measured runs (:mod:`virtsensor.recordings.measured`) and their
   conditions (:mod:`virtsensor.diagnose.conditions`);
2. re-simulate them from their driver inputs, identify each run's unknown conditions
   (:mod:`virtsensor.diagnose.nuisance`) and compare signal by signal
   (:mod:`virtsensor.diagnose.compare`);
3. identify every candidate effect of :mod:`sim.effects` and name the explanations,
   best first, or ``none``, or ``unexplained`` (:mod:`virtsensor.diagnose.identify`);
4. calibrate the simulator with them, regenerate the training campaign, retrain
   (:mod:`virtsensor.diagnose.calibrate`);
5. score the estimator before and after on held-out measured runs, and keep the
   calibrated one only if its gain is more than noise.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from virtsensor.recordings.measured import MeasuredRun


def diagnose(
    runs: Sequence[MeasuredRun],
    holdout: Sequence[MeasuredRun],
    base: Mapping[str, Any],
    *,
    mu: float | None = None,
    conditions: Sequence[Any] | None = None,
    backend: str = "loky",
    preset: str = "wide",
    recipe: str = "improved",
    seed: int = 0,
    max_iter: int | None = None,
    ensemble: int = 3,
    n_jobs: int = 1,
    retrain: bool = True,
    before: Any = None,
    log: Callable[[str], None] = lambda msg: None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Diagnose ``runs``; measure the estimator's gain on ``holdout``.

    Args:
        runs: measured runs for the diagnosis and the calibration.
        holdout: measured runs for scoring only (may be empty: no gain is measured).
        base: the simulator's nominal car.
        mu: the road friction of every run without a stated one (None: unknown, identified per run).
        conditions: each run's :class:`~virtsensor.diagnose.conditions.RunConditions` (None: none stated).
        backend: where the re-simulations run (``loky`` or ``ray``, :mod:`virtsensor.diagnose.parallel`).
        preset, recipe, seed, max_iter, ensemble: the training campaign and estimator
            recipe of the nominal estimator (``ensemble`` networks averaged); the calibrated one is always
            trained exactly like the nominal one (:func:`~virtsensor.diagnose.calibrate.retrain_like`).
        retrain: calibrate and retrain (False: diagnosis only).
        before: an already trained nominal :class:`~virtsensor.diagnose.calibrate.Estimator`
            (studies reuse it across cases); the calibrated one is trained like it, whatever
            ``preset``, ``seed``... say.

    Returns:
        ``(result, artefacts)``: the JSON-able result (what ``diagnose --json`` writes) and the
        objects the report draws (comparison, estimators).
    """
    from virtsensor.diagnose.compare import compare
    from virtsensor.diagnose.conditions import RunConditions, load_conditions
    from virtsensor.diagnose.identify import identify
    from virtsensor.diagnose.resim import compared_signals

    t0 = time.perf_counter()
    names = compared_signals(runs)
    if conditions is None:
        conditions = load_conditions([r.path for r in runs], None, default_mu=mu) if all(
            r.path is not None for r in runs) else [RunConditions({"mu": (mu, mu)} if mu else {}) for r in runs]
    idn = identify(runs, base, names, conditions=conditions, n_jobs=n_jobs, backend=backend, log=log)
    result = _identification_result(idn, runs, holdout, time.perf_counter() - t0, conditions)
    comparison = compare(runs, idn, names)
    result["comparison"] = comparison.as_dict()
    art: dict[str, Any] = {"comparison": comparison}
    if not retrain:
        return result, art
    before, after = _estimators(idn, base, before, preset=preset, recipe=recipe, seed=seed, max_iter=max_iter,
                                ensemble=ensemble, n_jobs=n_jobs, log=log)
    art.update(before=before, after=after)
    result.update(_scores(before, after, runs, holdout, idn, names, preset=preset, seed=seed))
    result["seconds_total"] = time.perf_counter() - t0
    return result, art


def _identification_result(idn, runs: Sequence[MeasuredRun], holdout: Sequence[MeasuredRun],
                           seconds: float, conditions: Sequence[Any] = ()) -> dict[str, Any]:
    """The diagnosis part of the result: the cause named, its fit, every candidate, the runs used;
    ``seconds`` is the identification's wall time; ``conditions``: each run's stated ones (their notes)."""
    best = idn.best if idn.unexplained is None else None
    return {
        "cause": idn.cause,
        "causes": [_cause_entry(f) for f in _named(idn)],
        "unexplained": idn.unexplained,
        "run_conditions": _run_conditions(idn, runs, conditions),
        "signal": best.candidate.signal if best else None,
        "estimate": best.estimate if best else None,
        "ci95": list(best.ci95) if best else None,
        "unit": _unit(best) if best else None,
        "nominal": best.candidate.nominal if best else None,
        "variance_explained": best.variance_explained if best else 0.0,
        "signature": _signature(best) if best else _residual_signature(idn),
        "residuals": _residuals(idn),
        "second_stage": [f.as_dict() for f in idn.second],
        "candidates": [f.as_dict() for f in idn.fits],
        "n_eff_factor": idn.n_eff_factor,
        "message_shifts_s": idn.shifts,
        "runs": [{"name": r.name, "file": str(r.path), "duration_s": r.duration_s,
                  "segments": len(r.segments), "gaps_s": r.gaps, "notes": r.notes,
                  "left_out": idn.excluded.get(r.name)} for r in runs],
        "holdout_runs": [{"name": r.name, "file": str(r.path), "duration_s": r.duration_s,
                          "gaps_s": r.gaps} for r in holdout],
        "simulations": idn.simulations,
        "seconds_identify": seconds,
    }


def _cause_entry(fit) -> dict[str, Any]:
    c = fit.candidate
    return {"cause": c.cause, "signal": c.signal, "estimate": fit.estimate, "ci95": list(fit.ci95),
            "unit": _unit(fit), "nominal": c.nominal, "bic_gain": fit.bic_gain,
            "variance_explained": fit.variance_explained,
            **({"kinematics": fit.groups["kinematics"]} if "kinematics" in fit.groups else {})}


def _run_conditions(idn, runs: Sequence[MeasuredRun], conditions: Sequence[Any] = ()) -> list[dict[str, Any]]:
    """Per run: the condition values the re-simulation used and, for the ranged ones, their identification
    (estimate, 95 % interval, whether the run excites them); ``notes``: what was left out of its stated
    conditions (:attr:`~virtsensor.diagnose.conditions.RunConditions.notes`, e.g. a JSON beside it that is
    another run's metadata, ignored)."""
    out = []
    for r, run in enumerate(runs):
        day = idn.day[r] if r < len(idn.day) else {}
        ident = idn.nuisance[r] if r < len(idn.nuisance) else {}
        notes = list(getattr(conditions[r], "notes", ())) if r < len(conditions) else []
        out.append({"name": run.name, "used": dict(day), "identified": ident, "notes": notes})
    return out


def _estimators(idn, base: Mapping[str, Any], before: Any, *, preset: str, recipe: str, seed: int,
                max_iter: int | None, ensemble: int, n_jobs: int, log: Callable[[str], None]) -> tuple[Any, Any]:
    """``(before, after)``: the estimator trained on the nominal simulator (``before`` if given) and the
    calibrated one (``before`` itself when no cause is named).

    The calibrated estimator undoes what can be undone where it happens: an offset or a gain of an input
    sensor is inverted at the estimator's input (:func:`~virtsensor.diagnose.calibrate.undo_sensor_errors`),
    so that the estimator sees the signal the simulator's sensor gives; a condition of the test day (the road's
    friction, :data:`DAY_CONDITIONS`) is no property of the car, and the estimator, trained over a range of roads
    already, is not retrained for it; every other cause (a physical one, a delay, which cannot be undone in real
    time) needs the estimator retrained on the simulator calibrated with it. A day with only input offsets and
    gains (and day conditions) keeps the nominal network, its inputs corrected (no retraining: the same network,
    so the gain is the correction's alone); otherwise the network retrained on the simulator with the other
    causes, its inputs corrected for the offsets and gains. The retraining repeats the nominal
    estimator's own (recipe, campaign, seed, epochs, ensemble: :func:`calibrate.retrain_like`), so that the
    difference between the two is the calibration's alone, also when ``before`` was trained elsewhere."""
    from sim.effects import with_effect
    from virtsensor.diagnose import calibrate

    if before is None:
        log(f"training the estimator on the nominal simulator ({preset} campaign, {recipe} recipe)")
        before = calibrate.train(base, preset=preset, recipe=recipe, seed=seed, n_jobs=n_jobs, max_iter=max_iter,
                                 ensemble=ensemble)
    causes = _named(idn)
    if not causes:
        return before, before
    at_input = [f for f in causes if f.candidate.cause in UNDONE_AT_INPUT]
    retrain = [f for f in causes if f.candidate.cause not in UNDONE_AT_INPUT + DAY_CONDITIONS]
    for f in causes:
        if f.candidate.cause in DAY_CONDITIONS:
            log(f"{f.candidate.key} = {f.estimate:.4g} is a condition of the day, not of the car: not retrained for")
    after = before
    if retrain:
        cal = dict(base)
        for f in retrain:
            c = f.candidate
            log(f"calibrating the simulator ({c.key} = {f.estimate:.4g})")
            cal = with_effect(cal, c.cause, f.estimate, c.signal)
        log("retraining on the calibrated simulator")
        after = calibrate.retrain_like(before, cal, n_jobs=n_jobs)
        after.recipe["retrained_with"] = {f.candidate.key: f.estimate for f in retrain}
    if at_input:
        errors = [_sensor_error(f) for f in at_input]
        log("undoing at the estimator's input: " + ", ".join(f.candidate.key for f in at_input))
        after = calibrate.undo_sensor_errors(after, errors)
    return before, after


#: sensor causes the calibrated estimator undoes at its input instead of learning them (:func:`_estimators`)
UNDONE_AT_INPUT = ("sensor_offset", "sensor_gain")
#: causes that are conditions of the test day, not properties of the car: the re-simulations take them, the
#: estimator (whose campaign spans a range of frictions: 0.4 to 1 for ``wide``) is not retrained for them
#: (:func:`_estimators`). Retraining for a day-wide friction of 0.8 would scale every road of the campaign by 0.8
#: and drop the dry ones.
DAY_CONDITIONS = ("road_friction",)


def _named(idn) -> list[Any]:
    """The causes the identification names (none when the day is ``unexplained``: nothing is calibrated then)."""
    return list(idn.causes) if idn.unexplained is None else []


def _sensor_error(fit) -> tuple[str, float, float]:
    """``(signal, offset, gain)`` of a named sensor offset or gain, as :func:`calibrate.undo_sensor_errors`
    takes it."""
    c = fit.candidate
    if c.cause == "sensor_offset":
        return str(c.signal), float(fit.estimate), 1.0
    return str(c.signal), 0.0, float(fit.estimate)


def _scores(before: Any, after: Any, runs: Sequence[MeasuredRun], holdout: Sequence[MeasuredRun], idn, names,
            *, preset: str, seed: int) -> dict[str, Any]:
    """The estimator part of the result: the campaigns, the ``before`` estimator on the diagnosis runs
    measured and re-simulated, and both estimators on ``holdout`` (None, with a note, when it is empty)."""
    from virtsensor.diagnose import calibrate

    result: dict[str, Any] = {}
    result["estimator"] = {"preset": preset, "recipe": before.recipe, "seed": seed,
                           "train_samples_before": before.samples, "train_samples_after": after.samples,
                           "retrained_with": after.recipe.get("retrained_with", {}),
                           "inputs_corrected": after.recipe.get("inputs_corrected", {}),
                           "day_conditions": {f.candidate.key: f.estimate for f in _named(idn)
                                              if f.candidate.cause in DAY_CONDITIONS}}
    # the estimator on measured data vs on its own simulation (the diagnosis runs, re-simulated)
    result["estimator_on_diagnosis_runs"] = {
        "measured": calibrate.score(before, runs),
        "simulated": calibrate.score(before, _as_simulated(runs, idn.nominal_sims, names)),
    }
    if holdout:
        sb, sa = calibrate.scores([before, after], holdout)
        gain = calibrate.paired_gain(before, after, holdout, seed=seed)
        keep = after is not before and not gain["better"]
        result.update(mae_before_nm=sb["mae_nm"], mae_after_nm=sb["mae_nm"] if keep else sa["mae_nm"],
                      r2_before=sb["r2"], r2_after=sb["r2"] if keep else sa["r2"],
                      holdout_before=sb, holdout_after=sa, gain=gain,
                      estimator_kept="nominal" if (keep or after is before) else "calibrated")
        if keep:
            result["gain_note"] = (f"the calibrated estimator is not better than the nominal one on the held-out runs "
                                   f"beyond noise (MAE {sb['mae_nm']:.2f} -> {sa['mae_nm']:.2f} Nm, gain 95 % "
                                   f"interval {gain['ci95_nm'][0]:+.2f} to {gain['ci95_nm'][1]:+.2f} Nm): "
                                   "the nominal estimator is kept")
    else:
        result.update(mae_before_nm=None, mae_after_nm=None, r2_before=None, r2_after=None,
                      gain_note="no held-out measured runs: the gain was not measured")
    return result


def _unit(fit) -> str:
    from sim.effects import EFFECTS
    from virtsensor import signals as cat

    c = fit.candidate
    if c.cause == "sensor_offset":
        return cat.SIGNALS[c.signal].unit
    return EFFECTS[c.cause].unit


def _signature(fit) -> dict[str, Any]:
    """Where the effect shows: the signals whose misfit it explains most."""
    top = sorted(fit.per_signal.items(), key=lambda kv: -kv[1])[:4]
    return {"explains": {k: round(v, 4) for k, v in top if v > 0.01}}


def _residual_signature(idn) -> dict[str, Any]:
    """With no cause named: each signal's residual RMS against the nominal re-simulation (its unit)."""
    import numpy as np

    rel = {k: float(np.sqrt(idn.rss_nominal[k] / max(idn.n[k], 1))) for k in idn.names}
    return {"residual_rms": {k: round(v, 6) for k, v in rel.items()}}


def _residuals(idn) -> dict[str, Any]:
    """Per signal: the residual RMS of the nominal car and of the best explanation (its unit), the
    measured signal's RMS about its mean, and the best explanation's residual over what a correct one
    leaves (``excess``, :func:`virtsensor.diagnose.identify.residual_excess`)."""
    import numpy as np

    def rms(rss: Mapping[str, float]) -> dict[str, float]:
        return {k: round(float(np.sqrt(rss[k] / max(idn.n[k], 1))), 6) for k in idn.names if k in rss}

    return {"nominal": rms(idn.rss_nominal), "best": rms(idn.rss_best or idn.rss_nominal),
            "signal": {k: round(v, 6) for k, v in (idn.scale or {}).items()},
            "excess": {k: round(v, 3) for k, v in (idn.excess or {}).items()},
            "excess_first_cause": {k: round(v, 3) for k, v in (idn.excess_first or {}).items()}}


def _as_simulated(runs: Sequence[MeasuredRun], sims, names) -> list[MeasuredRun]:
    """The diagnosis runs with their signals replaced by the nominal re-simulation's."""
    import numpy as np

    out = []
    for r, run in enumerate(runs):
        table = {k: np.array(v, copy=True) for k, v in run.table.items()}
        for s, seg in enumerate(run.segments):
            for n in names:
                table[n][seg.start:seg.stop] = sims[r][s]["pred"][n]
        out.append(MeasuredRun(run.name, run.path, table, run.segments, run.gaps, run.notes))
    return out
