"""The manoeuvres of the paper's Table I, as driving programmes (:class:`Plan`).

Each manoeuvre follows its ISO/NHTSA definition (see :mod:`sim.profiles` for
the input shapes) and is parameterised by the entry speed, the road friction
and a seed. Where a standard leaves the excitation level to the tester, the
level is drawn from the seed as a share of the friction limit, so that a
campaign covers the linear range and the limit of the tyres, as the paper's
data set does. Open-loop amplitudes come from the linear single-track model of
the same car (steering-wheel angle for a wanted steady lateral acceleration);
the FMVSS 126 and fishhook amplitudes follow their own rule from a simulated
slowly-increasing-steer test.

Speed ranges (km/h) are the paper's Table I.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.interpolate import CubicSpline

from sim import profiles
from sim.driver import (
    SPEED_COAST,
    SPEED_OPEN,
    SPEED_TARGET,
    STEER_FREE,
    STEER_HOLD,
    STEER_PATH,
    STEER_TABLE,
    Plan,
)
from sim.linear import linear_model
from sim.params import MU_RANGE

G = 9.81
#: "driven briskly": share of the road's friction the track speed profile asks of the
#: car in corners. The tyres give about 0.85 g on a mu = 1 road and the front-heavy
#: car understeers before that; 0.62 is brisk and still on the line (0.85 and 0.72
#: made the car plough off at the first corners).
TRACK_AY_FRACTION = 0.62
#: braking share of the friction limit on the track: without ABS and with a 78 %
#: front brake balance the front wheels lock near 0.85 g, and a locked front cannot
#: steer into the next corner.
TRACK_BRAKE_FRACTION = 0.5
#: acceleration share of the friction limit on the track: the driven front axle carries
#: 60 % of the weight and less as the car squats; more spins the front wheels on a wet
#: road and the car runs wide, off the line (the powertrain's 3 m/s^2 caps it on a dry one)
TRACK_ACCEL_FRACTION = 0.3
#: longitudinal shares of the friction the track driver never exceeds (drive, brake):
#: the planned ones with room for the speed loop's corrections
TRACK_GRIP = (0.4, 0.65)
#: circuits are 12 to 15 m wide: a car whose centre is 7.5 m off the centreline has left
#: the track, and the run ends there (outcome "off-track")
TRACK_HALF_WIDTH_M = 7.5


@dataclass(frozen=True)
class Manoeuvre:
    """A named manoeuvre: its speed range (km/h), standard and plan builder."""

    name: str
    speed_kmh: tuple[float, float]
    standard: str
    build: Callable[..., Plan]


def _base(name: str, duration: float, v0: float, mu: float, label: dict) -> tuple[np.ndarray, Plan]:
    t = Plan.grid(duration)
    n = len(t)
    plan = Plan(
        name=name, duration_s=duration, speed0_mps=v0,
        steer_mode=np.full(n, STEER_TABLE, np.int8), steer_sw=np.zeros(n),
        speed_mode=np.full(n, SPEED_TARGET, np.int8), speed_target=np.full(n, v0),
        motor_cmd=np.zeros(n), brake_cmd=np.zeros(n), mu_values=(mu,), label=label,
    )
    return t, plan


def _level(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _swa_for(params: Mapping[str, Any], v: float, ay: float) -> float:
    return float(_linear(json.dumps(params, sort_keys=True)).steering_wheel_angle(v, ay))


@functools.lru_cache(maxsize=16)
def _linear(params_json: str):
    return linear_model(json.loads(params_json))


def _direction(rng: np.random.Generator) -> int:
    return 1 if rng.random() < 0.5 else -1


# ---- open-loop steering manoeuvres -------------------------------------------------------
def steering_pulse(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any]) -> Plan:
    level = _level(rng, 0.3, 0.9)
    amp = _swa_for(params, v, level * mu * G) * _direction(rng)
    t, plan = _base("steering-pulse", 7.0, v, mu, {"level": level, "amplitude_rad": amp})
    plan.steer_sw[:] = profiles.steering_pulse(t, amp, t0=1.0, width=0.4)
    return plan


def single_sine(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any]) -> Plan:
    level = _level(rng, 0.3, 0.9)
    freq = _level(rng, 0.4, 0.8)
    amp = _swa_for(params, v, level * mu * G) * _direction(rng)
    t, plan = _base("single-sine", 1.0 / freq + 5.0, v, mu, {"level": level, "freq_hz": freq, "amplitude_rad": amp})
    plan.steer_sw[:] = profiles.single_sine(t, amp, freq=freq, t0=1.0)
    return plan


def random_steer(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any]) -> Plan:
    level = _level(rng, 0.25, 0.6)
    swept = rng.random() < 0.5
    duration = 20.0
    amp = _swa_for(params, v, level * mu * G)
    t, plan = _base("random-steer", duration, v, mu, {"level": level, "swept": swept})
    if swept:
        plan.steer_sw[:] = profiles.swept_sine(t, amp, f0=0.2, f1=2.0, duration=duration - 2.0, t0=1.0)
    else:
        seed = int(rng.integers(2**31))
        plan.steer_sw[:] = profiles.random_steer(t, amp / np.sqrt(2.0), seed=seed, f_max=2.0, t0=1.0)
    return plan


@functools.lru_cache(maxsize=16)
def _sis_amplitude(params_json: str) -> float:
    """FMVSS 126 'A': steering-wheel angle for 0.3 g in slowly increasing steer at 80 km/h."""
    from sim.engine import simulate_batch

    params = json.loads(params_json)
    runs = []
    for direction in (1, -1):
        t, plan = _base("slowly-increasing-steer", 5.0, 80 / 3.6, 1.0, {})
        plan.steer_sw[:] = profiles.slowly_increasing_steer(t, t0=0.5, direction=direction)
        runs.append(plan)
    res = simulate_batch(runs, [params, params])
    amps = []
    for i, direction in enumerate((1, -1)):
        run = res.run(i)
        amps.append(profiles.sis_amplitude_from_ay(direction * run["steer_angle_true_rad"],
                                                   direction * run["ay_true_mps2"]))
    return float(np.mean(amps))


def sis_amplitude(params: Mapping[str, Any]) -> float:
    """The car's FMVSS 126 characterisation amplitude A (rad), simulated once per car."""
    return _sis_amplitude(json.dumps(params, sort_keys=True))


