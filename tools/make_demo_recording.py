#!/usr/bin/env python3
"""Regenerate the recordings that ``virtsensor demo`` replays, with the project's own simulator.

    python tools/make_demo_recording.py            # (re)write sim/data/recordings/<run>.blf and its .json
    python tools/make_demo_recording.py --check    # simulate again into a temporary file, compare with the bundled

The runs are ``virtsensor.demo.DEMO_RUN`` and ``DEMO_LIMIT_RUN`` (manoeuvre, speed, road friction, seed; the
second reaches the grip limit); the command each amounts to is printed and stored in the ``.json`` sidecar beside
its log (with the log's sha256, frame count and duration), which the demo reads to describe the run. Same
simulator, same bytes: ``--check`` exits 1 when any differs (e.g. after a change to the simulator), 0 when all match.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

from virtsensor.cli import main as virtsensor_main
from virtsensor.demo import DEMO_LIMIT_RUN, DEMO_RUN, demo_recording_name, recordings_dir

RUNS = (DEMO_RUN, DEMO_LIMIT_RUN)


def simulate(out: Path, run: tuple = DEMO_RUN) -> list[str]:
    name, speed, mu, seed = run
    args = ["simulate", name, "--speed", f"{speed:g}", "--mu", f"{mu:g}", "--seed", str(seed), "--out", str(out)]
    rc = virtsensor_main(args)
    if rc != 0:
        raise SystemExit(f"virtsensor simulate failed (exit {rc})")
    return args


def sidecar(path: Path, args: list[str], run: tuple = DEMO_RUN) -> dict:
    from virtsensor.recordings.canlog import iter_log

    frames = list(iter_log(path))
    name, speed, mu, seed = run
    shown = [*args[:-1], f"sim/data/recordings/{path.name}"]
    return {"manoeuvre": name, "speed_kmh": speed, "mu": mu, "seed": seed,
            "command": "virtsensor " + " ".join(shown),
            "regenerate": "python tools/make_demo_recording.py",
            "frames": len(frames), "duration_s": round(frames[-1].timestamp - frames[0].timestamp, 6),
            "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
            "reference": "TE_WheelForceTransducer (Mz_FL, Mz_FR): the simulated tyres' self-aligning torque"}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare a fresh simulation with each bundled file")
    a = ap.parse_args()
    rc = 0
    for run in RUNS:
        target = recordings_dir() / demo_recording_name(run)
        if a.check:
            with tempfile.TemporaryDirectory() as tmp:
                fresh = Path(tmp) / target.name
                simulate(fresh, run)
                same = target.is_file() and fresh.read_bytes() == target.read_bytes()
            print(f"{target}: {'identical to a fresh simulation' if same else 'DIFFERS from a fresh simulation'}")
            rc = rc if same else 1
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        args = simulate(target, run)
        info = sidecar(target, args, run)
        target.with_suffix(".json").write_text(json.dumps(info, indent=2) + "\n")
        print(f"{info['command']}\n{target}: {info['frames']} frames, {info['duration_s']:g} s, "
              f"sha256 {info['sha256']}")
    return rc


if __name__ == "__main__":
    sys.exit(main())
