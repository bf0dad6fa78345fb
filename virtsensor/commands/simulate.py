"""``virtsensor simulate``: one manoeuvre, written as a 20 Hz table or a CAN log."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from virtsensor.commands._simargs import add_car_arguments, car_from_args, sim_errors
from virtsensor.errors import UserError
from virtsensor.fileio import dumps, staged_files
from virtsensor.recordings.files import LOG_SUFFIXES, TABLE_SUFFIXES
from virtsensor.recordings.simulated import check_usable, metadata_entry, metadata_path, run_table, write_run_file

HELP = f"simulate a manoeuvre and write a 20 Hz table (.csv) or a CAN log ({'/'.join(LOG_SUFFIXES)})"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from sim.params import MU_RANGE
    from virtsensor.commands import _types as t

    parser.add_argument("manoeuvre", metavar="MANOEUVRE",
                        help="free-steer, steering-pulse, double-lane-change, steady-state-circular, "
                             "single-sine, random-steer, braking-in-turn, fishhook, sine-with-dwell, "
                             "brake-accel, magny-cours, circuit (with --track), or recorded (with --inputs)")
    parser.add_argument("--speed", type=t.positive_float(500.0), metavar="KMH",
                        help="entry speed in km/h, > 0 (the manoeuvre sets the limit; magny-cours, circuit: "
                             "top speed); not with 'recorded'")
    parser.add_argument("--mu", type=t.float_range(*MU_RANGE), required=True,
                        help=f"road friction coefficient, {MU_RANGE[0]:g} to {MU_RANGE[1]:g} (magny-cours: dry lap)")
    parser.add_argument("--seed", type=t.seed(), default=0,
                        help="seed of the manoeuvre's levels and the sensor noise (0 to 2**32-1)")
    parser.add_argument("--out", required=True, metavar="FILE",
                        type=t.output_file(*TABLE_SUFFIXES, *LOG_SUFFIXES, companions=lambda p: [metadata_path(p)]),
                        help=f"output: .csv table or {'/'.join(LOG_SUFFIXES)} CAN log (its metadata "
                             "<stem>.json beside it)")
    parser.add_argument("--inputs", metavar="FILE", type=t.existing_file(),
                        help="for MANOEUVRE 'recorded': a table (.csv) or CAN log whose steering-wheel angle and "
                             "speed (or motor torque) drive the re-simulation")
    parser.add_argument("--longitudinal", choices=("speed", "torque"), default=None,
                        help="for 'recorded' only: follow the recorded speed (default) or apply the recorded "
                             "motor torque")
    parser.add_argument("--track", metavar="FILE", type=t.track_spec(),
                        help="for 'circuit': a bundled circuit (magny-cours, hungaroring, zandvoort, red-bull-ring), "
                             "a random one (random:SEED), or a closed centreline, .csv with header x_m,y_m or "
                             ".geojson LineString of lon/lat")
    parser.add_argument("--laps", type=t.positive_int(100), default=None, metavar="N",
                        help="for 'circuit': laps to drive, 1 to 100 (default 1)")
    add_car_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from sim.api import simulate
    from sim.manoeuvres import check

    out = Path(args.out)
    suffix = out.suffix.lower()
    if suffix not in TABLE_SUFFIXES + LOG_SUFFIXES:
        raise UserError(f"--out {out}: unknown format {suffix or '(none)'}; "
                        f"use one of {', '.join(TABLE_SUFFIXES + LOG_SUFFIXES)}")
    if not out.parent.exists():
        raise UserError(f"--out {out}: directory {out.parent} does not exist")
    _check_metadata_free(out)
    if args.manoeuvre == "recorded":
        sim_run = _resimulate(args)
    else:
        from sim.manoeuvres import MANOEUVRES

        if args.manoeuvre not in MANOEUVRES:  # (before what the manoeuvre would need)
            raise UserError(f"unknown manoeuvre {args.manoeuvre!r}; choose one of: {', '.join(MANOEUVRES)}, "
                            "recorded")
        if args.speed is None:
            raise UserError(f"{args.manoeuvre}: --speed KMH is required")
        if args.inputs is not None or args.longitudinal is not None:
            raise UserError(f"{'--inputs' if args.inputs is not None else '--longitudinal'} goes with the "
                            "manoeuvre 'recorded' only")
        if args.manoeuvre != "circuit" and (args.track is not None or args.laps is not None):
            raise UserError("--track and --laps go with the manoeuvre 'circuit' only")
        with sim_errors():
            check(args.manoeuvre, args.speed, args.mu)
        params = car_from_args(args)
        with sim_errors():
            sim_run = simulate(args.manoeuvre, args.speed, args.mu, args.seed, params,
                               track=args.track, laps=args.laps)
    what = f"recorded (inputs {args.inputs})" if args.manoeuvre == "recorded" else args.manoeuvre
    table = run_table(sim_run)
    check_usable(sim_run, table, what)  # a run that ends early but long enough is written, and says so below
    with staged_files(out, metadata_path(out)) as (run_tmp, meta_tmp):  # the run and its metadata, both or neither
        write_run_file(sim_run, run_tmp, table)
        meta_tmp.write_text(dumps(metadata_entry(sim_run, out, table)) + "\n", encoding="utf-8")
    n = len(table["time_s"])
    speed = f"{args.speed:g} km/h" if args.speed is not None else f"recorded inputs of {args.inputs}"
    print(f"{args.manoeuvre} at {speed}, mu {args.mu:g}: {n} samples at 20 Hz "
          f"({table['time_s'][-1]:.2f} s), {_outcome_text(sim_run.outcome)} -> {out}", file=sys.stderr)
    return 0


def _check_metadata_free(out: Path) -> None:
    """Refuse an ``out`` whose metadata file (``<stem>.json``) describes another recording (``x.blf`` beside
    ``x.csv``): writing it would leave that recording with this run's metadata."""
    from virtsensor.recordings.sidecar import read_json_object

    meta = metadata_path(out)
    doc = read_json_object(meta)
    if doc is None:
        return  # (none, or not a run's metadata: the output checks already decided on it)
    other = doc.get("file")
    name = Path(other).name if isinstance(other, str) else ""
    if name not in ("", ".", "..", out.name) and (meta.parent / name).is_file():
        raise UserError(f"--out {out}: {meta} is the metadata of another recording, {name}; "
                        f"writing this run would replace it (give --out another name)")


