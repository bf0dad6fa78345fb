"""``virtsensor campaign``: simulate a data-set preset in parallel into a directory."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from virtsensor.commands._simargs import add_car_arguments, car_from_args, sim_errors
from virtsensor.errors import UserError
from virtsensor.interrupt import sigterm_interrupts
from virtsensor.recordings.files import WRITE_FORMATS as FORMATS

HELP = "simulate a whole data-set preset (e.g. the paper's Table I campaign) in parallel"
#: joblib backends the campaign may run on (ray and dask register themselves when installed).
BACKENDS = ("loky", "threading", "multiprocessing", "sequential", "ray", "dask")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from virtsensor.commands import _types as t

    parser.add_argument("preset", metavar="PRESET",
                        help="paper (Table I, ~45,000 samples), wide (90 runs, ~21,000 samples), smoke (20 runs), "
                             "tiny (4 runs) or circuits (32 laps of random circuits)")
    parser.add_argument("--out", required=True, metavar="DIR", type=t.output_dir(empty=True),
                        help="output directory (created; must be empty); its manifest.json is written last")
    parser.add_argument("--format", choices=FORMATS, default="csv", help="file format of each run (default csv)")
    parser.add_argument("--seed", type=t.seed(), default=0,
                        help="campaign seed, 0 to 2**32-1 (every run's seed derives from it)")
    parser.add_argument("--jobs", type=t.jobs(), default=-1, metavar="N",
                        help="parallel workers (1 to 1024, or -1: all cores, the default)")
    parser.add_argument("--batch-size", type=t.int_range(1, 10000), default=25, metavar="N",
                        help="runs per vectorised batch (1 to 10000; default 25)")
    parser.add_argument("--backend", default=None, choices=BACKENDS,
                        help="joblib backend (default loky; ray and dask need their packages)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--car-pressures", action="store_true",
                        help="no pressure draw: every run keeps the car's own tyre pressures (parameter file, --set); "
                             "default: each run's four pressures drawn around nominal (--pressure-bar forces one)")
    add_car_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from sim.campaign import PRESETS, draw_pressures, outcome_tally
    from virtsensor.recordings.campaign import write_campaign

    if args.preset not in PRESETS:
        raise UserError(f"unknown preset {args.preset!r}; choose one of: {', '.join(PRESETS)}")
    if args.batch_size < 1:
        raise UserError(f"--batch-size must be >= 1, got {args.batch_size}")
    params = car_from_args(args)
    requests = PRESETS[args.preset](args.seed)
    if args.car_pressures and args.pressure_bar is not None:
        raise UserError("--car-pressures and --pressure-bar exclude each other")
    drawn = args.pressure_bar is None and not args.car_pressures
    if drawn:  # each run's four tyres at their own pressures (--pressure-bar: one for all)
        requests = draw_pressures(requests, args.seed)
    info = {"preset": args.preset, "seed": args.seed, "overrides": args.overrides,
            "param_files": args.param_files, "pressure_bar": args.pressure_bar,
            "pressures": "drawn per run" if drawn else "forced" if args.pressure_bar is not None else "the car's"}
    with sim_errors(), sigterm_interrupts():
        manifest = write_campaign(requests, params, Path(args.out), fmt=args.format, info=info, n_jobs=args.jobs,
                                  batch_size=args.batch_size, backend=args.backend, progress=not args.quiet)
    runs, samples, simulated, wall = len(manifest["runs"]), manifest["samples"], manifest["simulated_s"], \
        manifest["wall_s"]
    tally = outcome_tally(e["outcome"] for e in manifest["runs"])
    print(f"{args.preset}: {runs} runs ({tally}), {samples} samples at 20 Hz, {simulated:.0f} s simulated "
          f"in {wall:.1f} s wall (real-time factor {simulated / wall:.0f}) -> {args.out}", file=sys.stderr)
    return 0
