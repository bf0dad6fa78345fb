"""Sim-to-real: what the simulation gets wrong about measured data, why, and the gain of fixing it.

:func:`diagnose` is the whole procedure behind ``virtsensor diagnose``:

1. load and check the measured runs (:mod:`virtsensor.recordings.measured`);
2. re-simulate them from their driver inputs and compare signal by signal
   (:mod:`virtsensor.diagnose.compare`);
3. identify every candidate effect of :mod:`sim.effects` and name the best
   explanation, or ``none`` (:mod:`virtsensor.diagnose.identify`);
4. calibrate the simulator with it, regenerate the training campaign, retrain
   (:mod:`virtsensor.diagnose.calibrate`);
5. score the estimator before and after on held-out measured runs.
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
    mu: float = 1.0,
    preset: str = "smoke",
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
        mu: the test track's road friction (what the re-simulation assumes).
        preset, recipe, seed, max_iter, ensemble: the training campaign and estimator
            recipe used before and after the calibration (``ensemble`` networks averaged).
        retrain: calibrate and retrain (False: diagnosis only).
        before: an already trained nominal :class:`~virtsensor.diagnose.calibrate.Estimator`
            (studies reuse it across cases).

    Returns:
        ``(result, artefacts)``: the JSON-able result (what ``diagnose --json`` writes) and the
        objects the report draws (comparison, estimators).
    """
    from virtsensor.diagnose.compare import compare
    from virtsensor.diagnose.identify import identify
    from virtsensor.diagnose.resim import compared_signals

    t0 = time.perf_counter()
    names = compared_signals(runs)
    idn = identify(runs, base, names, mu=mu, n_jobs=n_jobs, log=log)
    result = _identification_result(idn, runs, holdout, time.perf_counter() - t0)
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
                           seconds: float) -> dict[str, Any]:
    """The diagnosis part of the result: the cause named, its fit, every candidate, the runs used;
    ``seconds`` is the identification's wall time."""
    best = idn.best
    return {
        "cause": idn.cause,
        "signal": best.candidate.signal if best else None,
        "estimate": best.estimate if best else None,
        "ci95": list(best.ci95) if best else None,
        "unit": _unit(best) if best else None,
        "nominal": best.candidate.nominal if best else None,
        "variance_explained": best.variance_explained if best else 0.0,
        "signature": _signature(best) if best else _residual_signature(idn),
        "candidates": [f.as_dict() for f in idn.fits],
        "n_eff_factor": idn.n_eff_factor,
        "message_shifts_s": idn.shifts,
        "runs": [{"name": r.name, "file": str(r.path), "duration_s": r.duration_s,
                  "segments": len(r.segments), "gaps_s": r.gaps, "notes": r.notes} for r in runs],
        "holdout_runs": [{"name": r.name, "file": str(r.path), "duration_s": r.duration_s,
                          "gaps_s": r.gaps} for r in holdout],
        "simulations": idn.simulations,
        "seconds_identify": seconds,
    }


def _estimators(idn, base: Mapping[str, Any], before: Any, *, preset: str, recipe: str, seed: int,
                max_iter: int | None, ensemble: int, n_jobs: int, log: Callable[[str], None]) -> tuple[Any, Any]:
    """``(before, after)``: the estimator trained on the nominal simulator (``before`` if given) and the
    one trained on the simulator calibrated with the named cause (``before`` itself when none is named)."""
    from sim.effects import with_effect
    from virtsensor.diagnose import calibrate

    if before is None:
        log(f"training the estimator on the nominal simulator ({preset} campaign, {recipe} recipe)")
        before = calibrate.train(base, preset=preset, recipe=recipe, seed=seed, n_jobs=n_jobs, max_iter=max_iter,
                                 ensemble=ensemble)
    best = idn.best
    if best is None:
        return before, before
    log(f"calibrating the simulator ({best.candidate.key} = {best.estimate:.4g}) and retraining")
    cal = with_effect(base, best.candidate.cause, best.estimate, best.candidate.signal)
    after = calibrate.train(cal, preset=preset, recipe=recipe, seed=seed, n_jobs=n_jobs, max_iter=max_iter,
                            ensemble=ensemble)
    return before, after


def _scores(before: Any, after: Any, runs: Sequence[MeasuredRun], holdout: Sequence[MeasuredRun], idn, names,
            *, preset: str, seed: int) -> dict[str, Any]:
    """The estimator part of the result: the campaigns, the ``before`` estimator on the diagnosis runs
    measured and re-simulated, and both estimators on ``holdout`` (None, with a note, when it is empty)."""
    from virtsensor.diagnose import calibrate

    result: dict[str, Any] = {}
    result["estimator"] = {"preset": preset, "recipe": before.recipe, "seed": seed,
                           "train_samples_before": before.samples, "train_samples_after": after.samples}
    # the estimator on measured data vs on its own simulation (the diagnosis runs, re-simulated)
    result["estimator_on_diagnosis_runs"] = {
        "measured": calibrate.score(before, runs),
        "simulated": calibrate.score(before, _as_simulated(runs, idn.nominal_sims, names)),
    }
    if holdout:
        sb, sa = calibrate.scores([before, after], holdout)
        result.update(mae_before_nm=sb["mae_nm"], mae_after_nm=sa["mae_nm"], r2_before=sb["r2"], r2_after=sa["r2"],
                      holdout_before=sb, holdout_after=sa)
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
