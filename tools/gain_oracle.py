"""What bounds the held-out gain of a calibration: nominal, oracle and calibrated estimators, per campaign.

For development cases (seeds 900-999, never the study's), each with one hidden effect on a uniform dry day
(:data:`virtsensor.diagnose.hidden.DAY_PROGRAMME`), the held-out SAT MAE (the case's three held-out runs) of

- ``nominal``: the estimator trained on the nominal simulator;
- ``oracle``: trained on the simulator with the TRUE hidden effect (a perfect calibration: what calibration can
  gain at best with this training recipe);
- ``calibrated``: trained on the simulator calibrated with what the diagnosis named (``--no-calibrated``: skip
  the diagnosis);
- ``nominal_seed+1``: the nominal recipe with the next seed (how much the MAE moves with the seed alone);

all with the same recipe, campaign, seed and epochs (like for like), for each campaign given. A sensor
offset or gain of an input is undone at the estimator's input, as :func:`virtsensor.diagnose._estimators`
does. Also: the nominal estimator's MAE on the held-out runs of a control car (nothing hidden), the floor of
the recipe. One JSON line per (campaign, case) on stdout.

    nice -n 15 python tools/gain_oracle.py --campaigns smoke --n-jobs 1
    nice -n 15 python tools/gain_oracle.py --campaigns dry wide --n-jobs 1 --no-seed-spread --named named.json

(``wide`` is the simulator's preset, about 4.5 times the training data of ``smoke``; ``dry`` is defined here.)
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: development cases: (seed, cause, value, signal)
CASES = (
    (901, "tyre_pressure", 1.51, None),
    (902, "steering_friction", 4.35, None),
    (903, "vehicle_mass", 286.0, None),
    (904, "sensor_gain", 1.14, "motor_torque_nm"),
)


def dry_preset(seed: int = 0):
    """Each Table I manoeuvre at two speeds (a third and two thirds of its range) on the dry track only
    (20 runs, the size of ``smoke``): a campaign matched to a dry test day at the same cost."""
    from sim.api import Request
    from sim.campaign import PAPER_MANOEUVRES
    from sim.manoeuvres import MANOEUVRES

    seeds = np.random.SeedSequence(seed).generate_state(2 * len(PAPER_MANOEUVRES))
    out = []
    for i, name in enumerate(PAPER_MANOEUVRES):
        lo, hi = MANOEUVRES[name].speed_kmh
        for j, f in enumerate((1 / 3, 2 / 3)):
            out.append(Request(name, float(round(lo + f * (hi - lo), 1)), 1.0, int(seeds[2 * i + j])))
    return out


def _case(seed: int, cause: str, value: float, signal, tmp: Path, control: bool = False):
    from sim.effects import Hidden
    from virtsensor.diagnose.hidden import DAY_PROGRAMME, make_case
    from virtsensor.recordings.measured import load_measured

    case = make_case(seed, tmp / f"c{seed}{'ctl' if control else ''}", control=control,
                     hidden=None if control else Hidden(cause, value, signal), programme=DAY_PROGRAMME)
    return load_measured(case.diagnosis, skipped=[]), load_measured(case.holdout, skipped=[])


def _named(runs, hold, base, n_jobs: int) -> tuple[list[tuple[str, float, str | None]], float]:
    from virtsensor.diagnose import diagnose

    t0 = time.perf_counter()
    res, _ = diagnose(runs, hold, base, mu=1.0, retrain=False, n_jobs=n_jobs)
    return [(c["cause"], c["estimate"], c["signal"]) for c in res["causes"]], time.perf_counter() - t0


def _estimator(base, effects, nominal, args, preset: str, seed: int):
    """The estimator for ``effects`` (cause, value, signal): input sensor errors undone on ``nominal``'s
    network when they are all there is, else retrained on the simulator with the other effects."""
    from sim.effects import with_effect
    from virtsensor.diagnose import UNDONE_AT_INPUT, calibrate

    at_input = [e for e in effects if e[0] in UNDONE_AT_INPUT]
    phys = [e for e in effects if e[0] not in UNDONE_AT_INPUT]
    est = nominal
    if phys:
        cal = dict(base)
        for c, v, s in phys:
            cal = with_effect(cal, c, v, s)
        est = calibrate.train(cal, preset=preset, seed=seed, n_jobs=args.n_jobs, max_iter=args.max_iter,
                              ensemble=args.ensemble)
    if at_input:
        est = calibrate.undo_sensor_errors(est, [(s, v, 1.0) if c == "sensor_offset" else (s, 0.0, v)
                                                 for c, v, s in at_input])
    return est


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--campaigns", nargs="+", default=["smoke"])
    ap.add_argument("--cases", type=int, nargs="+", help="indices into CASES (default: all)")
    ap.add_argument("--max-iter", type=int, default=300)
    ap.add_argument("--ensemble", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-jobs", type=int, default=1)
    ap.add_argument("--no-calibrated", action="store_true")
    ap.add_argument("--named", type=Path, help="JSON cache of what the diagnosis named per case seed: read if it "
                    "exists, else written")
    ap.add_argument("--save", type=Path, help="pickle each (campaign, case)'s estimators and held-out runs here")
    ap.add_argument("--no-seed-spread", action="store_true", help="skip the nominal estimator of the next seed")
    args = ap.parse_args(argv)

    from sim.campaign import PRESETS
    from sim.params import car_parameters
    from virtsensor.diagnose import calibrate

    PRESETS.setdefault("dry", dry_preset)
    base = car_parameters()
    cases = [CASES[i] for i in (args.cases if args.cases is not None else range(len(CASES)))]
    with tempfile.TemporaryDirectory() as tmp:
        data = {c[0]: _case(*c, Path(tmp)) for c in cases}
        _, ctl_hold = _case(999, "", 0.0, None, Path(tmp), control=True)
        named = {int(k): (v[0], v[1]) for k, v in json.loads(args.named.read_text()).items()} \
            if args.named is not None and args.named.exists() else {}
        for c in cases:
            if c[0] not in named:
                named[c[0]] = ([], 0.0) if args.no_calibrated else _named(*data[c[0]], base, args.n_jobs)
            print(f"case {c}: named {named[c[0]][0]} in {named[c[0]][1]:.0f} s", file=sys.stderr, flush=True)
        if args.named is not None and not args.named.exists():
            args.named.write_text(json.dumps(named))
        for preset in args.campaigns:
            t0 = time.perf_counter()
            nominal = calibrate.train(base, preset=preset, seed=args.seed, n_jobs=args.n_jobs,
                                      max_iter=args.max_iter, ensemble=args.ensemble)
            t_nom = time.perf_counter() - t0
            alt = None if args.no_seed_spread else calibrate.train(
                base, preset=preset, seed=args.seed + 1, n_jobs=args.n_jobs, max_iter=args.max_iter,
                ensemble=args.ensemble)
            floor = calibrate.score(nominal, ctl_hold)["mae_nm"]
            for c in cases:
                hold = data[c[0]][1]
                t1 = time.perf_counter()
                oracle = _estimator(base, [(c[1], c[2], c[3])], nominal, args, preset, args.seed)
                t_or = time.perf_counter() - t1
                ests = {"nominal": nominal, "oracle": oracle} | ({} if alt is None else {"nominal_seed+1": alt})
                if named[c[0]][0]:
                    ests["calibrated"] = _estimator(base, named[c[0]][0], nominal, args, preset, args.seed)
                sc = calibrate.scores(list(ests.values()), hold)
                row = {"campaign": preset, "samples": nominal.samples, "case_seed": c[0], "hidden": list(c[1:]),
                       "named": named[c[0]][0], "seconds_diagnosis": round(named[c[0]][1], 1),
                       "seconds_train": round(t_nom, 1), "seconds_oracle": round(t_or, 1),
                       "mae_floor_control_nm": round(floor, 3),
                       "mae_nm": {k: round(s["mae_nm"], 3) for k, s in zip(ests, sc, strict=True)},
                       "gain": {k: calibrate.paired_gain(nominal, e, hold, seed=args.seed)
                                for k, e in ests.items() if k != "nominal"}}
                print(json.dumps(row), flush=True)
                if args.save is not None:
                    import pickle

                    args.save.mkdir(parents=True, exist_ok=True)
                    with open(args.save / f"{preset}-{c[0]}.pkl", "wb") as fh:
                        pickle.dump({"row": row, "estimators": ests, "holdout": hold}, fh)
    return 0


if __name__ == "__main__":
    sys.exit(main())