def sine_with_dwell(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any]) -> Plan:
    a_sis = sis_amplitude(params)
    series = profiles.fmvss126_amplitudes(a_sis)
    amp = float(series[int(rng.integers(len(series)))])
    direction = _direction(rng)
    t, plan = _base("sine-with-dwell", 6.5, v, mu,
                    {"amplitude_rad": amp, "direction": direction, "A_rad": a_sis})
    plan.steer_sw[:] = profiles.sine_with_dwell(t, amp, t0=1.0, direction=direction)
    plan.speed_mode[t >= 1.0] = SPEED_COAST  # FMVSS 126: throttle released as the steering starts
    return plan


def fishhook(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any]) -> Plan:
    a_sis = sis_amplitude(params)
    scale = _level(rng, 0.4, 1.0)  # share of the NHTSA 6.5 A amplitude (the full one is the last of a series)
    amp = 6.5 * a_sis * scale
    direction = _direction(rng)
    t, plan = _base("fishhook", 7.5, v, mu, {"amplitude_rad": amp, "direction": direction, "A_rad": a_sis})
    plan.steer_sw[:] = profiles.fishhook(t, amp, t0=1.0, direction=direction)
    plan.speed_mode[t >= 1.0] = SPEED_COAST
    return plan


def brake_accel(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any]) -> Plan:
    """Straight line: a drive-torque step, then a brake step (open loop), then coast."""
    drive_level = _level(rng, 0.3, 1.0)
    brake_level = _level(rng, 0.2, 0.9)
    t, plan = _base("brake-accel", 9.0, v, mu, {"drive_level": drive_level, "brake_level": brake_level})
    veh = params["vehicle"]
    pt = params["powertrain"]
    open_ = t >= 1.0
    plan.speed_mode[open_] = SPEED_OPEN
    plan.motor_cmd[(t >= 1.0) & (t < 4.0)] = drive_level * pt["motor_max_torque_nm"]
    decel = brake_level * mu * G
    brake = decel * veh["mass_kg"] * 0.31 * params["brakes"]["front_share"] / 2.0
    plan.brake_cmd[(t >= 5.0) & (t < 7.5)] = brake
    plan.speed_mode[t >= 7.5] = SPEED_COAST
    return plan


