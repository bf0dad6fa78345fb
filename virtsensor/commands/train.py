"""``virtsensor train``: fit an estimator recipe on recordings and export it to ONNX.

Example::

    virtsensor campaign paper --out data/paper
    virtsensor train --data data/paper --recipe improved --out models/improved.onnx
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

#: Folds of the grid search (whole runs per fold).
GRID_FOLDS = 3
#: rows the grid search uses unless --grid-rows says otherwise
GRID_ROWS = 12000
HELP = "train the paper's MLP (or the improved one) on recordings and export it to ONNX with its model card"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from virtsensor.commands import _types as t

    parser.add_argument("--data", nargs="+", required=True, metavar="PATH", type=t.existing_path(),
                        help="recordings (.csv tables or CAN logs) or directories of them (2 runs or more)")
    parser.add_argument("--recipe", default="paper",
                        help="paper (Table III), improved, or tpms (improved + front TPMS pressures; needs --fallback) "
                             "(default: paper)")
    parser.add_argument("--fallback", metavar="FILE.onnx", type=t.existing_file(".onnx"), default=None,
                        help="recipe tpms: the pressure-free model (beside --out, reading this model's first "
                             "features) that estimates where the pressures are unknown")
    parser.add_argument("--out", required=True, metavar="FILE.onnx", type=t.output_file(".onnx"),
                        help="ONNX file; the card goes beside it")
    parser.add_argument("--grid", action="store_true", help="grid search of Section III.B before the final fit")
    parser.add_argument("--grid-rows", type=t.int_range(100, 10**7), default=None, metavar="N",
                        help=f"with --grid: rows the grid search uses (100 to 10,000,000; default {GRID_ROWS})")
    parser.add_argument("--seed", type=t.seed(), default=0,
                        help="seed of the splits and the network's initialisation (0 to 2**32-1)")
    parser.add_argument("--jobs", type=t.jobs(), default=None, metavar="N",
                        help="parallel workers of the grid search (with --grid; 1 to 1024, or -1: all cores; "
                             "default -1)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from threadpoolctl import threadpool_limits

    from virtsensor import signals as cat
    from virtsensor.errors import UserError
    from virtsensor.features import SPECS
    from virtsensor.interrupt import fitted
    from virtsensor.learning.dataset import build_dataset, load_runs
    from virtsensor.learning.evaluation import grouped_split, require_rows, require_variation
    from virtsensor.learning.training import RECIPES, grid_search, make_pipeline
    from virtsensor.metrics import metrics

    _check_options(args, RECIPES)
    out = Path(args.out)  # kind, suffix and directory checked by the argument's type

    def say(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr)

    recipe = json.loads(json.dumps(RECIPES[args.recipe]))
    spec = SPECS[recipe["features"]]
    fallback = _fallback(args, recipe, spec, out)
    runs = load_runs(args.data, needed=(*spec.signals, *cat.OUTPUTS))
    ds = build_dataset(runs, spec)
    require_rows(ds, runs, recipe["features"])  # (a run too short for the features' lags, say: it counted as one)
    unknown = sum(1 for r in runs if r.meta.get("pressure_unknown"))
    if unknown:
        say(f"{unknown} run(s) without TPMS pressures: pressure unknown (not nominal), their rows not trained on")
    n_runs = len(np.unique(ds.groups))
    if n_runs < 2:
        raise UserError(f"--data: {n_runs} run(s) with usable rows; training holds whole runs out, so it needs at "
                        "least 2")
    require_variation(ds, recipe["features"])
    tr, te = grouped_split(ds.groups, args.seed)  # (held out before the grid search: it never sees those runs)
    n_fit = len(np.unique(ds.groups[tr]))
    if args.grid and n_fit < GRID_FOLDS:
        raise UserError(f"--data: {n_runs} run(s) with usable rows, {n_fit} of them besides the runs held out; --grid "
                        f"searches on those alone, one per fold: it needs at least {GRID_FOLDS}")
    say(f"{len(ds.runs)} runs, {len(ds.X)} rows of {len(ds.feature_names)} features "
        f"({ds.dropped_nonfinite} non-finite rows dropped)")
    report: dict = {"recipe": args.recipe}
    # small MLPs train faster on one BLAS thread than on a pool (README, "Measured figures": the paper fit)
    with warnings.catch_warnings(), threadpool_limits(1):
        warnings.simplefilter("ignore")  # convergence notes: the iteration counts go to the card instead
        if args.grid:
            try:
                result = grid_search(ds.X[tr], ds.Y[tr], ds.groups[tr], folds=GRID_FOLDS,
                                     max_rows=args.grid_rows or GRID_ROWS,
                                     seed=args.seed, n_jobs=-1 if args.jobs is None else args.jobs,
                                     progress=not args.quiet,
                                     base_params=recipe["params"])
            except ValueError as exc:  # (no candidate with a finite R2)
                raise UserError(f"--grid: {exc}") from None
            recipe["params"] = result.best_params
            report["grid_search"] = {"best_r2": result.best_r2, "seconds": result.seconds, "rows": result.rows,
                                     "folds": result.folds, "candidates": result.candidates}
            say(f"grid search: {len(result.candidates)} candidates in {result.seconds:.0f} s, "
                f"best R2 {result.best_r2:.4f} with {json.dumps(result.best_params, default=str)}")
        holdout = fitted(lambda: make_pipeline(recipe["params"], args.seed).fit(ds.X[tr], ds.Y[tr]))
        report["grouped_holdout"] = metrics(ds.Y[te], holdout.predict(ds.X[te]))
        held = report["grouped_holdout"]
        say(f"runs held out: R2 {held['r2']:.4f}, MAE {held['mae_nm']:.2f} Nm")
        t0 = time.perf_counter()
        model = fitted(lambda: make_pipeline(recipe["params"], args.seed).fit(ds.X, ds.Y))
        fit_s = time.perf_counter() - t0
    report["train"] = metrics(ds.Y, model.predict(ds.X))
    mlp = model.steps[-1][1]
    report["fit_seconds"] = fit_s
    report["iterations"] = int(getattr(mlp, "n_iter_", 0))
    say(f"final fit on all runs: {fit_s:.1f} s, {report['iterations']} epochs, training R2 {report['train']['r2']:.4f}")
    rng = np.random.default_rng(args.seed)
    parity_rows = ds.X[rng.choice(len(ds.X), min(5000, len(ds.X)), replace=False)]
    try:
        card = _export(model, ds, out, parity_rows, args, recipe, spec, report, runs, fallback)
    except ValueError as exc:  # parity beyond 1e-3 Nm: nothing was written
        raise UserError(f"{out}: export refused: {exc}") from None
    say(f"wrote {out} (sha256 {card['sha256'][:12]}..., ONNX/sklearn parity {card.get('parity_max_abs_nm', 0):.2e} Nm)")
    return 0


def _check_options(args: argparse.Namespace, recipes) -> None:
    """Refuse an unknown recipe, and an option of the grid search without --grid (it would do nothing)."""
    from virtsensor.errors import UserError

    if args.recipe not in recipes:
        raise UserError(f"--recipe: unknown recipe {args.recipe!r}; choose one of: {', '.join(recipes)}")
    for option, value, what in (("--grid-rows", args.grid_rows, "rows"), ("--jobs", args.jobs, "workers")):
        if value is not None and not args.grid:
            raise UserError(f"{option} goes with --grid (the grid search's {what}); add --grid or drop it")


def _fallback(args, recipe, spec, out):
    """The card's fallback entry (recipe with a fallback: --fallback required), or None."""
    from virtsensor.errors import UserError
    from virtsensor.model.fallback import fallback_entry

    if "fallback" not in recipe:
        if args.fallback is not None:
            raise UserError(f"--fallback: recipe {args.recipe} has no fallback (only tpms has)")
        return None
    if args.fallback is None:
        raise UserError(f"--recipe {args.recipe}: needs --fallback FILE.onnx (a {recipe['fallback']} model beside "
                        f"--out) for the rows without pressures")
    return fallback_entry(Path(args.fallback), out, spec.names)


def _export(model, ds, out, parity_rows, args, recipe, spec, report, runs, fallback=None):
    import numpy as np

    from virtsensor.learning.dataset import trained_digests
    from virtsensor.model import ModelCard
    from virtsensor.model.envelope import Envelope
    from virtsensor.model.export import export_pipeline, pipeline_weights

    return export_pipeline(model, len(ds.feature_names), out, parity_X=parity_rows, card_extra=ModelCard.trainer_fields(
        model=f"virtsensor-{args.recipe}", spec=spec, recipe=recipe, seed=args.seed, metrics=report,
        training_data={
            "fingerprint_sha256": ds.fingerprint(), "rows": int(len(ds.X)), "runs": len(ds.runs),
            "dropped_nonfinite": ds.dropped_nonfinite, "sources": [str(p) for p in args.data],
            "run_digests": trained_digests([runs[i] for i in np.unique(ds.groups)]),  # (runs that gave rows)
        },
        # the same weights as plain arrays: the numpy back-end and audits need no sklearn
        weights=pipeline_weights(model),
        # where the training rows lie: the daemon, score and explain flag rows outside it
        envelope=Envelope.fit(ds.X, ds.feature_names)) | ({} if fallback is None else {"fallback": fallback}))
