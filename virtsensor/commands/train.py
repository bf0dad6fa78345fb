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

HELP = "train the paper's MLP (or the improved one) on recordings and export it to ONNX with its model card"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", nargs="+", required=True, metavar="PATH",
                        help="recordings (.csv tables or CAN logs) or directories of them")
    parser.add_argument("--recipe", default="paper", help="paper (Table III) or improved (default: paper)")
    parser.add_argument("--out", required=True, metavar="FILE.onnx", help="ONNX file; the card goes beside it")
    parser.add_argument("--grid", action="store_true", help="grid search of Section III.B before the final fit")
    parser.add_argument("--grid-rows", type=int, default=12000, help="rows the grid search uses (default 12000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the splits and the network's initialisation")
    parser.add_argument("--jobs", type=int, default=-1, help="parallel workers of the grid search")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from threadpoolctl import threadpool_limits

    from virtsensor import signals as cat
    from virtsensor.dataset import build_dataset, load_runs
    from virtsensor.errors import UserError
    from virtsensor.evaluation import grouped_split
    from virtsensor.features import SPECS
    from virtsensor.training import RECIPES, grid_search, make_pipeline, metrics

    if args.recipe not in RECIPES:
        raise UserError(f"--recipe: unknown recipe {args.recipe!r}; choose one of: {', '.join(RECIPES)}")
    out = Path(args.out)
    if out.suffix != ".onnx":
        raise UserError(f"--out {out}: the model file must end in .onnx")
    if not out.parent.exists():
        raise UserError(f"--out {out}: directory {out.parent} does not exist")

    def say(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr)

    recipe = json.loads(json.dumps(RECIPES[args.recipe]))
    spec = SPECS[recipe["features"]]
    runs = load_runs(args.data, needed=(*spec.signals, *cat.OUTPUTS))
    ds = build_dataset(runs, spec)
    say(f"{len(ds.runs)} runs, {len(ds.X)} rows of {len(ds.feature_names)} features "
        f"({ds.dropped_nonfinite} non-finite rows dropped)")
    report: dict = {"recipe": args.recipe}
    # small MLPs train ~5x faster on one BLAS thread than on a 2-core pool
    with warnings.catch_warnings(), threadpool_limits(1):
        warnings.simplefilter("ignore")  # convergence notes: the iteration counts go to the card instead
        if args.grid:
            result = grid_search(ds.X, ds.Y, ds.groups, max_rows=args.grid_rows, seed=args.seed, n_jobs=args.jobs,
                                 progress=not args.quiet, base_params=recipe["params"])
            recipe["params"] = result.best_params
            report["grid_search"] = {"best_r2": result.best_r2, "seconds": result.seconds, "rows": result.rows,
                                     "folds": result.folds, "candidates": result.candidates}
            say(f"grid search: {len(result.candidates)} candidates in {result.seconds:.0f} s, "
                f"best R2 {result.best_r2:.4f} with {json.dumps(result.best_params, default=str)}")
        tr, te = grouped_split(ds.groups, args.seed)
        holdout = make_pipeline(recipe["params"], args.seed).fit(ds.X[tr], ds.Y[tr])
        report["grouped_holdout"] = metrics(ds.Y[te], holdout.predict(ds.X[te]))
        held = report["grouped_holdout"]
        say(f"runs held out: R2 {held['r2']:.4f}, MAE {held['mae_nm']:.2f} Nm")
        t0 = time.perf_counter()
        model = make_pipeline(recipe["params"], args.seed).fit(ds.X, ds.Y)
        fit_s = time.perf_counter() - t0
    report["train"] = metrics(ds.Y, model.predict(ds.X))
    mlp = model.steps[-1][1]
    report["fit_seconds"] = fit_s
    report["iterations"] = int(getattr(mlp, "n_iter_", 0))
    say(f"final fit on all runs: {fit_s:.1f} s, {report['iterations']} epochs, training R2 {report['train']['r2']:.4f}")
    rng = np.random.default_rng(args.seed)
    parity_rows = ds.X[rng.choice(len(ds.X), min(5000, len(ds.X)), replace=False)]
    try:
        card = _export(model, ds, out, parity_rows, args, recipe, spec, report)
    except ValueError as exc:  # parity beyond 1e-3 Nm: nothing was written
        raise UserError(f"{out}: export refused: {exc}") from None
    say(f"wrote {out} (sha256 {card['sha256'][:12]}..., ONNX/sklearn parity {card.get('parity_max_abs_nm', 0):.2e} Nm)")
    return 0


def _export(model, ds, out, parity_rows, args, recipe, spec, report):
    from virtsensor.model import ModelCard
    from virtsensor.model.export import export_pipeline, pipeline_weights

    return export_pipeline(model, len(ds.feature_names), out, parity_X=parity_rows, card_extra=ModelCard.trainer_fields(
        model=f"virtsensor-{args.recipe}", spec=spec, recipe=recipe, seed=args.seed, metrics=report,
        training_data={
            "fingerprint_sha256": ds.fingerprint(), "rows": int(len(ds.X)), "runs": len(ds.runs),
            "dropped_nonfinite": ds.dropped_nonfinite, "sources": [str(p) for p in args.data],
        },
        # the same weights as plain arrays: the numpy back-end and audits need no sklearn
        weights=pipeline_weights(model)))