# ---- closed-loop manoeuvres -----------------------------------------------------------------
def double_lane_change(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any]) -> Plan:
    lead, run_out = 30.0, 60.0
    ds = 0.5
    x = np.arange(-lead, 125.0 + run_out + ds, ds)
    direction = _direction(rng)
    y = direction * profiles.double_lane_change_path(x)
    path = np.stack([x + lead, y], axis=1)
    duration = (lead + 125.0 + run_out - 20.0) / v
    t, plan = _base("double-lane-change", duration, v, mu, {"direction": direction})
    plan.steer_mode[:] = STEER_PATH
    plan.path, plan.path_ds = path, ds
    # the test is driven once the car is through the exit gate; the run-out beyond it is margin
    plan.planned_distance_m = lead + 125.0
    return plan


def _circle_entry(radius: float, direction: int, lead: float = 20.0, laps: float = 1.5) -> np.ndarray:
    """ISO 4138 circle with a straight lead-in, as (N, 2) points every 0.5 m."""
    p = profiles.circle_path(radius, laps, ds=0.5, direction=direction, lead_in=lead)
    return np.stack([p.x, p.y], axis=1)


def constant_radius(radius: float, v_start: float, v_end: float, duration: float, mu: float,
                    direction: int = 1, name: str = "steady-state-circular", label: dict | None = None) -> Plan:
    """ISO 4138 constant-radius test: follow a circle while the speed rises slowly.

    The speed is held at ``v_start`` for 5 s on entry, then ramps linearly to
    ``v_end`` over the rest of the run but the last 2 s.
    """
    path = _circle_entry(radius, direction, laps=(duration * max(v_start, v_end)) / (2 * np.pi * radius) + 0.5)
    t, plan = _base(name, duration, v_start, mu, {"radius_m": radius, "direction": direction, **(label or {})})
    plan.steer_mode[:] = STEER_PATH
    plan.path, plan.path_ds = path, 0.5
    ramp = np.clip((t - 5.0) / (duration - 7.0), 0.0, 1.0)
    plan.speed_target[:] = v_start + (v_end - v_start) * ramp
    return plan


def steady_state_circular(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any]) -> Plan:
    """ISO 4138 constant radius: speed raised slowly from half to the given speed.

    The radius is chosen so that the final speed asks for a share (drawn from the
    seed) of the friction limit.
    """
    level = _level(rng, 0.5, 0.95)
    radius = max(v * v / (level * mu * G), 15.0)
    return constant_radius(radius, 0.5 * v, v, 30.0, mu, _direction(rng), label={"level": level})


def free_steer(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any]) -> Plan:
    """Steady turn on a circle, then the driver lets go of the wheel (ISO 17288 release)."""
    level = _level(rng, 0.3, 0.8)
    radius = max(v * v / (level * mu * G), 12.0)
    direction = _direction(rng)
    hold = 6.0
    duration = hold + 5.0
    path = _circle_entry(radius, direction, lead=15.0, laps=(duration * v) / (2 * np.pi * radius) + 0.5)
    t, plan = _base("free-steer", duration, v, mu, {"radius_m": radius, "level": level, "direction": direction})
    plan.steer_mode[:] = STEER_PATH
    plan.steer_mode[t >= hold] = STEER_FREE
    plan.path, plan.path_ds = path, 0.5
    plan.speed_mode[t >= hold] = SPEED_COAST
    return plan


