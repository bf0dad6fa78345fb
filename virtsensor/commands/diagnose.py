"""``virtsensor diagnose``: what the simulation gets wrong about measured data, why, and the gain.

Example::

    virtsensor diagnose --measured day1/run01.blf day1/run02.blf day1/run03.blf \\
        --holdout day1/run04.blf day1/run05.blf --json diagnosis.json --report diagnosis/ \\
        --export-model models/calibrated.onnx

Measured runs are CAN logs (decoded through the DBC), MDF4 files or canonical
20 Hz CSV tables with the 12 inputs and the reference SATs. ``--holdout`` runs
are used only to measure the estimator before and after the calibration; without
it, the last third of the ``--measured`` runs is held out (when there are 3 or more).
``--conditions`` (or a JSON beside each run) states what is known of each run (see
:mod:`virtsensor.diagnose.conditions`; a JSON whose ``file`` names another file is another run's metadata:
ignored, and the summary and the JSON say so); ``--backend ray`` runs the re-simulations on
a Ray cluster.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

HELP = "sim-to-real: compare measured runs with their re-simulation, name the cause, calibrate, measure the gain"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from sim.params import MU_RANGE
    from virtsensor.commands import _types as t
    from virtsensor.commands._simargs import add_car_arguments

    parser.add_argument("--measured", nargs="+", required=True, metavar="FILE", type=t.existing_path(),
                        help="measured runs (.blf/.asc/.log/.trc CAN logs, .mf4 MDF4, .csv tables) or directories")
    parser.add_argument("--holdout", nargs="+", metavar="FILE", type=t.existing_path(),
                        help="measured runs used only to score the estimator before/after (default: the last "
                             "third of --measured when there are 3 or more)")
    parser.add_argument("--json", metavar="FILE", type=t.output_file(), help="write the result as JSON")
    parser.add_argument("--report", metavar="DIR", type=t.output_dir(),
                        help="write diagnosis.md and PNG plots into this directory")
    parser.add_argument("--mu", type=t.float_range(*MU_RANGE), default=None,
                        help=f"road friction of every run without a stated one ({MU_RANGE[0]:g} to {MU_RANGE[1]:g}; "
                             "default: not known, identified per run where the run excites it)")
    parser.add_argument("--conditions", metavar="FILE.csv", type=t.existing_path(),
                        help="per-run conditions: a 'file' column and any of mu, pressure_bar, mass_kg, each exact "
                             "(0.7) or a range (0.5..0.9); a JSON beside a run (same stem) works too")
    parser.add_argument("--backend", default="loky", choices=("loky", "ray"),
                        help="where re-simulations run: local joblib workers (loky, default) or a Ray cluster "
                             "(ray; needs the 'distributed' extra)")
    parser.add_argument("--campaign", default=None, help="training campaign preset for the estimators "
                        "(wide, smoke, tiny, paper; default wide: an estimator trained on smoke errs so much on "
                        "held-out runs that a calibration's gain hardly shows)")
    parser.add_argument("--recipe", default=None, help="estimator recipe (paper, improved; default improved)")
    parser.add_argument("--max-iter", type=t.int_range(1, 100000), default=None, metavar="N",
                        help="MLP epochs (1 to 100000; default: the recipe's)")
    parser.add_argument("--ensemble", type=t.int_range(1, 10), default=None, metavar="N",
                        help="networks averaged per estimator (merged into one ONNX network; 1 to 10, default 3)")
    parser.add_argument("--seed", type=t.seed(), default=None,
                        help="seed of the campaigns and the training (0 to 2**32-1; default 0)")
    parser.add_argument("--n-jobs", type=t.jobs(), default=-1, metavar="N",
                        help="joblib workers for the re-simulations (1 to 1024, or -1: all cores)")
    parser.add_argument("--no-retrain", action="store_true",
                        help="diagnose only: no calibration, no gain (the options of the retraining, --campaign to "
                             "--seed, --holdout and --export-model, are refused with it)")
    parser.add_argument("--export-model", metavar="FILE.onnx", type=t.output_file(".onnx"),
                        help="export the calibrated estimator (ONNX and model card)")
    parser.add_argument("--quiet", action="store_true")
    add_car_arguments(parser)


#: The options that set the retraining (option, argument name, default): --no-retrain skips what they set.
RETRAINING = (("--campaign", "campaign", "wide"), ("--recipe", "recipe", "improved"), ("--max-iter", "max_iter", None),
              ("--ensemble", "ensemble", 3), ("--seed", "seed", 0), ("--holdout", "holdout", None),
              ("--export-model", "export_model", None))


def _check_retraining_options(args: argparse.Namespace) -> None:
    """Refuse an option of the retraining given with --no-retrain (it would do nothing, without a word); then
    fill in the defaults of those not given."""
    from virtsensor.errors import UserError

    given = [opt for opt, name, _ in RETRAINING if getattr(args, name) is not None]
    if args.no_retrain and given:
        raise UserError(f"{', '.join(given)} set{'s' if len(given) == 1 else ''} the retraining and the held-out "
                        f"score, which --no-retrain skips: drop {'it' if len(given) == 1 else 'them'} or --no-retrain")
    for _, name, default in RETRAINING:
        if getattr(args, name) is None:
            setattr(args, name, default)


def run(args: argparse.Namespace) -> int:
    from sim.campaign import PRESETS
    from virtsensor.commands._simargs import car_from_args
    from virtsensor.diagnose import diagnose
    from virtsensor.errors import UserError
    from virtsensor.learning.training import RECIPES
    from virtsensor.recordings.measured import load_measured

    _check_retraining_options(args)
    if args.campaign not in PRESETS:
        raise UserError(f"--campaign {args.campaign!r}: one of {', '.join(PRESETS)}")
    if args.recipe not in RECIPES:
        raise UserError(f"--recipe {args.recipe!r}: one of {', '.join(RECIPES)}")
    from virtsensor.diagnose.conditions import load_conditions
    from virtsensor.diagnose.parallel import check_backend

    check_backend(args.backend)
    base = car_from_args(args)
    skipped: list[tuple[str, str]] = []
    runs = load_measured(args.measured, skipped=skipped)
    if args.holdout:
        holdout = load_measured(args.holdout, skipped=skipped)
        from virtsensor.recordings.identity import refuse_repeats

        refuse_repeats([(r.path, r.digest, r.table) for r in (*runs, *holdout)],
                       "given both as --measured and --holdout: a held-out run must play no part in the diagnosis")
    elif len(runs) >= 3 and not args.no_retrain:
        k = len(runs) // 3
        runs, holdout = runs[:-k], runs[-k:]
    else:
        holdout = []

    def log(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr)

    # held-out runs may be listed in the conditions file too (their conditions are not used)
    conds = load_conditions([r.path for r in (*runs, *holdout)], Path(args.conditions) if args.conditions else None,
                            default_mu=args.mu, also=[p for p, _ in skipped])[:len(runs)]
    for path, why in skipped:
        log(f"left out {path}: {why}")
    if holdout and not args.holdout and not args.quiet:
        log(f"holding out {', '.join(r.name for r in holdout)} for the gain (give --holdout to choose)")
    res, art = diagnose(runs, holdout, base, mu=args.mu, conditions=conds, backend=args.backend,
                        preset=args.campaign, recipe=args.recipe, seed=args.seed, max_iter=args.max_iter,
                        ensemble=args.ensemble, n_jobs=args.n_jobs, retrain=not args.no_retrain, log=log)
    res["skipped_runs"] = [{"file": p, "reason": why} for p, why in skipped]
    export = _export(art["after"], res, args) if args.export_model else None
    n_plots = _write_outputs(res, art, args, export)
    print(_summary(res))
    if args.report:
        d = Path(args.report)
        log(f"report: {d / 'diagnosis.md'}" + (f" and {n_plots} plots" if n_plots else
                                                " (plots skipped: matplotlib is not installed)"))
    return 0


def _write_outputs(res, art, args, export) -> int:
    """The JSON, the exported model and its card, the report and its plots: all or none (each written into a
    staged file or folder, put in place once every one is written); returns the number of plots."""
    from contextlib import nullcontext

    from virtsensor.fileio import staged_dir, staged_files, write_json
    from virtsensor.model.card import card_path_for

    model = Path(args.export_model) if export is not None else None
    n_plots = 0
    with staged_files(args.json, model, None if model is None else card_path_for(model)) as (js, mo, ca), \
            (staged_dir(args.report) if args.report else nullcontext()) as rep:
        if js is not None:
            write_json(js, res)
        if export is not None and mo is not None and ca is not None:
            onnx_bytes, card = export
            card.verify()
            mo.write_bytes(onnx_bytes)
            ca.write_bytes(card.text().encode("utf-8"))
        if rep is not None:
            from virtsensor.diagnose.report import markdown, plots

            (rep / "diagnosis.md").write_bytes(markdown(res).encode())
            n_plots = len(plots(art, res, rep))
    return n_plots


def _summary(res) -> str:
    if res["cause"] == "none":
        line = "cause: none (no candidate explains the residual decisively)"
    elif res["cause"] == "unexplained":
        u = res["unexplained"]
        line = (f"cause: unexplained (no catalogue effect accounts for the misfit; it remains in "
                f"{', '.join(u['signals'])}, {u['region']}); no calibration applied")
    else:
        parts = []
        for c in res["causes"]:
            on = f" on {c['signal']}" if c["signal"] else ""
            parts.append(f"{c['cause']}{on}, estimate {c['estimate']:.4g} {c['unit']} "
                         f"(95 % CI {c['ci95'][0]:.4g} to {c['ci95'][1]:.4g}; nominal {c['nominal']:.4g})")
        line = "cause: " + "\nand: ".join(parts)
    for rc in res.get("run_conditions", []):
        for note in rc.get("notes", []):
            line += f"\n{rc['name']}: {note}"
        for q, v in rc["identified"].items():
            how = "" if v["excited"] else " (the run does not excite it)"
            line += (f"\n{rc['name']}: {q} {v['estimate']:.3g} (95 % CI {v['ci95'][0]:.3g} to "
                     f"{v['ci95'][1]:.3g}){how}")
    if res.get("mae_before_nm") is not None:
        line += (f"\nheld-out SAT MAE {res['mae_before_nm']:.2f} -> {res['mae_after_nm']:.2f} Nm, "
                 f"R2 {res['r2_before']:.3f} -> {res['r2_after']:.3f}")
        if res.get("gain_note"):
            line += f"\n{res['gain_note']}"
    return line


def _export(est, res, args) -> tuple[bytes, Any]:
    """The calibrated estimator as ONNX bytes and its sealed card (nothing written: :func:`_write_outputs`); sets
    ``res["exported_model"]``."""
    import numpy as np

    from virtsensor.errors import UserError
    from virtsensor.features import SPECS
    from virtsensor.model import ModelCard
    from virtsensor.model.export import build_export, pipeline_weights

    spec = SPECS[est.recipe["features"]]
    rng = np.random.default_rng(args.seed)
    mlp_scale = est.pipeline[0]
    parity = rng.normal(size=(500, len(spec.names))) * getattr(mlp_scale, "scale_", 1.0) + getattr(
        mlp_scale, "center_", 0.0)
    extra = ModelCard.trainer_fields(
        model=f"virtsensor-{args.recipe}-calibrated", spec=spec, recipe=est.recipe, seed=args.seed,
        training_data={"fingerprint_sha256": est.fingerprint, "rows": est.samples, "campaign": args.campaign,
                       "calibration": {k: res[k] for k in ("cause", "signal", "estimate", "ci95")}},
        metrics={k: res.get(k) for k in ("mae_before_nm", "mae_after_nm", "r2_before", "r2_after")},
        weights=pipeline_weights(est.pipeline))
    try:
        onnx_bytes, card = build_export(est.pipeline, len(spec.names), args.export_model, parity_X=parity,
                                        card_extra=extra)
    except ValueError as exc:
        raise UserError(f"{args.export_model}: export refused: {exc}") from None
    res["exported_model"] = f"{args.export_model} (sha256 {card['sha256'][:12]}...)"
    return onnx_bytes, card
