#!/usr/bin/env python3
"""Drive development circuits at a top speed on roads of several frictions; say how each lap went.

Usage::

    python tools/circuit_study.py [--speed 150] [--mu 1.0 0.7 0.5 0.3 0.2]
        [--track hungaroring zandvoort red-bull-ring FILE...] [--json study.json]

One lap per circuit and friction, all in one vectorised batch (``sim.api.simulate_many``).
Per run it prints the outcome (completed, spun / stopped / off-track at t, or behind-plan and
the share of the lap driven when the planned time ran out), the car's
largest distance from the centreline (m), its largest body side-slip (deg) and the 99th
percentile of the front tyres' longitudinal slip (-; above ~0.15 the driven wheels spin
or the brakes lock). Magny-Cours is the report circuit: leave it out of any tuning.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from sim.api import Request, SimRun, simulate_many  # noqa: E402
from sim.params import car_parameters  # noqa: E402


def lap_figures(run: SimRun) -> dict[str, float]:
    """Largest distance across the path (m), largest side-slip (deg), p99 front longitudinal slip (-)."""
    from scipy.spatial import cKDTree

    t, path = run.truth, run.plan.path
    _, j = cKDTree(path).query(np.column_stack([t["x_m"], t["y_m"]]))
    # distance across the path at the nearest vertex (the vertices are 2 m apart: the distance
    # to the vertex itself would read up to 1 m for a car right on the line)
    step = np.diff(path, axis=0)
    heading = np.arctan2(step[:, 1], step[:, 0])[np.minimum(j, len(step) - 1)]
    off = np.abs(-(t["x_m"] - path[j, 0]) * np.sin(heading) + (t["y_m"] - path[j, 1]) * np.cos(heading))
    beta = np.degrees(np.arctan2(t["vy_mps"], np.abs(t["vx_true_mps"])))
    slip = np.maximum(np.abs(t["kappa_fl"]), np.abs(t["kappa_fr"]))
    return {"off_path_max_m": float(off.max()), "sideslip_max_deg": float(np.abs(beta).max()),
            "front_slip_p99": float(np.percentile(slip, 99))}


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--speed", type=float, default=150.0, help="top speed, km/h (default 150)")
    parser.add_argument("--mu", type=float, nargs="+", default=[1.0, 0.7, 0.5, 0.3, 0.2], help="road frictions")
    parser.add_argument("--track", nargs="+", default=["hungaroring", "zandvoort", "red-bull-ring"],
                        help="bundled circuit names or centreline files")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args(argv)
    requests = [Request("circuit", args.speed, mu, 0, track=tr, laps=1) for mu in args.mu for tr in args.track]
    t0 = time.perf_counter()
    runs = simulate_many(requests, car_parameters())
    rows = []
    for run in runs:
        row = {"track": run.request.track, "mu": run.request.mu, **run.outcome, **lap_figures(run)}
        rows.append(row)
        end = "completed" if row["status"] == "completed" else f"{row['status']} at {row['at_s']:.1f} s"
        if row["status"] == "behind-plan":  # the time ran out short of the lap
            end = f"behind-plan, {100 * row['driven_m'] / row['planned_m']:.1f} % of lap"
        print(f"{row['track']:>16s}  mu {row['mu']:.1f}  {end:<22s} of {row['planned_s']:6.1f} s  "
              f"off path <= {row['off_path_max_m']:7.1f} m  side-slip <= {row['sideslip_max_deg']:4.1f} deg  "
              f"front slip p99 {row['front_slip_p99']:.3f}")
    done = sum(r["status"] == "completed" for r in rows)
    print(f"{done}/{len(rows)} laps completed at {args.speed:g} km/h ({time.perf_counter() - t0:.0f} s wall)")
    if args.json:
        args.json.write_text(json.dumps({"speed_kmh": args.speed, "runs": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
