"""Simulate manoeuvres: the entry points the CLI, the campaigns and the tools use.

``simulate_many`` builds the plans of several requests, advances them together
in one batch (vectorised across runs) and returns, per run, the truth on the
100 Hz base grid and the sensor streams (what the CAN writer encodes). The
canonical 20 Hz table is what a CAN receiver samples from those streams
(:func:`virtsensor.recordings.canlog.simulated_recording`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim.driver import Plan
from sim.engine import simulate_batch
from sim.manoeuvres import build_plan, check
from sim.params import apply_overrides, car_parameters, check_car
from sim.sensors import make_streams


@dataclass(frozen=True)
class Request:
    """One run to simulate: manoeuvre, entry speed (km/h), road friction, seed.

    ``track`` and ``laps`` go with the manoeuvre ``circuit`` only: a bundled circuit's
    name or a centreline file (:func:`sim.track.load_track`) and the number of laps.
    """

    manoeuvre: str
    speed_kmh: float
    mu: float
    seed: int = 0
    track: str | None = None
    laps: int | None = None
    #: the four tyres' inflation pressures (gauge, bar; FL, FR, RL, RR) of this run; None: the car's own
    pressures_bar: tuple[float, float, float, float] | None = None

    def options(self) -> dict[str, Any]:
        """The manoeuvre's own options (``track``, ``laps``) that are set."""
        return {k: v for k, v in (("track", self.track), ("laps", self.laps)) if v is not None}


@dataclass
class SimRun:
    """A simulated run.

    Attributes:
        request: what was asked.
        plan: the driving programme that was executed.
        params: the full parameter tree of the car.
        truth: truth channels on the 100 Hz base grid (``time_s`` first).
        streams: the car's signals as its sensors deliver them, on the same grid.
        outcome: how the run ended (:meth:`sim.engine.BatchResult.outcome`): completed,
            or spun or stopped at a time short of the plan.
    """

    request: Request
    plan: Plan
    params: Mapping[str, Any]
    truth: dict[str, np.ndarray]
    streams: dict[str, np.ndarray]
    outcome: dict[str, Any] = field(default_factory=lambda: {"status": "completed"})


def with_pressure(params: Mapping[str, Any], pressure_bar: float | None) -> dict[str, Any]:
    """Parameters with all four tyres at ``pressure_bar`` (gauge, bar); None keeps them."""
    if pressure_bar is None:
        return dict(params)
    if not (0.5 <= pressure_bar <= 5.0):
        raise ValueError(f"tyre pressure {pressure_bar:g} bar is outside 0.5-5 bar")
    pa = pressure_bar * 1e5
    return apply_overrides(params, {"tyres.pressure_front_pa": pa, "tyres.pressure_rear_pa": pa})


def with_pressures(params: Mapping[str, Any], pressures_bar: Sequence[float] | None) -> dict[str, Any]:
    """Parameters with each tyre at its own pressure: ``pressures_bar`` = (FL, FR, RL, RR), gauge, bar (each
    within 0.5-5 bar); None keeps them. Each axle gets its mean and its left-minus-right difference."""
    if pressures_bar is None:
        return dict(params)
    if len(pressures_bar) != 4 or not all(0.5 <= float(p) <= 5.0 for p in pressures_bar):
        raise ValueError(f"tyre pressures {list(pressures_bar)} bar: need four values within 0.5-5 bar")
    fl, fr, rl, rr = (float(p) * 1e5 for p in pressures_bar)
    return apply_overrides(params, {"tyres.pressure_front_pa": 0.5 * (fl + fr),
                                    "tyres.pressure_rear_pa": 0.5 * (rl + rr),
                                    "tyres.pressure_left_right_front_pa": fl - fr,
                                    "tyres.pressure_left_right_rear_pa": rl - rr})


def simulate_many(
    requests: Sequence[Request],
    params: Mapping[str, Any] | Sequence[Mapping[str, Any]] | None = None,
    progress: Callable[[int], None] | None = None,
    plans: Sequence[Plan] | None = None,
) -> list[SimRun]:
    """Simulate several runs in one vectorised batch.

    Args:
        requests: the runs.
        params: one parameter tree for all runs, or one per run (default car if None).
        progress: called with the number of control steps simulated so far.
        plans: the requests' plans when the caller has built them already
            (:func:`sim.manoeuvres.build_plan`); built here otherwise.
    """
    if not requests:
        return []
    if params is None:
        params = car_parameters()
    trees = [params] * len(requests) if isinstance(params, Mapping) else list(params)
    if len(trees) != len(requests):
        raise ValueError("one parameter tree per request")
    trees = [with_pressures(t, r.pressures_bar) if r.pressures_bar is not None else t
             for t, r in zip(trees, requests, strict=True)]
    for tree in {id(t): t for t in trees}.values():
        check_car(tree)
    for r in requests:
        check(r.manoeuvre, r.speed_kmh, r.mu)
    if plans is None:
        plans = [build_plan(r.manoeuvre, r.speed_kmh, r.mu, r.seed, tree, **r.options())
                 for r, tree in zip(requests, trees, strict=True)]
    elif len(plans) != len(requests):
        raise ValueError("one plan per request")
    result = simulate_batch(plans, trees, progress=progress)
    runs = []
    for i, (req, tree) in enumerate(zip(requests, trees, strict=True)):
        truth = result.run(i)
        # sensor noise is seeded apart from the manoeuvre's own randomness
        streams = make_streams(truth, tree, seed=int(np.random.SeedSequence([req.seed, 1]).generate_state(1)[0]))
        runs.append(SimRun(req, plans[i], tree, truth, streams, result.outcome(i)))
    return runs


def simulate_plan(plan: Plan, params: Mapping[str, Any] | None = None, seed: int = 0) -> SimRun:
    """Simulate one ready-made plan (e.g. :func:`sim.manoeuvres.from_recording`)."""
    params = car_parameters() if params is None else params
    check_car(params)
    result = simulate_batch([plan], [params])
    truth = result.run(0)
    streams = make_streams(truth, params, seed=int(np.random.SeedSequence([seed, 1]).generate_state(1)[0]))
    mu = float(plan.mu_values[0])
    return SimRun(Request(plan.name, float(plan.speed0_mps * 3.6), mu, seed), plan, params, truth, streams,
                  result.outcome(0))


def simulate(manoeuvre: str, speed_kmh: float, mu: float, seed: int = 0,
             params: Mapping[str, Any] | None = None, **options: Any) -> SimRun:
    """Simulate one run (see :func:`simulate_many`); ``options``: ``track``, ``laps`` for ``circuit``."""
    return simulate_many([Request(manoeuvre, speed_kmh, mu, seed, **options)], params)[0]


def simulate_streams(manoeuvre: str, *, speed_kmh: float, mu: float, seed: int = 0,
                     overrides: Iterable[str] = ()) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The sensor streams of one simulated run: ``(time_s, {signal: values})`` (for replay)."""
    run = simulate(manoeuvre, speed_kmh, mu, seed, car_parameters(list(overrides)))
    signals = {k: v for k, v in run.streams.items() if k != "time_s"}
    return run.streams["time_s"], signals
