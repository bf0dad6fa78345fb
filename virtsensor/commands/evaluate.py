"""``virtsensor evaluate``: Table IV, the paper's protocols beside honest ones.

Example::

    virtsensor simulate magny-cours --speed 180 --mu 1.0 --out data/track.csv
    virtsensor evaluate --model models/improved.onnx --data data/paper --track data/track.csv \\
        --circuits data/unseen/*.csv --json evaluation.json --markdown evaluation.md
"""

from __future__ import annotations

import argparse
import sys
import warnings

HELP = "Table IV: the paper's protocols and honest ones, baselines, JSON and Markdown"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from virtsensor.commands import _types as t

    parser.add_argument("--model", required=True, metavar="FILE.onnx", type=t.existing_file(".onnx"),
                        help="the model under test; its card's recipe is evaluated as 'improved' "
                             "(unless it is the paper's) and the ONNX file itself on the track laps")
    parser.add_argument("--data", nargs="+", required=True, metavar="PATH", type=t.existing_path(),
                        help="Table I recordings (files or directories), as for train")
    parser.add_argument("--train-extra", nargs="+", default=[], metavar="PATH", type=t.existing_path(),
                        help="recordings added to the training side of every protocol of the improved recipe "
                             "(e.g. the circuits campaign); test rows and held-out runs come from --data only")
    parser.add_argument("--track", metavar="FILE", type=t.existing_file(),
                        help="Magny-Cours recording (dry lap then wet lap)")
    parser.add_argument("--circuits", nargs="+", default=[], metavar="FILE", type=t.existing_file(),
                        help="recordings of circuits never trained on: one Table IV row each (named by the file "
                             "stem), the shipped model also scored inside and outside its validity envelope")
    parser.add_argument("--tpms-model", metavar="FILE.onnx", type=t.existing_file(".onnx"),
                        help="the TPMS model (recipe tpms) scored beside --model in the pressure protocol")
    parser.add_argument("--pressure-runs", nargs="+", default=[], metavar="PATH", type=t.existing_path(),
                        help="pressure protocol: whole held-out runs (seeds unused in training) at fixed pressures, "
                             "nominal among them, grouped by their front TPMS pressure; needs --tpms-model")
    parser.add_argument("--pressure-train", nargs="+", default=[], metavar="PATH", type=t.existing_path(),
                        help="the TPMS model's training runs: the trail correction by pressure of the pressure-free "
                             "model is fitted on them and scored in the pressure protocol too")
    parser.add_argument("--json", required=True, metavar="FILE", type=t.output_file(), help="write the results here")
    parser.add_argument("--markdown", metavar="FILE", type=t.output_file(),
                        help="also write the Table IV comparison as Markdown")
    parser.add_argument("--seed", type=t.seed(), default=0,
                        help="seed of the splits and initialisations (0 to 2**32-1)")
    parser.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    from virtsensor import signals as cat
    from virtsensor.errors import UserError
    from virtsensor.features import SPECS, FeatureSpec
    from virtsensor.fileio import dumps, write_texts
    from virtsensor.learning.dataset import (
        build_dataset,
        check_disjoint,
        load_runs,
        refuse_trained_on,
        split_track_laps,
    )
    from virtsensor.learning.evaluation import evaluate, held_out_runs, markdown_table
    from virtsensor.learning.gripscore import score_grip
    from virtsensor.learning.scoring import envelope_split
    from virtsensor.learning.training import RECIPES, same_recipe
    from virtsensor.metrics import metrics
    from virtsensor.model.onnx import OnnxModel

    if bool(args.pressure_runs) != bool(args.tpms_model) or (args.pressure_train and not args.pressure_runs):
        raise UserError("--pressure-runs and --tpms-model go together (--pressure-train needs both)")
    model = OnnxModel.load(args.model)
    card = model.card
    recipe = card.get("recipe")
    if not recipe or recipe.get("features") not in SPECS:
        raise UserError(f"{args.model}: its card has no recipe this version can retrain")
    pressure = _pressure_inputs(model, args) if args.pressure_runs else None  # checked before any work
    recipes = {"paper": RECIPES["paper"]}
    recipes["improved"] = RECIPES["improved"] if same_recipe(recipe, RECIPES["paper"]) else recipe
    needed = {s for r in recipes.values() for s in SPECS[r["features"]].signals} | set(cat.OUTPUTS)
    runs = load_runs(args.data, needed=sorted(needed))
    track = load_runs([args.track], needed=sorted(needed))[0] if args.track else None
    extra = {"improved": load_runs(args.train_extra, needed=sorted(needed))} if args.train_extra else None
    circuits = load_runs(args.circuits, needed=sorted(needed)) if args.circuits else []
    check_disjoint([("--data", runs), ("--train-extra", extra["improved"] if extra else []),
                    ("--track", [track] if track is not None else []), ("--circuits", circuits)],
                   "a run plays one part: the held-out runs, laps and circuits are never trained on")
    refuse_trained_on(card, [("--track", [track] if track is not None else []), ("--circuits", circuits)],
                      str(args.model), "its rows on the track's laps and the circuits are for runs it never saw")

    def log(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr)

    from threadpoolctl import threadpool_limits

    with warnings.catch_warnings(), threadpool_limits(1):
        warnings.simplefilter("ignore")
        result = evaluate(runs, track, recipes, circuits=circuits, seed=args.seed, train_extra=extra, log=log)
    held = held_out_runs(split_track_laps(track) if track is not None else {}, circuits)
    if held:
        spec = FeatureSpec.from_json(card["feature_spec"])
        env = card.envelope
        shipped = {}
        for key, r in held.items():
            ds = build_dataset([r], spec)
            P = model.predict(ds.X)
            shipped[key] = metrics(ds.Y, P)
            shipped[key]["envelope"] = envelope_split(
                ds.Y, P, None if env is None else env.outside_rows(ds.X, ds.feature_names))
        result["shipped_model"] = {"file": str(args.model), "sha256": card["sha256"], **shipped}
    # the grip margin of the shipped model's SATs: on the runs it never trained on (the track's laps and the
    # circuits; refused above where its card lists one), and apart on --data, which it was likely trained on
    result["grip"] = score_grip(model, [*([track] if track is not None else []), *circuits])
    result["grip_data"] = score_grip(model, runs)
    if pressure is not None:
        result["pressure_protocol"] = _pressure(model, *pressure)
    table = markdown_table(result)
    if args.pressure_runs:
        from virtsensor.learning.pressure import pressure_markdown

        table += "\n" + pressure_markdown(result["pressure_protocol"])
    write_texts((args.json, dumps(result) + "\n"), (args.markdown, table))  # (both or neither)
    print(table)
    return 0


