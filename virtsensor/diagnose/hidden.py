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
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.effects import CAUSES, Hidden, draw_hidden, with_effect
from sim.params import car_parameters
from virtsensor import signals as cat

#: (manoeuvre, speed km/h): used for the diagnosis and the calibration
DIAGNOSIS_PROGRAMME: tuple[tuple[str, float], ...] = (
    ("random-steer", 70.0), ("sine-with-dwell", 80.0), ("double-lane-change", 100.0))
#: a test day of five runs of about 20 s (the README's timing case, the study's days)
DAY_PROGRAMME: tuple[tuple[str, float], ...] = (
    ("random-steer", 50.0), ("random-steer", 65.0), ("random-steer", 80.0), ("sine-with-dwell", 80.0),
    ("double-lane-change", 100.0))
#: (manoeuvre, speed km/h): held out, only for measuring the estimator's gain
HOLDOUT_PROGRAMME: tuple[tuple[str, float], ...] = (
    ("single-sine", 70.0), ("random-steer", 60.0), ("fishhook", 70.0))
#: the proving ground's friction (the diagnosis is told the track, not the car)
TRACK_MU = 1.0
#: surfaces of a mixed-surface day: the range the engineer states for it and the range the true friction of a
#: run on it is drawn from (a wet or polished surface's friction is known only roughly)
SURFACES: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {
    "dry": ((0.85, 1.15), (0.9, 1.1)),
    "wet": ((0.5, 0.85), (0.55, 0.8)),
    "low": ((0.2, 0.5), (0.25, 0.45)),
}


@dataclass(frozen=True)
class Foreign:
    """An effect outside the catalogue of :mod:`sim.effects`: a name and its parameter overrides."""

    name: str
    overrides: tuple[tuple[str, object], ...]

    def as_dict(self) -> dict[str, object]:
        return {"name": self.name, "overrides": dict(self.overrides)}


def draw_foreign(name: str, rng: np.random.Generator) -> Foreign:
    """An out-of-catalogue effect at a random realistic size: ``toe`` (front toe 0.25-0.5 deg per wheel off),
    ``camber`` (front static camber -1.5 to -2.5 deg), ``tyre`` (another tyre on all four wheels, the bundled
    255/55 R20), ``rear_toe`` (rear toe 0.25-0.5 deg per wheel off: a rear axle knocked out of alignment).
    A steering ratio, out of the catalogue at first, is in it (``steering_ratio``)."""
    from sim.params import car_parameters

    car = car_parameters()
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if name == "toe":
        return Foreign(name, (("tyres.toe_in_front_rad",
                               round(car["tyres"]["toe_in_front_rad"] + sign * np.radians(rng.uniform(0.25, 0.5)),
                                     6)),))
    if name == "camber":
        return Foreign(name, (("tyres.static_camber_front_rad", round(-np.radians(rng.uniform(1.5, 2.5)), 6)),))
    if name == "tyre":
        return Foreign(name, (("tyres.file", "tyres/mf61_255_55R20.tir"),))
    if name == "rear_toe":
        return Foreign(name, (("tyres.toe_in_rear_rad",
                               round(car["tyres"]["toe_in_rear_rad"] + sign * np.radians(rng.uniform(0.25, 0.5)),
                                     6)),))
    raise ValueError(f"unknown out-of-catalogue effect {name!r}")


FOREIGN = ("toe", "camber", "tyre", "rear_toe")


@dataclass
class Case:
    """A generated case: what was hidden (``hidden``: the catalogue effects, empty for a control; ``foreign``:
    an out-of-catalogue effect), the files written, the true friction of each diagnosis run and the
    conditions file given with them (None: a uniform day on the proving ground)."""

    hidden: Hidden | None
    diagnosis: list[Path]
    holdout: list[Path]
    effects: list[Hidden] = field(default_factory=list)
    foreign: Foreign | None = None
    mu: list[float] = field(default_factory=list)
    conditions: Path | None = None


def make_case(seed: int, out_dir: str | Path, *, control: bool = False, causes: Sequence[str] = CAUSES,
              hidden: Hidden | Sequence[Hidden] | None = None, suffix: str = ".csv",
              programme: Sequence[tuple[str, float]] = DIAGNOSIS_PROGRAMME,
              holdout: Sequence[tuple[str, float]] = HOLDOUT_PROGRAMME,
              surfaces: Sequence[str] | None = None, foreign: Foreign | None = None,
              conditions: str | Path | None = None) -> Case:
    """Simulate a case's runs into ``out_dir`` (``run01``, ``run02``... in ``suffix`` format).

    Args:
        seed: draws the effect, its size, the runs' friction and the manoeuvres' randomness.
        control: no catalogue effect at all.
        causes: the causes to draw from.
        hidden: given effect(s) instead of a random one.
        surfaces: each diagnosis run's surface (:data:`SURFACES`): its true friction is drawn in the surface's
            range and the surface's stated range is written to ``conditions`` (a CSV, ``file,mu``); None: every
            run on the dry proving ground at :data:`TRACK_MU`, no conditions written.
        foreign: an out-of-catalogue effect added to the car.
        conditions: where the conditions CSV goes (default: ``conditions.csv`` beside ``out_dir``).
    """
    from sim.api import Request, simulate_many
    from sim.params import apply_overrides
    from virtsensor.recordings.simulated import run_table, write_run

    rng = np.random.default_rng(seed)
    if hidden is None and not control:
        hidden = draw_hidden(rng, tuple(causes))
    effects = [] if hidden is None else ([hidden] if isinstance(hidden, Hidden) else list(hidden))
    params = car_parameters()
    for h in effects:
        params = with_effect(params, h.cause, h.value, h.signal)
    if foreign is not None:
        params = apply_overrides(params, dict(foreign.overrides))
    if surfaces is not None and len(surfaces) != len(programme):
        raise ValueError("one surface per diagnosis run")
    mus = [TRACK_MU] * len(programme) if surfaces is None else \
        [round(float(rng.uniform(*SURFACES[s][1])), 3) for s in surfaces]
    seeds = rng.integers(0, 2**31 - 1, size=len(programme) + len(holdout))
    reqs = [Request(m, v, mu, int(s)) for (m, v), s, mu in
            zip((*programme, *holdout), seeds, [*mus, *[TRACK_MU] * len(holdout)], strict=True)]
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
    cond_path = None
    if surfaces is not None:
        cond_path = Path(conditions) if conditions is not None else out.parent / f"{out.name}-conditions.csv"
        lines = ["file,mu"] + [f"{p.name},{SURFACES[s][0][0]:g}..{SURFACES[s][0][1]:g}"
                               for p, s in zip(files, surfaces, strict=False)]
        cond_path.write_text("\n".join(lines) + "\n")
    first = effects[0] if effects else None
    return Case(first, files[:len(programme)], files[len(programme):], effects, foreign, mus, cond_path)
