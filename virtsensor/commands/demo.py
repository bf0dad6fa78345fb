"""``virtsensor demo``: the daemon on a bundled wet-road manoeuvre, estimated against true SAT, live.

Examples::

    virtsensor demo                                   # bundled run, real time, plot in figures/demo.png
    virtsensor demo --rate 20 --no-live --json demo.json
    virtsensor demo --recording dlc.blf --model models/paper.onnx --plot dlc.png

Replays a CAN log (default: a random-steer run at 70 km/h on a wet road, mu 0.7, bundled under
``sim/data/recordings/``) onto python-can's in-process virtual bus, runs the real daemon on it in sync mode,
and compares its ``SAT_FRONT`` with the wheel-force-transducer reference of the same log. See
:mod:`virtsensor.demo`.
"""

from __future__ import annotations

import argparse

HELP = "the daemon on a bundled wet-road manoeuvre: estimated vs true SAT live, MAE, R2, latency, plot"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from virtsensor.commands import _types as t
    from virtsensor.demo import DEFAULT_PLOT, default_model, default_recording, limit_plot_path

    parser.add_argument("--model", metavar="FILE.onnx", default=None,
                        type=t.existing_file(".onnx", implicit=default_model),
                        help="ONNX model, its .card.json beside it (default: the shipped models/improved.onnx)")
    parser.add_argument("--recording", metavar="LOG", default=None,
                        type=t.existing_file(what="log file", implicit=default_recording),
                        help="CAN log to replay (.blf, .asc, .log, .csv, .trc; default: the bundled wet-road run)")
    parser.add_argument("--rate", default="1.0", type=t.rate(),
                        help="replay speed factor, 0.001 to 1000 (1.0 = real time, the default), or 'max' "
                             "(as fast as possible)")
    parser.add_argument("--no-live", dest="live", action="store_false",
                        help="no line per half second during the run, only the closing figures")
    parser.add_argument("--plot", metavar="FILE.png", default=None,
                        type=t.output_file(".png", mkdirs=True, companions=lambda p: [limit_plot_path(p)]),
                        help=f"PNG of estimated vs true SAT and the error (needs matplotlib, the 'plots' extra: "
                             f"refused without it; default {DEFAULT_PLOT}, skipped with a note without it); "
                             "on the bundled defaults the limit run's beside it, <name>_limit.png")
    parser.add_argument("--json", dest="json_path", metavar="FILE", default=None, type=t.output_file(),
                        help="write the figures as JSON")


def run(args: argparse.Namespace) -> int:
    from virtsensor import plotting
    from virtsensor.demo import DEFAULT_PLOT, run_demo

    if args.plot is not None:  # (a plot asked for is drawn or refused; the default one is skipped with a note)
        plotting.require("--plot")
    result = run_demo(model=args.model, recording=args.recording, rate=args.rate, live=args.live,
                      plot=DEFAULT_PLOT if args.plot is None else args.plot, json_path=args.json_path,
                      plot_optional=args.plot is None)
    return 130 if result["interrupted"] else 0
