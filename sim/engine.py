"""The integration loop: a batch of runs advanced together with fixed-step RK4.

One Python iteration advances *every* run of the batch by one step; there is no
loop over runs. The driver updates at 100 Hz (zero-order hold over the RK4
stages), the truth is recorded on the 100 Hz base grid.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from sim.driver import CONTROL_DT, Driver, Plan
from sim.params import step_counts
from sim.vehicle import (
    IOM,
    IPHI,
    IPSI,
    IR,
    ISW,
    ITH,
    IVX,
    IVY,
    IX,
    IY,
    WHEELS,
    Vehicle,
)

#: truth channels recorded on the base grid (name -> per-wheel or scalar)
TRUTH_SCALARS = (
    "x_m", "y_m", "yaw_rad", "vx_true_mps", "vy_mps", "yaw_rate_true_radps", "roll_rad", "pitch_rad",
    "ax_true_mps2", "ay_true_mps2", "steer_angle_true_rad", "steer_torque_true_nm",
    "assist_torque_true_nm", "motor_torque_true_nm", "road_mu", "steer_angle_cmd_rad",
)
TRUTH_WHEELS = ("alpha", "kappa", "fz", "fy", "fx", "delta", "sat", "comp", "omega", "re", "pressure", "util")
#: a tyre's friction utilisation sqrt(Fx^2 + Fy^2) / (mu Fz) (road mu) is recorded up to this (a wheel lifting
#: off, Fz -> 0, would make it unbounded)
UTIL_MAX = 2.0


@dataclass
class BatchResult:
    """Recorded truth of a batch: ``data[name]`` is (B, N) on ``time_s`` (N,)."""

    time_s: np.ndarray
    data: dict[str, np.ndarray]
    n_valid: np.ndarray  # (B,) valid samples of each run (runs differ in length; aborted runs end early)
    plans: Sequence[Plan]
    params: Sequence[Mapping[str, Any]]
    #: (B,) why each run ended: one of :data:`OUTCOMES` (index)
    ended_by: np.ndarray | None = None
    #: (B,) distance (m) each run's car had covered along its path at its last valid sample
    driven_m: np.ndarray | None = None

    def outcome(self, i: int) -> dict[str, Any]:
        """How run ``i`` ended: ``{"status": s, "at_s": t, "planned_s": T}``, ``s`` in :data:`OUTCOMES`.

        ``at_s`` is the time of the run's last valid sample (s); ``planned_s`` the
        plan's duration. A spun (body side-slip beyond ``ABORT_SIDESLIP_RAD``), stopped
        (speed below ``ABORT_SPEED_MPS``) or off-track (farther from the path it follows
        than its plan's ``track_half_width_m``) run ends there, short of its plan. A run
        with a planned distance (:attr:`sim.driver.Plan.planned_distance_m`: circuits, the
        double lane change) also gives ``driven_m``, how far along its path the car got
        (m), and ``planned_m``; one whose time ran out short of it is ``behind-plan``.
        """
        code = 0 if self.ended_by is None else int(self.ended_by[i])
        n = int(self.n_valid[i])
        out: dict[str, Any] = {"status": OUTCOMES[code], "at_s": round(float(self.time_s[max(n - 1, 0)]), 3),
                               "planned_s": round(float(self.plans[i].duration_s), 3)}
        planned = self.plans[i].planned_distance_m
        if planned is not None and self.driven_m is not None:
            out.update(driven_m=round(float(self.driven_m[i]), 1), planned_m=round(float(planned), 1))
        return out

    def run(self, i: int) -> dict[str, np.ndarray]:
        """Run ``i``'s channels, trimmed to its own duration."""
        n = int(self.n_valid[i])
        out = {"time_s": self.time_s[:n]}
        out.update({k: v[i, :n] for k, v in self.data.items()})
        return out


def simulate_batch(
    plans: Sequence[Plan],
    params: Sequence[Mapping[str, Any]],
    progress: Callable[[int], None] | None = None,
) -> BatchResult:
    """Simulate ``plans[i]`` with car ``params[i]`` for every i, all at once.

    Args:
        plans: one driving programme per run.
        params: one parameter tree per run (:func:`sim.params.car_parameters`).
        progress: called with the number of simulated control steps done so far.

    Raises:
        FloatingPointError: a run's state became non-finite (the simulation diverged); the message names
            the time and the run(s), and numpy's floating-point warnings of that step are not shown
            (:class:`_FloatingPointEvents`).
    """
    events = _FloatingPointEvents()
    with events.caught():
        return _simulate_batch(plans, params, progress, events)


def _simulate_batch(plans: Sequence[Plan], params: Sequence[Mapping[str, Any]],
                    progress: Callable[[int], None] | None, events: _FloatingPointEvents) -> BatchResult:
    if len(plans) != len(params):
        raise ValueError("one parameter tree per plan")
    dt, sub, rec_every = _steps(params)
    veh = Vehicle(params)
    drv = Driver(veh, plans, params)
    B = veh.B
    speed0 = np.array([p.speed0_mps for p in plans], dtype=float)
    x = veh.initial_state(speed0)
    drv.reset(x)
    n_ctl = drv.n
    n_rec = (n_ctl - 1) // rec_every + 1
    rec: dict[str, np.ndarray] = {k: np.empty((B, n_rec), np.float64) for k in TRUTH_SCALARS}
    for w in TRUTH_WHEELS:
        for name in WHEELS:
            rec[f"{w}_{name}"] = np.empty((B, n_rec), np.float64)

    half = 0.5 * dt
    j = 0
    # per run, the first recorded sample after which it is no longer a test; kept up to date
    # sample by sample, so no step rescans the recorded history
    aborted_at = np.full(B, n_rec)
    ended_by = np.zeros(B, dtype=np.int8)
    plan_samples = np.array([(p.n - 1) // rec_every + 1 for p in plans])  # each run's own recorded samples
    station = np.zeros((B, n_rec))  # where each car is along its path at each recorded sample (m)
    for k in range(n_ctl):
        x_prev = x
        u = drv.update(k, x)
        for s in range(sub):
            veh.new_step()
            t0 = s * dt - CONTROL_DT  # the robot's ramp: see Inputs.steer_lead_s
            u = replace(u, steer_lead_s=t0)
            k1, aux = veh.derivatives(x, u)
            if s == 0 and k % rec_every == 0:
                _record(rec, j, x, aux, u, drv, veh)
                station[:, j] = drv.station_m
                aborted_at = _update_abort(aborted_at, ended_by, rec, j, n_rec, drv.off_track(k))
                j += 1
            veh.commit(aux)
            if k == n_ctl - 1:
                break
            u_half = replace(u, steer_lead_s=t0 + half)
            k2, _ = veh.derivatives(x + half * k1, u_half)
            k3, _ = veh.derivatives(x + half * k2, u_half)
            k4, _ = veh.derivatives(x + dt * k3, replace(u, steer_lead_s=t0 + dt))
            x = x + (dt / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
        # a run whose every sample is recorded (it ended: spun, stopped, off-track, or its own
        # plan is over in a longer batch) is no longer a test: its state stays where it was.
        # Integrated on, a spun car under a driver still chasing its path (the front wheels
        # spun up, the car sliding backwards) diverges until the tyre and body terms overflow
        # (RuntimeWarnings on stderr) while the batch's other runs go on, and none of it is kept
        done = (np.maximum(aborted_at, 1) < j) | (j >= plan_samples)
        if done.any():
            x = np.where(done[:, None], x_prev, x)
        if not np.all(np.isfinite(x)):  # a run still live diverged: an error (it says what numpy saw)
            bad = np.flatnonzero(~np.all(np.isfinite(x), axis=1))
            raise FloatingPointError(f"the simulation diverged (its state became non-finite) at "
                                     f"t={k * CONTROL_DT:.2f} s in {_runs_named(plans, bad)}")
        events.warn(k, plans)
        if progress is not None and (k % 100 == 0 or k == n_ctl - 1):
            progress(k + 1)
        if done.all():
            break  # every run has ended or is over: nothing left to simulate
    time_s = np.arange(n_rec) * (rec_every * CONTROL_DT)
    n_valid, driven = _finish(plans, plan_samples, aborted_at, ended_by, station, j)
    return BatchResult(time_s, rec, n_valid, plans, params, ended_by, driven)


def _run_name(plan: Plan) -> str:
    """A run as a person names it: its manoeuvre, and its entry speed, friction and seed when its label gives
    them (``double-lane-change at 80 km/h, mu 1, seed 0``)."""
    label = plan.label
    parts = [f"{label['speed_kmh']:g} km/h" if isinstance(label.get("speed_kmh"), int | float) else "",
             f"mu {label['mu']:g}" if isinstance(label.get("mu"), int | float) else "",
             f"seed {label['seed']}" if "seed" in label else ""]
    details = ", ".join(p for p in parts if p)
    return f"{plan.name} at {details}" if details else plan.name


def _runs_named(plans: Sequence[Plan], which: Sequence[int] | np.ndarray) -> str:
    """The runs ``which`` of a batch, named (:func:`_run_name`; the first three and how many more)."""
    names = "; ".join(_run_name(plans[int(i)]) for i in which[:3])
    return f"{names} (and {len(which) - 3} more)" if len(which) > 3 else names


class _FloatingPointEvents:
    """numpy's floating-point errors (overflow, invalid value, division by zero) of each control step.

    The loop runs under ``np.errstate(call=...)`` (thread- and context-local): numpy reports each error here
    instead of warning at once. A step whose state then diverges raises FloatingPointError, which says all
    that its warnings would (a bad car or tyre gives one line, not a screen of RuntimeWarnings before it);
    any other step's errors are warned as RuntimeWarning, once per kind and batch, naming the runs.
    """

    def __init__(self) -> None:
        self.kinds: list[str] = []
        self.warned: set[str] = set()

    def __call__(self, kind: str, flag: int) -> None:
        self.kinds.append(kind)

    def caught(self) -> np.errstate:
        """The context in which numpy reports its floating-point errors here."""
        return np.errstate(over="call", invalid="call", divide="call", call=self)

    def warn(self, k: int, plans: Sequence[Plan]) -> None:
        """Warn the errors of control step ``k`` that no divergence explained (each kind once per batch)."""
        new = sorted(set(self.kinds) - self.warned)
        self.kinds.clear()
        if new:
            self.warned.update(new)
            warnings.warn(f"floating-point {' and '.join(new)} in the simulation at t={k * CONTROL_DT:.2f} s "
                          f"(batch of {_runs_named(plans, range(len(plans)))})", RuntimeWarning, stacklevel=2)


def _steps(params: Sequence[Mapping[str, Any]]) -> tuple[float, int, int]:
    """``(dt, sub, rec_every)``: the integration step (s) the batch's runs share, the steps per control period and
    the control periods per recorded sample (:func:`sim.params.step_counts`); ValueError when they do not fit."""
    dt = float(params[0]["simulation"]["step_s"])
    if any(float(p["simulation"]["step_s"]) != dt for p in params):
        raise ValueError("runs of one batch must share simulation.step_s")
    sub, rec_every = step_counts(dt, float(params[0]["simulation"]["record_rate_hz"]))
    return dt, sub, rec_every


def _finish(plans: Sequence[Plan], plan_samples: np.ndarray, aborted_at: np.ndarray, ended_by: np.ndarray,
            station: np.ndarray, j: int) -> tuple[np.ndarray, np.ndarray]:
    """``(n_valid, driven_m)`` per run once the batch is over (``j`` samples recorded): its valid samples (its own
    plan's, cut at an abort) and the distance covered along its path at the last of them; sets ``ended_by`` in
    place (an abort after a run's own plan has ended, in a longer batch, is no abort; ``behind-plan``)."""
    n_rec = station.shape[1]
    n_valid = np.minimum(np.minimum(np.minimum(plan_samples, n_rec), j), np.maximum(aborted_at, 1))
    ended_by[aborted_at >= plan_samples] = 0
    driven = station[np.arange(len(plans)), n_valid - 1]
    ended_by[(ended_by == 0) & _behind(plans, driven)] = OUTCOMES.index("behind-plan")
    return n_valid, driven


#: a test driver ends a run once the car has (nearly) stopped or is spinning
ABORT_SPEED_MPS = 3.0
ABORT_SIDESLIP_RAD = np.deg2rad(30.0)
#: how a run ended (index: ``BatchResult.ended_by``). ``behind-plan``: its time ran out before
#: the car had covered its plan's distance (it fell behind the speed profile: too little
#: power, say); its recording is whole, what the car did, but not the lap it planned
OUTCOMES = ("completed", "spun", "stopped", "off-track", "behind-plan")
#: how far short of its planned distance (share of it) a run may end and still be ``completed``.
#: A plan carries its own margin (a circuit's duration is its speed profile's lap time plus 1 s;
#: a double lane change runs 40 m on past its exit gate), so a car on plan ends past the planned
#: distance: the default car's completed laps of the ``circuits`` campaign (seed 0) ended at
#: 100.1-100.7 % of theirs. The speed loop trails the profile, most on a dry road (Zandvoort
#: at 150 km/h, mu 1: by about 29 m, 0.7 % of the lap, so 13 m past the line); over many laps
#: that lag adds up while the margin does not, and 1 % still covers it. A car a hundredth of
#: its laps behind is flagged; a crippled motor is far behind (10 Nm: 62 % of Zandvoort at 150 km/h).
BEHIND_TOLERANCE = 0.01


def _behind(plans: Sequence[Plan], driven_m: np.ndarray) -> np.ndarray:
    """(B,) bool: runs with a planned distance whose car covered less than it (less the tolerance)."""
    planned = np.array([np.nan if p.planned_distance_m is None else p.planned_distance_m for p in plans])
    return driven_m < planned * (1.0 - BEHIND_TOLERANCE)  # nan (no planned distance): False


def _update_abort(aborted_at: np.ndarray, ended_by: np.ndarray, rec: Mapping[str, np.ndarray], j: int,
                  never: int, off_track: np.ndarray | None = None) -> np.ndarray:
    """``aborted_at`` with recorded sample ``j`` taken into account; ``ended_by`` updated in place.

    Per run, the first recorded sample at which the run is no longer a test (stopped,
    spinning, or, per ``off_track`` (B,) bool, off the track it follows), or ``never``.
    Callers use ``max(aborted_at, 1)``: a run keeps its first sample. A car sliding
    sideways beyond the side-slip limit has spun, whatever its speed or place.
    """
    vx, vy = rec["vx_true_mps"][:, j], rec["vy_mps"][:, j]
    spun = np.abs(np.arctan2(vy, np.abs(vx))) > ABORT_SIDESLIP_RAD
    stopped = vx < ABORT_SPEED_MPS
    off = np.zeros_like(spun) if off_track is None else off_track
    new = (aborted_at == never) & (spun | stopped | off)
    ended_by[new] = np.where(spun[new], 1, np.where(stopped[new], 2, 3))
    return np.where(new, j, aborted_at)


def _record(rec: dict[str, np.ndarray], j: int, x: np.ndarray, aux: Mapping[str, np.ndarray],
            u: Any, drv: Driver, veh: Vehicle) -> None:
    g = veh.g
    phi, th = x[:, IPHI], x[:, ITH]
    rec["x_m"][:, j] = x[:, IX]
    rec["y_m"][:, j] = x[:, IY]
    rec["yaw_rad"][:, j] = x[:, IPSI]
    rec["vx_true_mps"][:, j] = x[:, IVX]
    rec["vy_mps"][:, j] = x[:, IVY]
    rec["yaw_rate_true_radps"][:, j] = x[:, IR]
    rec["roll_rad"][:, j] = phi
    rec["pitch_rad"][:, j] = th
    # what a body-fixed accelerometer at the CG measures: specific force, gravity through roll/pitch
    rec["ax_true_mps2"][:, j] = aux["ax_kin"] * np.cos(th) - g * np.sin(th)
    rec["ay_true_mps2"][:, j] = aux["ay_kin"] * np.cos(phi) + g * np.sin(phi)
    rec["steer_angle_true_rad"][:, j] = x[:, ISW]
    rec["steer_torque_true_nm"][:, j] = aux["t_bar"]
    rec["assist_torque_true_nm"][:, j] = aux["t_assist"]
    rec["motor_torque_true_nm"][:, j] = drv.motor
    rec["road_mu"][:, j] = u.mu
    rec["steer_angle_cmd_rad"][:, j] = u.steer_cmd + u.steer_cmd_rate * u.steer_lead_s
    for w, src in (("alpha", "alpha"), ("kappa", "kappa"), ("fz", "fz"), ("fy", "fy"), ("fx", "fx"),
                   ("delta", "delta"), ("sat", "mz"), ("comp", "comp"), ("re", "re")):
        a = aux[src]
        for i, name in enumerate(WHEELS):
            rec[f"{w}_{name}"][:, j] = a[:, i]
    om = x[:, IOM]
    for i, name in enumerate(WHEELS):
        rec[f"omega_{name}"][:, j] = om[:, i]
        rec[f"pressure_{name}"][:, j] = veh.pressure[:, i]
    # friction utilisation of each tyre against the road's mu (the issue-19 truth); 0/0 (unloaded) -> UTIL_MAX
    demand = np.hypot(aux["fx"], aux["fy"])
    cap = np.asarray(u.mu, dtype=float)[:, None] * aux["fz"]
    util = np.where(cap > 1e-9, demand / np.maximum(cap, 1e-9), UTIL_MAX)
    for i, name in enumerate(WHEELS):
        rec[f"util_{name}"][:, j] = np.minimum(util[:, i], UTIL_MAX)