def _pressure_inputs(model, args):
    """``(TPMS model, its feature spec, --pressure-train runs, --pressure-runs runs)``, each checked
    (:func:`virtsensor.learning.pressure.check_models`: a model without tyre pressures is refused)."""
    from virtsensor import signals as cat
    from virtsensor.learning.dataset import check_disjoint, load_runs
    from virtsensor.learning.pressure import check_models
    from virtsensor.model.onnx import OnnxModel

    tpms = OnnxModel.load(args.tpms_model)
    spec = check_models(model, tpms)
    needed = sorted({*spec.signals, *cat.OUTPUTS})
    train = load_runs(args.pressure_train, needed=needed) if args.pressure_train else []
    held = load_runs(args.pressure_runs, needed=needed)
    check_disjoint([("--pressure-train", train), ("--pressure-runs", held)],
                   "the pressure protocol's held-out runs are never fitted on")
    return tpms, spec, train, held


def _pressure(model, tpms, spec, train, held):
    """The pressure protocol: --model (pressure-free) and --tpms-model on --pressure-runs, with the trail
    correction fitted on --pressure-train when given."""
    from virtsensor.learning.pressure import fit_trail_correction, pressure_protocol

    coef = fit_trail_correction(model, train, spec) if train else None
    return pressure_protocol(model, tpms, held, coef)
