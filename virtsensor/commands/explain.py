"""``virtsensor explain``: the paper's Section IV.B figures for a shipped model.

Correlation of the inputs (Fig. 2), global SHAP importance (Fig. 8) and SHAP
dependence (Fig. 9) of the ONNX model on the test rows of the paper's random
70/30 split, and, with ``--track``, the Magny-Cours laps (Figs. 5-7). See
:mod:`virtsensor.learning.explain` for what is computed and why.

Example::

    virtsensor explain --model models/paper.onnx --data data/paper --track data/track.csv --out figures/
"""

from __future__ import annotations

import argparse
import sys

HELP = "Section IV.B figures: input correlation, SHAP importance/dependence, track laps"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from virtsensor.assets import model_path
    from virtsensor.commands import _types as t

    parser.add_argument("--model", metavar="FILE.onnx", default=None,
                        type=t.existing_file(".onnx", implicit=model_path),
                        help="the model (its card beside it names the features; default: the shipped improved "
                             "model)")
    parser.add_argument("--data", nargs="+", required=True, metavar="PATH", type=t.existing_path(),
                        help="recordings (files or directories), as for train")
    parser.add_argument("--track", metavar="FILE", type=t.existing_file(),
                        help="Magny-Cours recording (dry lap then wet lap): adds Figs. 5, 6 and 7")
    parser.add_argument("--circuits", nargs="+", default=[], metavar="FILE", type=t.existing_file(),
                        help="recordings of circuits the model never saw: one estimate-vs-truth figure each "
                             "(circuit_<file stem>.png), out-of-envelope stretches shaded")
    parser.add_argument("--out", required=True, metavar="DIR", type=t.output_dir(),
                        help="output directory for the PNGs and explain.json")
    parser.add_argument("--seed", type=t.seed(), default=0,
                        help="seed of the 70/30 split, of the explained and background rows and of the permutations "
                             "(0 to 2**32-1)")
    parser.add_argument("--samples", type=t.int_range(1, 100000), default=500, metavar="N",
                        help="test rows to explain (1 to 100000; default 500)")
    parser.add_argument("--background", type=t.int_range(1, 10000), default=100, metavar="N",
                        help="background rows of the independent masker (1 to 10000; default 100)")
    parser.add_argument("--method", choices=("auto", "exact", "permutation"), default="auto",
                        help="SHAP explainer: exact Shapley values when affordable (auto, default), "
                             "or force exact / permutation sampling")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def run(args: argparse.Namespace) -> int:
    from virtsensor.assets import model_path
    from virtsensor.learning.explain import explain

    def log(msg: str) -> None:
        if not args.quiet:
            print(msg, file=sys.stderr)

    model = model_path() if args.model is None else args.model
    doc = explain(model, args.data, args.out, track=args.track, circuits=args.circuits, seed=args.seed,
                  samples=args.samples, background=args.background, method=args.method, log=log)
    fl = doc["model"]["outputs"][0]
    print(f"{fl}: " + ", ".join(doc["ranking"][fl][:3]) + f"  ({len(doc['figures'])} figures in {args.out})")
    return 0
