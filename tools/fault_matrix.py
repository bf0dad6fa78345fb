"""Single-sensor faults against the daemon's VALID: which faults still let it publish VALID with a large error.

For each manoeuvre, the car is simulated clean and then with one sensor fault at a time (``sensor_errors``:
an offset, a gain or a delay on one of the 12 inputs; the car itself drives the same, only what its sensor
reports changes), its CAN log replayed through the daemon as ``virtsensor demo`` does (the shipped model,
sync mode, as fast as possible). Per run: the share of ticks the daemon marks VALID and the MAE (Nm, mean of
the two wheels) over those ticks. A *hole* is a fault that leaves VALID on more than half the ticks while the
MAE on them is above twice the clean run's, or above 5 Nm.

    python tools/fault_matrix.py --out docs/fault_matrix.md [--json fm.json] [--manoeuvres rs dlc bit]

About 5 s per run on one core (67 runs per manoeuvre, 17 min in all).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

#: the manoeuvres: straight and turning, a lane change on a wet road, braking in a turn
MANOEUVRES = {"rs": ("random-steer", 70.0, 1.0, 5), "dlc": ("double-lane-change", 80.0, 0.7, 5),
              "bit": ("braking-in-turn", 80.0, 1.0, 5)}
#: offsets per input (gross: a third to a half of the signal's use in these manoeuvres)
OFFSETS = {"ax_mps2": (3.0, -3.0), "ay_mps2": (3.0,), "vx_mps": (7.0, -7.0), "yaw_rate_radps": (0.2,),
           "steer_angle_rad": (0.3, 0.6), "steer_torque_nm": (2.0,), "assist_torque_nm": (4.0,),
           "motor_torque_nm": (100.0, -100.0), "susp_defl_fl_m": (0.02,), "susp_defl_fr_m": (0.02,),
           "wheel_speed_fl_radps": (20.0, -20.0), "wheel_speed_fr_radps": (20.0, -20.0)}
GAINS = (0.01, 0.5, 2.0)
DELAY_S = 0.3


def faults() -> list[tuple[str, str, float] | None]:
    """None (the clean run), then ``(signal, field, value)`` per fault."""
    out: list[tuple[str, str, float] | None] = [None]
    for sig, offs in OFFSETS.items():
        out += [(sig, "offset", o) for o in offs] + [(sig, "gain", g) for g in GAINS] + [(sig, "delay_s", DELAY_S)]
    return out


def one_run(key: str, fault: tuple[str, str, float] | None, work: Path) -> dict[str, Any]:
    """Simulate ``key`` with ``fault``, replay it through the daemon; the VALID share and MAE on VALID ticks."""
    from sim.api import simulate
    from sim.params import car_parameters
    from virtsensor.demo import run_demo
    from virtsensor.recordings.simulated import run_table, write_metadata, write_run

    m, v, mu, seed = MANOEUVRES[key]
    overrides = [] if fault is None else [f"sensor_errors.{fault[0]}.{fault[1]}={fault[2]}"]
    run = simulate(m, v, mu, seed, car_parameters(overrides))
    log = work / "run.blf"
    table = run_table(run)
    write_run(run, log, table)
    write_metadata(run, log, table)
    with contextlib.redirect_stderr(io.StringIO()):  # (the daemon's JSON log lines: implausible, envelope...)
        res = run_demo(recording=log, rate="max", live=False, plot=None, json_path=None, out=io.StringIO())
    w = [res["metrics"][k] for k in ("fl", "fr")] if res.get("metrics") else []
    maes = [x["mae_valid_nm"] for x in w if x["mae_valid_nm"] is not None]
    return {"manoeuvre": key, "fault": None if fault is None else f"{fault[0]} {fault[1]}={fault[2]:g}",
            "valid_share": round(sum(x["valid_share"] for x in w) / len(w), 3) if w else 0.0,
            "mae_valid_nm": round(sum(maes) / len(maes), 2) if len(maes) == 2 else None}


def is_hole(row: dict[str, Any], clean_mae: float) -> bool:
    mae = row["mae_valid_nm"]
    return (row["fault"] is not None and row["valid_share"] > 0.5 and mae is not None
            and (mae > 2.0 * clean_mae or mae > 5.0))


def markdown(rows: list[dict[str, Any]]) -> str:
    clean = {r["manoeuvre"]: r["mae_valid_nm"] for r in rows if r["fault"] is None}
    holes = [r for r in rows if is_hole(r, clean[r["manoeuvre"]])]
    lines = ["Single-sensor faults against VALID: `python tools/fault_matrix.py --out docs/fault_matrix.md`", "",
             f"{len(holes)} holes in {sum(r['fault'] is not None for r in rows)} faulted runs (VALID on more than "
             "half the ticks, MAE on them above twice the clean run's or above 5 Nm). Manoeuvres: "
             + ", ".join(f"{k} = {m} {v:g} km/h mu {mu:g} seed {s}" for k, (m, v, mu, s) in MANOEUVRES.items()
                         if k in clean) + ".", "",
             "| manoeuvre | fault | VALID share | MAE on VALID (Nm) | clean MAE (Nm) | hole |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        mae = "—" if r["mae_valid_nm"] is None else f"{r['mae_valid_nm']:.2f}"
        lines.append(f"| {r['manoeuvre']} | {r['fault'] or 'clean'} | {r['valid_share']:.2f} | {mae} | "
                     f"{clean[r['manoeuvre']]:.2f} | {'HOLE' if is_hole(r, clean[r['manoeuvre']]) else ''} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, help="Markdown table to write")
    ap.add_argument("--json", help="also the rows as JSON")
    ap.add_argument("--manoeuvres", nargs="+", choices=sorted(MANOEUVRES), default=list(MANOEUVRES))
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for key in args.manoeuvres:
            for fault in faults():
                rows.append(one_run(key, fault, Path(tmp)))
                print(json.dumps(rows[-1]), flush=True)
    if any(r["fault"] is None and (r["mae_valid_nm"] is None or not math.isfinite(r["mae_valid_nm"]))
           for r in rows):
        print("a clean run has no VALID tick: nothing to compare with", file=sys.stderr)
        return 1
    Path(args.out).write_text(markdown(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