def _outcome_text(outcome: dict) -> str:
    """How the run ended, for the summary line; with the distance driven along the path when planned."""
    status = outcome.get("status", "completed")
    driven, planned = outcome.get("driven_m"), outcome.get("planned_m")
    distance = f"{driven:.0f} m of {planned:.0f} m driven" if driven is not None and planned else ""
    if status == "behind-plan":
        return (f"BEHIND PLAN: {distance} ({100.0 * driven / planned:.1f} %) when the planned "
                f"{outcome['planned_s']:.1f} s ran out")
    if status == "completed":
        return f"completed ({distance})" if distance else "completed"
    return (f"{status.upper()} at t={outcome['at_s']:.2f} s of {outcome['planned_s']:.2f} s planned"
            f"{', ' + distance if distance else ''} (run cut short)")


def _resimulate(args: argparse.Namespace):
    """Re-simulate a recorded run from its driver inputs (``simulate recorded``)."""
    from sim.api import simulate_plan
    from sim.manoeuvres import from_recording
    from sim.params import MU_RANGE
    from virtsensor.learning.dataset import load_runs

    if args.inputs is None:
        raise UserError("recorded: --inputs FILE is required (a .csv table or a CAN log)")
    if args.speed is not None:
        raise UserError("recorded: the speed comes from --inputs; drop --speed")
    if args.track is not None or args.laps is not None:
        raise UserError("--track and --laps go with the manoeuvre 'circuit' only")
    if not MU_RANGE[0] <= args.mu <= MU_RANGE[1]:
        raise UserError(f"mu {args.mu:g} is outside the range {MU_RANGE[0]:g}-{MU_RANGE[1]:g}")
    longitudinal = args.longitudinal or "speed"
    needed = ["steer_angle_rad", "vx_mps" if longitudinal == "speed" else "motor_torque_nm"]
    table = load_runs([args.inputs], needed=needed)[0].table
    params = car_from_args(args)
    with sim_errors():
        plan = from_recording(table, args.mu, longitudinal=longitudinal)
        return simulate_plan(plan, params, args.seed)