def braking_in_turn(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any]) -> Plan:
    """ISO 7975: steady turn, then the steering wheel is held and the brakes applied."""
    level = _level(rng, 0.3, 0.6)
    decel_level = _level(rng, 0.2, 0.8)
    radius = max(v * v / (level * mu * G), 15.0)
    direction = _direction(rng)
    t_brake = 7.0
    duration = t_brake + 4.0
    path = _circle_entry(radius, direction, lead=15.0, laps=(duration * v) / (2 * np.pi * radius) + 0.5)
    t, plan = _base("braking-in-turn", duration, v, mu,
                    {"radius_m": radius, "level": level, "decel_level": decel_level, "direction": direction})
    plan.steer_mode[:] = STEER_PATH
    plan.steer_mode[t >= t_brake] = STEER_HOLD
    plan.path, plan.path_ds = path, 0.5
    braking = t >= t_brake
    plan.speed_mode[braking] = SPEED_OPEN
    decel = decel_level * mu * G
    plan.brake_cmd[braking] = decel * params["vehicle"]["mass_kg"] * 0.31 * params["brakes"]["front_share"] / 2.0
    return plan


def _track_plan(name: str, tr: Any, laps: int, mu_laps: tuple[float, ...], v: float, label: dict) -> Plan:
    """Brisk laps of ``tr`` (a :class:`sim.track.Track`), lap i on friction ``mu_laps[i]``.

    The car starts on the line heading +x at the speed profile's speed there, going straight; ``v`` caps
    the speed (m/s) and the profile follows the curvature and each lap's friction. A line inside a corner (a
    circuit traced from its first GPS point, a random circuit) is moved on to the next straight
    (:meth:`~sim.track.Track.next_straight`), recorded as ``line_moved_m`` in ``label``: a car in a corner is not
    going straight, and the path follower asked for the whole corner's lock at once (0 to 120 degrees of steering
    in 0.15 s at the robot's rate limit, with the hand torque near the CAN range).
    """
    from sim import track as trk

    moved = tr.next_straight()
    if moved:
        tr = tr.started_at(moved)
        label["line_moved_m"] = round(moved, 1)
    # the path runs on past the line by a lap: the run lasts the laps and one second more,
    # and the follower's preview point needs road ahead of the car to the very end
    path = tr.laps(laps + 1).aligned_to_start()
    s = path.s
    mu_s = np.asarray(mu_laps, dtype=float)[np.minimum((s // tr.length).astype(int), laps - 1)]
    vprof = trk.speed_profile(path.curvature, s, mu_s, v_max_mps=v, ay_frac=TRACK_AY_FRACTION,
                              ax_brake_frac=TRACK_BRAKE_FRACTION, ax_accel_frac=TRACK_ACCEL_FRACTION)
    ds = float(s[1] - s[0])
    n_laps = int(round(laps * tr.length / ds))
    duration = float(np.sum(ds / np.maximum(vprof[:n_laps], 1.0))) + 1.0
    _, plan = _base(name, duration, float(vprof[0]), mu_laps[0], label)
    plan.steer_mode[:] = STEER_PATH
    plan.path, plan.path_ds, plan.path_speed = np.stack([path.x, path.y], axis=1), ds, vprof
    plan.mu_dist = tuple(tr.length * np.arange(1, laps))
    plan.mu_values = tuple(float(m) for m in mu_laps)
    plan.path_grip = TRACK_GRIP
    plan.track_half_width_m = TRACK_HALF_WIDTH_M
    # the laps are the plan: the last second of its duration is margin past the line
    plan.planned_distance_m = laps * float(tr.length)
    return plan


def magny_cours(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any],
                wet_mu: float = 0.7) -> Plan:
    """Two brisk laps of Magny-Cours: the first at ``mu`` (dry), the second at ``wet_mu``.

    ``v`` caps the speed (m/s); the speed profile follows the curvature and the
    friction of each lap.
    """
    from sim import track as trk

    tr = trk.load_magny_cours()
    return _track_plan("magny-cours", tr, 2, (mu, wet_mu), v,
                       {"lap_length_m": tr.length, "mu_dry": mu, "mu_wet": wet_mu, "v_max_mps": v})


#: most laps of one ``circuit`` run
MAX_LAPS = 20


def circuit(v: float, mu: float, rng: np.random.Generator, params: Mapping[str, Any],
            track: str | None = None, laps: int | None = None) -> Plan:
    """Brisk laps of any closed circuit at friction ``mu``, the speed capped at ``v`` (m/s).

    Args:
        track: a bundled circuit's name or a centreline file (:func:`sim.track.load_track`).
        laps: number of laps (default 1, at most :data:`MAX_LAPS`).

    Raises:
        ManoeuvreError: no track, a bad lap count, or a centreline that cannot be driven
            (unreadable, open, crossing itself other than at a bridge, too short, or tighter than the car can steer).
    """
    from sim import track as trk
    from sim.centreline import check_steerable

    laps = 1 if laps is None else laps
    if track is None:
        raise ManoeuvreError("circuit: --track (a circuit name or a .csv/.geojson centreline) is required")
    if int(laps) != laps or not 1 <= laps <= MAX_LAPS:
        raise ManoeuvreError(f"circuit: --laps must be a whole number from 1 to {MAX_LAPS}, got {laps}")
    try:
        tr = trk.load_track(track)
        check_steerable(tr, params, str(track))
    except trk.TrackError as exc:
        raise ManoeuvreError(str(exc)) from None
    return _track_plan("circuit", tr, int(laps), (mu,) * int(laps), v,
                       {"track": str(track), "laps": int(laps), "lap_length_m": tr.length, "v_max_mps": v})


def from_recording(table: Mapping[str, np.ndarray], mu: float, *, longitudinal: str = "speed",
                   name: str = "recorded") -> Plan:
    """Re-simulate a recorded run from its driver inputs.

    The steering robot follows the recorded steering-wheel angle
    (``steer_angle_rad``); the longitudinal input is either the recorded speed
    (``longitudinal="speed"``: the speed controller tracks ``vx_mps``, starting
    from the recorded ``motor_torque_nm`` when there is one) or the
    recorded traction-motor torque (``"torque"``: ``motor_torque_nm`` open loop,
    no braking). Samples may come at any steady rate (a 20 Hz table, say); they
    are interpolated onto the 100 Hz control grid (a cubic spline for the steering). Non-finite samples
    (gaps) are not bridged silently: the plan holds the last good value and the
    gap positions are listed in ``plan.label["gaps_s"]``.

    Args:
        table: ``time_s`` and the recorded signals (catalogue names, SI units).
        mu: road friction for the re-simulation.
        longitudinal: ``"speed"`` or ``"torque"``.
    """
    needed = ["time_s", "steer_angle_rad", "vx_mps" if longitudinal == "speed" else "motor_torque_nm"]
    if longitudinal not in ("speed", "torque"):
        raise ManoeuvreError(f"longitudinal input must be 'speed' or 'torque', got {longitudinal!r}")
    missing = [k for k in needed if k not in table]
    if missing:
        raise ManoeuvreError(f"recorded inputs lack {', '.join(missing)}")
    t_rec = np.asarray(table["time_s"], dtype=float)
    if t_rec.size < 2 or not np.all(np.diff(t_rec) > 0):
        raise ManoeuvreError("recorded inputs need at least two samples with increasing time_s")
    t_rec = t_rec - t_rec[0]
    gaps: list[float] = []

    def series(key: str) -> np.ndarray:
        y = np.asarray(table[key], dtype=float)
        bad = ~np.isfinite(y)
        if bad.all():
            raise ManoeuvreError(f"recorded {key} has no finite sample")
        if bad.any():
            gaps.extend(float(x) for x in t_rec[bad & ~np.roll(bad, 1)])
            good = np.flatnonzero(~bad)
            y = y[good[np.maximum(np.searchsorted(good, np.arange(len(y)), side="right") - 1, 0)]]
        return y

    sw = series("steer_angle_rad")
    duration = float(t_rec[-1])
    v0 = float(series("vx_mps")[0]) if "vx_mps" in table else 20.0
    t, plan = _base(name, duration, v0, mu, {"gaps_s": sorted(set(gaps)), "longitudinal": longitudinal})
    # a cubic spline through the samples: a 20 Hz table carries steering up to a few Hz,
    # which straight lines between samples would cut by up to a tenth of its amplitude
    plan.steer_sw[:] = CubicSpline(t_rec, sw)(np.clip(t, t_rec[0], t_rec[-1])) if len(sw) > 3 \
        else np.interp(t, t_rec, sw)
    if longitudinal == "speed":
        v = series("vx_mps")
        if "motor_torque_nm" in table and len(v) > 6:
            # a centred 0.3 s average keeps the speed sensor's noise and steps out of the loop
            w = max(1, int(round(0.3 / float(np.median(np.diff(t_rec))))))
            pad = np.concatenate([np.full(w // 2, v[0]), v, np.full(w - 1 - w // 2, v[-1])])
            v = np.convolve(pad, np.ones(w) / w, mode="valid")
        plan.speed_target[:] = np.interp(t, t_rec, v)
        if "motor_torque_nm" in table:
            # the car's own motor torque as feedforward: the speed loop corrects, it does not lag
            plan.motor_feedforward = np.interp(t, t_rec, series("motor_torque_nm"))
    else:
        plan.speed_mode[:] = SPEED_OPEN
        plan.motor_cmd[:] = np.interp(t, t_rec, series("motor_torque_nm"))
    return plan


MANOEUVRES: dict[str, Manoeuvre] = {
    m.name: m
    for m in (
        Manoeuvre("free-steer", (20, 80), "ISO 17288-1 free-steer (release)", free_steer),
        Manoeuvre("steering-pulse", (20, 80), "ISO 7401 pulse input", steering_pulse),
        Manoeuvre("double-lane-change", (40, 120), "ISO 3888-1", double_lane_change),
        Manoeuvre("steady-state-circular", (40, 80), "ISO 4138 constant radius", steady_state_circular),
        Manoeuvre("single-sine", (40, 80), "ISO 7401 one-period sine", single_sine),
        Manoeuvre("random-steer", (40, 80), "ISO 7401 random / swept-sine input", random_steer),
        Manoeuvre("braking-in-turn", (40, 120), "ISO 7975", braking_in_turn),
        Manoeuvre("fishhook", (40, 80), "NHTSA fishhook", fishhook),
        Manoeuvre("sine-with-dwell", (40, 120), "FMVSS 126 sine with dwell", sine_with_dwell),
        Manoeuvre("brake-accel", (40, 120), "steady brake/acceleration command", brake_accel),
        Manoeuvre("magny-cours", (60, 250), "Magny-Cours, 2 laps, dry then wet", magny_cours),
        Manoeuvre("circuit", (40, 250), "laps of any closed circuit (--track)", circuit),
    )
}


class ManoeuvreError(ValueError):
    """An unknown manoeuvre, or a speed or friction outside its range."""


def check(name: str, speed_kmh: float, mu: float) -> Manoeuvre:
    """Validate a request; the error message names what is wrong and the valid range."""
    if name not in MANOEUVRES:
        raise ManoeuvreError(f"unknown manoeuvre {name!r}; choose one of: {', '.join(MANOEUVRES)}")
    m = MANOEUVRES[name]
    lo, hi = m.speed_kmh
    if not (np.isfinite(speed_kmh) and lo <= speed_kmh <= hi):
        raise ManoeuvreError(f"speed {speed_kmh:g} km/h is outside {name}'s range {lo:g}-{hi:g} km/h")
    if not (np.isfinite(mu) and MU_RANGE[0] <= mu <= MU_RANGE[1]):
        raise ManoeuvreError(f"mu {mu:g} is outside the range {MU_RANGE[0]:g}-{MU_RANGE[1]:g}")
    return m


def build_plan(name: str, speed_kmh: float, mu: float, seed: int, params: Mapping[str, Any],
               **options: Any) -> Plan:
    """The plan of manoeuvre ``name`` at ``speed_kmh`` on a road of friction ``mu``.

    ``options`` are the manoeuvre's own (``track``, ``laps`` for ``circuit``); any other
    manoeuvre given one is refused.
    """
    m = check(name, speed_kmh, mu)
    given = {k: v for k, v in options.items() if v is not None}
    if given and name != "circuit":
        raise ManoeuvreError(f"{name}: {', '.join(sorted(given))} go(es) with the manoeuvre 'circuit' only")
    rng = np.random.default_rng(seed)
    plan = m.build(speed_kmh / 3.6, mu, rng, params, **given)
    plan.label.update({"manoeuvre": name, "speed_kmh": speed_kmh, "mu": mu, "seed": seed})
    return plan
