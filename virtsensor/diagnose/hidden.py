"""Hidden-effect cases: "measured" runs of a car with one effect the diagnosis must find.

A case is a test day on a dry proving ground: a diagnosis programme (a random
steer for the transients, a sine with dwell to the grip limit, a double lane
change at speed) and a held-out programme of other manoeuvres for measuring the
estimator's gain. The car has one effect of :mod:`sim.effects`, drawn at random
(seeded) at a realistic magnitude, or none (a control). Runs are written as the
test vehicle would record them (the 12 inputs and the reference SATs, through
the CAN path), under neutral names; what was hidden is returned to the caller
and never written next to the runs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.effects import CAUSES, Hidden, draw_hidden, with_effect
from sim.params import car_parameters
from virtsensor import signals as cat

#: (manoeuvre, speed km/h): used for the diagnosis and the calibration
DIAGNOSIS_PROGRAMME: tuple[tuple[str, float], ...] = (
    ("random-steer", 70.0), ("sine-with-dwell", 80.0), ("double-lane-change", 100.0))
#: (manoeuvre, speed km/h): held out, only for measuring the estimator's gain
HOLDOUT_PROGRAMME: tuple[tuple[str, float], ...] = (
    ("single-sine", 70.0), ("random-steer", 60.0), ("fishhook", 70.0))
#: the proving ground's friction (the diagnosis is told the track, not the car)
TRACK_MU = 1.0


@dataclass
class Case:
    """A generated case: what was hidden (None: control) and the files written."""

    hidden: Hidden | None
    diagnosis: list[Path]
    holdout: list[Path]


def make_case(seed: int, out_dir: str | Path, *, control: bool = False, causes: Sequence[str] = CAUSES,
              hidden: Hidden | None = None, suffix: str = ".csv",
              programme: Sequence[tuple[str, float]] = DIAGNOSIS_PROGRAMME,
              holdout: Sequence[tuple[str, float]] = HOLDOUT_PROGRAMME) -> Case:
    """Simulate a case's runs into ``out_dir`` (``run01``, ``run02``... in ``suffix`` format).

    Args:
        seed: draws the effect, its size and the manoeuvres' randomness.
        control: no effect at all.
        causes: the causes to draw from.
        hidden: a given effect instead of a random one.
    """
    from sim.api import Request, simulate_many
    from virtsensor.recordings.simulated import run_table, write_run

    rng = np.random.default_rng(seed)
    if hidden is None and not control:
        hidden = draw_hidden(rng, tuple(causes))
    params = car_parameters()
    if hidden is not None:
        params = with_effect(params, hidden.cause, hidden.value, hidden.signal)
    seeds = rng.integers(0, 2**31 - 1, size=len(programme) + len(holdout))
    reqs = [Request(m, v, TRACK_MU, int(s)) for (m, v), s in zip((*programme, *holdout), seeds, strict=True)]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    measured = ("time_s", *cat.INPUTS, *cat.OUTPUTS)
    for i, run in enumerate(simulate_many(reqs, params), start=1):
        path = out / f"run{i:02d}{suffix}"
        if suffix == ".csv":
            from virtsensor.recordings.canlog import write_csv

            table = run_table(run)
            write_csv(path, {k: table[k] for k in measured})
        else:
            write_run(run, path)
        files.append(path)
    return Case(hidden, files[:len(programme)], files[len(programme):])
