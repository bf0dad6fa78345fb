"""A named gain of a motion sensor, checked against the car's kinematics: a second measure of the same gain
that does not go through the vehicle model.

The physics (ISO 8855, body axes, the IMU at the centre of gravity): the lateral specific force is
``ay = dvy/dt + r vx + g sin(roll)``. Over a stretch of driving that starts and ends straight (no yaw rate, no
lateral acceleration: the lateral velocity ``vy`` is ~0 at both ends) the integral of ``ay - r vx`` is the roll
term alone, which the re-simulation models. A change of the car (a load, a rear toe, a stiffer tyre) changes how
``r`` and ``ay`` respond to the steering, but together: it leaves that integral as it was. A gain ``g`` of the
yaw-rate, speed or lateral-acceleration sensor scales one term of it, and nothing in the car restores it.

So over the day's stretches, the measured integral minus the re-simulated one, regressed on the term the gain
scales (:data:`TERMS`), is the gain the kinematics want relative to the one re-simulated: the sensor's gain measured
without the vehicle model (:func:`measure`; for the speed, which drives the re-simulation, see there), with a
99 % interval (Student's t over the stretches) and the relation's own model error (:data:`MODEL_ERROR`). A
named gain whose own 95 % interval and this one are disjoint is contradicted by the kinematics (an effect outside
the catalogue that a sensor gain imitated: a rear toe read as a yaw-rate gain, study seed 40000, case 40).

The relation holds one combination of the three gains, ``g_ay / (g_r g_vx)``: a gain of one of them that is
real but not named is read as a change of the named one (a day with two such gains, one named, may then be
contradicted and left ``unexplained``; never is a cause named for it).

Inputs are plain arrays (one entry per compared segment), so this module needs nothing of the identification.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

#: the signals whose gain the check measures, and the sign of the term of ``ay - r vx`` the gain scales:
#: ``+1``: ``ay`` (the regressor is the integral of ``ay``); ``-1``: ``r`` or ``vx`` (the integral of ``r vx``)
TERMS: dict[str, int] = {"ay_mps2": +1, "yaw_rate_radps": -1, "vx_mps": -1}
#: the car is straight where the re-simulated yaw rate (rad/s) and lateral acceleration (m/s^2) are this small
#: (a gentle lane change already exceeds both; straight, ``vy`` is a few mm/s)
STRAIGHT_YAW_RADPS = 0.01
STRAIGHT_AY_MPS2 = 0.3
#: a stretch between two straight instants counts when it lasts this long (s): shorter ones hold no corner
MIN_STRETCH_S = 1.0
#: fewer stretches than this give no verdict (the interval's spread is not measured)
MIN_STRETCHES = 3
#: the kinematic interval's confidence
CONFIDENCE = 0.99
#: the relation's own model error on a gain, relative (added in quadrature to the statistical half-width): the
#: roll term, g sin(roll), is a few percent of ``ay`` (1-4 % over the stretches of the days looked at), and a
#: payload, another CG height or other springs than the re-simulated ones change the roll gradient by 10-20 %:
#: up to 4 % x 20 %
MODEL_ERROR = 0.008


@dataclass(frozen=True)
class Segment:
    """One compared segment: time (s), measured and re-simulated ``ay`` (m/s^2), ``r`` (rad/s), ``vx`` (m/s),
    and the rows compared (bool); all of one length."""

    t: np.ndarray
    meas: dict[str, np.ndarray]
    pred: dict[str, np.ndarray]
    valid: np.ndarray


@dataclass(frozen=True)
class Kinematic:
    """The sensor's gain as the kinematics measure it (dimensionless, 1: exact), its :data:`CONFIDENCE`
    half-width (the statistical one and :data:`MODEL_ERROR`, in quadrature) and the number of stretches it rests
    on."""

    gain: float
    half_width: float
    stretches: int


def _stretches(seg: Segment) -> list[slice]:
    """Slices of ``seg`` from one straight instant to the next, at least :data:`MIN_STRETCH_S` apart, every row
    between compared."""
    straight = (np.abs(seg.pred["yaw_rate_radps"]) < STRAIGHT_YAW_RADPS) & (
        np.abs(seg.pred["ay_mps2"]) < STRAIGHT_AY_MPS2) & seg.valid
    bad = np.concatenate([[0], np.cumsum(~seg.valid)])  # invalid rows before each index
    idx = np.flatnonzero(straight)
    return [slice(a, b + 1) for a, b in zip(idx[:-1], idx[1:], strict=True)
            if seg.t[b] - seg.t[a] >= MIN_STRETCH_S and bad[b + 1] == bad[a]]


def _integrals(seg: Segment, sl: slice) -> tuple[float, ...]:
    """Over one stretch (m/s): the measured integrals of ``ay`` and ``r vx``, the re-simulated ones."""
    dt = np.gradient(seg.t)[sl]
    m, p = seg.meas, seg.pred
    return (float(np.sum(m["ay_mps2"][sl] * dt)), float(np.sum(m["yaw_rate_radps"][sl] * m["vx_mps"][sl] * dt)),
            float(np.sum(p["ay_mps2"][sl] * dt)), float(np.sum(p["yaw_rate_radps"][sl] * p["vx_mps"][sl] * dt)))


def _slope(y: np.ndarray, x: np.ndarray) -> tuple[float, float] | None:
    """Least-squares slope of ``y`` on ``x`` through the origin and its :data:`CONFIDENCE` half-width (None: no
    spread in ``x``)."""
    sxx = float(np.sum(x * x))
    if not sxx > 1e-12 * max(float(np.sum(y * y)), 1e-12):
        return None
    b = float(np.sum(x * y) / sxx)
    res = y - b * x
    se = float(np.sqrt(np.sum(res * res) / (len(y) - 1) / sxx))
    return b, float(stats.t.ppf(0.5 + CONFIDENCE / 2, len(y) - 1) * se)


def measure(segments: Sequence[Segment], signal: str, simulated: float) -> Kinematic | None:
    """The gain of ``signal`` (a key of :data:`TERMS`) as the kinematics measure it, where the re-simulation
    (``segments``' ``pred``) holds a gain ``simulated`` of it; None: fewer than :data:`MIN_STRETCHES` stretches,
    no corner in them, or a value not finite.

    The measured minus re-simulated integral of ``ay - r vx``, regressed on the re-simulated term the gain scales,
    is the relative change of gain the data want: the dynamics of each stretch (its ``vy`` at the ends, its roll)
    cancel between the car and its re-simulation. ``ay`` and ``r`` are not in the re-simulation's loop: for them
    this is exact, whatever gain was simulated. ``vx`` drives it (the re-simulated car runs at the measured speed
    over the simulated gain), so the re-simulated car's own ``r`` and ``ay`` follow the gain it holds, and the
    kinematic gain is off the true one by a share of the simulated gain's own error (up to a third of it in
    synthetic drives, either way, as the car's sideslip and yaw response change with speed): small where the fit
    is right, so a contradiction there takes a fit whose interval misses the truth. (A slope of the
    measured integrals alone does not depend on the simulated gain, but the stretches' own dynamics spread it
    about five times as wide: ±0.09 against ±0.02 on seed 40000's case 35, a speed gain on a mixed-surface day.)
    """
    rows = np.array([_integrals(seg, sl) for seg in segments for sl in _stretches(seg)]).reshape(-1, 4)
    if len(rows) < MIN_STRETCHES or not np.all(np.isfinite(rows)) or not np.isfinite(simulated) or simulated == 0:
        return None
    ay_m, rv_m, ay_p, rv_p = rows.T
    d = (ay_m - rv_m) - (ay_p - rv_p)
    fit = _slope(d, ay_p if TERMS[signal] > 0 else -rv_p)
    if fit is None:
        return None
    gain, half = simulated * (1.0 + fit[0]), abs(simulated) * fit[1]
    half = float(np.hypot(half, abs(gain) * MODEL_ERROR))
    return Kinematic(gain, half, len(rows)) if np.isfinite(gain) and np.isfinite(half) else None


def contradicts(ci95: tuple[float, float], k: Kinematic) -> bool:
    """Whether a named gain's 95 % interval ``ci95`` and the kinematic one are disjoint (False where ``ci95`` is
    not finite: no verdict)."""
    lo, hi = ci95
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return False
    return bool(k.gain + k.half_width < lo or k.gain - k.half_width > hi)
