"""``virtsensor campaign``: simulate a data-set preset in parallel into a directory."""

from __future__ import annotations

import argparse
import json
import sys
import time
from functools import partial
from pathlib import Path

from virtsensor.commands._simargs import add_car_arguments, car_from_args, sim_errors
from virtsensor.errors import UserError

HELP = "simulate a whole data-set preset (e.g. the paper's Table I campaign) in parallel"
FORMATS = ("csv", "blf", "asc", "log")
#: joblib backends the campaign may run on (ray and dask register themselves when installed).
BACKENDS = ("loky", "threading", "multiprocessing", "sequential", "ray", "dask")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from virtsensor.commands import _types as t

    parser.add_argument("preset", metavar="PRESET",
                        help="paper (Table I, ~45,000 samples), smoke (20 runs) or tiny (4 runs)")
    parser.add_argument("--out", required=True, metavar="DIR", type=t.output_dir(empty=True),
                        help="output directory (created; must be empty)")
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
    add_car_arguments(parser)


def _write(run, out_dir: Path, fmt: str) -> dict:
    from sim.campaign import manifest_entry
    from virtsensor.commands.simulate import write_run

    r = run.request
    name = f"{r.manoeuvre}_{r.speed_kmh:g}kmh_mu{r.mu:g}_{r.seed}.{fmt}"
    path = out_dir / name
    table = write_run(run, path)
    t = table["time_s"]
    return manifest_entry(run, path, samples=len(t), duration_s=float(t[-1] - t[0]) if len(t) else 0.0)


def run(args: argparse.Namespace) -> int:
    from sim.campaign import PRESETS, run_campaign

    if args.preset not in PRESETS:
        raise UserError(f"unknown preset {args.preset!r}; choose one of: {', '.join(PRESETS)}")
    if args.batch_size < 1:
        raise UserError(f"--batch-size must be >= 1, got {args.batch_size}")
    out_dir = Path(args.out)
    if out_dir.exists() and any(out_dir.iterdir()):
        raise UserError(f"--out {out_dir}: directory is not empty (refusing to mix campaigns)")
    params = car_from_args(args)
    requests = PRESETS[args.preset](args.seed)
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with sim_errors():
        entries = run_campaign(requests, params, n_jobs=args.jobs, batch_size=args.batch_size,
                               writer=partial(_write, out_dir=out_dir, fmt=args.format),
                               progress=not args.quiet, backend=args.backend)
    wall = time.perf_counter() - t0
    samples = sum(e["samples"] for e in entries)
    simulated = sum(e["duration_s"] for e in entries)
    manifest = {
        "preset": args.preset, "seed": args.seed, "format": args.format, "runs": entries,
        "samples": samples, "simulated_s": simulated, "wall_s": wall,
        "overrides": args.overrides, "param_files": args.param_files, "pressure_bar": args.pressure_bar,
    }
    (out_dir / "manifest.json").write_text(json.dumps(manifest, indent=1))
    print(f"{args.preset}: {len(entries)} runs, {samples} samples at 20 Hz, {simulated:.0f} s simulated "
          f"in {wall:.1f} s wall (real-time factor {simulated / wall:.0f}) -> {out_dir}", file=sys.stderr)
    return 0
