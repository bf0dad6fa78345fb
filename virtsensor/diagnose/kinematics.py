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
without the vehicle model. :func:`gain_shift` computes it with a 99 % interval (Student's t over the stretches),
:func:`kinematic_gain` adds the relation's own model error (:data:`MODEL_ERROR`); a
named gain whose own 95 % interval and this one are disjoint is contradicted by the kinematics (an effect outside
the catalogue that a sensor gain imitated: a rear toe read as a yaw-rate gain, study seed 40000, case 40).

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
#: the relation's own model error on a gain (added in quadrature to the statistical half-width): the roll term,
#: g sin(roll), is a few percent of ``ay`` (1-4 % over the stretches of the days looked at), and a payload,
#: another CG height or other springs than the re-simulated ones change the roll gradient by 10-20 %
MODEL_ERROR = 0.005


@dataclass(frozen=True)
class Segment:
    """One compared segment: time (s), measured and re-simulated ``ay`` (m/s^2), ``r`` (rad/s), ``vx`` (m/s),
    and the rows compared (bool); all of one length."""

    t: np.ndarray
    meas: dict[str, np.ndarray]
    pred: dict[str, np.ndarray]
    valid: np.ndarray


@dataclass(frozen=True)
class Shift:
    """The gain the kinematics want relative to the re-simulated one ``g_sim``: ``g = g_sim (1 + shift)``
    (dimensionless, 0: the same), the shift's :data:`CONFIDENCE` half-width and the number of stretches it rests
    on."""

    shift: float
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


def _integral_terms(seg: Segment, sl: slice) -> tuple[float, float, float]:
    """Over one stretch: measured minus re-simulated integral of ``ay - r vx`` (m/s), and the integrals of the
    re-simulated ``ay`` and ``r vx`` (m/s): the terms as the re-simulated gain scales them."""
    dt = np.gradient(seg.t)[sl]
    m, p = seg.meas, seg.pred
    rv_m = m["yaw_rate_radps"][sl] * m["vx_mps"][sl]
    rv_p = p["yaw_rate_radps"][sl] * p["vx_mps"][sl]
    d = float(np.sum((m["ay_mps2"][sl] - rv_m - p["ay_mps2"][sl] + rv_p) * dt))
    return d, float(np.sum(p["ay_mps2"][sl] * dt)), float(np.sum(rv_p * dt))


def gain_shift(segments: Sequence[Segment], signal: str) -> Shift | None:
    """The gain of ``signal`` (a key of :data:`TERMS`) the kinematics want beyond the re-simulated one, or None
    (fewer than :data:`MIN_STRETCHES` stretches, or no corner in them)."""
    rows = [_integral_terms(seg, sl) for seg in segments for sl in _stretches(seg)]
    if len(rows) < MIN_STRETCHES:
        return None
    d = np.array([r[0] for r in rows])
    x = np.array([r[1] if TERMS[signal] > 0 else -r[2] for r in rows])
    sxx = float(np.sum(x * x))
    if sxx <= 0:
        return None
    shift = float(np.sum(d * x) / sxx)
    res = d - shift * x
    se = float(np.sqrt(np.sum(res * res) / (len(d) - 1) / sxx))
    half = float(stats.t.ppf(0.5 + CONFIDENCE / 2, len(d) - 1) * se)
    return Shift(shift, half, len(d))


def kinematic_gain(estimate: float, s: Shift) -> tuple[float, float]:
    """The gain the kinematics measure, and its half-width (the statistical one and :data:`MODEL_ERROR` in
    quadrature), where ``estimate`` is the gain re-simulated."""
    return estimate * (1.0 + s.shift), abs(estimate) * float(np.hypot(s.half_width, MODEL_ERROR))


def contradicts(estimate: float, ci95: tuple[float, float], s: Shift) -> bool:
    """Whether a named gain (``estimate``, re-simulated; its 95 % interval ``ci95``) and the kinematic one
    (:func:`kinematic_gain`) have disjoint intervals."""
    g, h = kinematic_gain(estimate, s)
    return bool(g + h < ci95[0] or g - h > ci95[1])
