"""``virtsensor score``: a shipped model on any recordings, without retraining.

Example::

    virtsensor score --model models/improved.onnx --data my_runs/ --json score.json --markdown score.md
"""

from __future__ import annotations

import argparse
import sys

HELP = "score a shipped model (the ONNX file and its card) on recordings: R2 and MAE per run and overall"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from virtsensor.assets import model_path
    from virtsensor.commands import _types as t

    parser.add_argument("--model", metavar="FILE.onnx", default=None,
                        type=t.existing_file(".onnx", implicit=model_path),
                        help="the model file (its card beside it; default: the shipped improved model)")
    parser.add_argument("--data", nargs="+", required=True, metavar="PATH", type=t.existing_path(),
                        help="recordings: .csv tables or CAN logs (.blf, .asc, .log, .trc), or directories of them; "
                             "each needs the model's inputs and the wheel-force-transducer SATs")
    parser.add_argument("--json", required=True, metavar="FILE", type=t.output_file(), help="write the scores here")
    parser.add_argument("--markdown", metavar="FILE", type=t.output_file(),
                        help="also write them as a Markdown table")


def run(args: argparse.Namespace) -> int:
    from virtsensor.assets import model_path
    from virtsensor.fileio import dumps, write_texts
    from virtsensor.learning.dataset import load_runs
    from virtsensor.learning.gripscore import grip_markdown
    from virtsensor.learning.scoring import markdown, needed_signals, score_runs
    from virtsensor.model.onnx import OnnxModel

    model = OnnxModel.load(model_path() if args.model is None else args.model)
    runs = load_runs(args.data, needed=needed_signals(model.card))
    result = score_runs(model, runs)
    table = markdown(result)
    write_texts((args.json, dumps(result) + "\n"), (args.markdown, table))  # (both or neither)
    o = result["overall"]
    print(f"{len(runs)} run(s), {o['n']} samples: R2 {o['r2']:.3f}, MAE {o['mae_nm']:.2f} Nm "
          f"(mean of both front wheels) -> {args.json}", file=sys.stderr)
    if o.get("pressure_unknown_rows"):
        print(f"{o['pressure_unknown_rows']} sample(s) without a known front tyre pressure (no TPMS or a sensor "
              f"missing; not taken as nominal): scored with the pressure-free fallback {o['fallback']['file']}",
              file=sys.stderr)
    if o.get("runs_trained_on"):
        print(f"{o['runs_trained_on']} of these runs the model was trained on (its card lists them; \"trained_on\" in "
              f"{args.json}): in-sample, not a test of it", file=sys.stderr)
    if o.get("grip") is not None:
        print(grip_markdown({"overall": o["grip"]}).strip(), file=sys.stderr)
    return 0
