"""The grip margin from the SAT: front-axle friction utilisation, road friction and a grip-limit warning.

The paper's Section V.B motivates SAT estimation by the early detection of the friction limit: the pneumatic
trail (SAT over lateral force) collapses while the lateral force still rises. This module turns the two
estimated front SATs and the estimator's inputs into what a chassis controller needs, after Hsu, Laws and
Gerdes (IEEE TCST 2010, "Estimation of tire slip angle and friction limits using steering torque"): in a brush
tyre the normalised trail is a function of the friction utilisation alone, so the trail gives the
utilisation without knowing the road, and the force used divided by the utilisation gives the road friction,
but only once the trail has fallen far enough to tell (the tyres are excited enough); before that the
friction is unknown, never a guess.

Per 20 Hz tick (:meth:`GripEstimator.step`), all in ISO 8855 body axes and SI units:

* the front axle's lateral force from the lateral acceleration and the yaw acceleration of a rigid car,
  ``Fy = (m b ay + Iz dr/dt) / L`` (N); its longitudinal force from the traction motor torque (``T i / r``,
  driving or regenerating) plus the front share of the brakes' force, ``min(m ax + D vx^2 - T i / r, 0)``
  (what the deceleration leaves after drive and air drag ``D vx^2``); its load from the static
  front load and the longitudinal load transfer, ``Fz = m g b / L - m h ax / L``, held at 0.2 of the static load
  or more (a hard acceleration does not unload the axle to nothing);
* the force ratio ``n = |F| / Fz`` (the friction the axle uses) and the axle trail ``t = -Mz sgn(Fy) / |Fy|``
  (m) from the sum of the two SATs, both low-passed (:attr:`GripParams.filter_s`); where the front TPMS
  pressures are known (:meth:`GripEstimator.set_front_pressure`), the trail is read at the calibration's
  pressure (a harder tyre's trail is shorter at the same utilisation): for the SATs of a model that reads the
  pressures, on the tyre's own curves at that pressure (:attr:`GripParams.trail_at_pressure`, from its MF 6.1
  file); for a model that does not (its trail carries only part of the pressure's effect), ``t / (1 - PPZ1 dpi)``;
* the road friction ``mu = n / k(t)``, with ``k`` the calibrated force ratio per unit of friction at that
  trail (:attr:`GripParams.use_at_trail`; the axle's ``n / mu`` is below the utilisation of its more used
  tyre), and the half-width of its 90 % interval, the 90th percentile of the absolute error at that trail for
  estimates in that band on the calibration's worst road (:attr:`GripParams.interval_at_trail`: meant to hold the
  truth on every road, not only pooled over a mix of mostly easy samples); it is given only where the trail
  is read (``|Fy| >= min_force_ratio Fz`` and ``|Fx| <= max_long_ratio Fz``: the brush trail is that of pure
  side slip), while the force changes slowly (:attr:`GripParams.max_force_rate`), with a calibrated relative
  error at most ``rel_err_max``, a pooled error (:attr:`GripParams.abs_err90_at_trail`) at most
  :attr:`GripParams.halfwidth_max` and a published half-width at most :attr:`GripParams.interval_max` (else
  nan: unknown);
* the road's friction holds while the car drives on: the median of the latest ``hold_count`` given estimates
  (robust to a stray one) is given on for ``hold_m`` metres after the latest, with its half-widths grown by
  ``hold_widen_per_m`` per metre (the road met since may differ), but only while the tyres are excited, the
  axle force ratio at least ``hold_min_use`` times the held friction (straight driving and gentle corners stay
  unknown), and while the held median's own calibrated error (:attr:`GripParams.hold_err90`) and its published
  half-width, both widened, stay within the gates; a change of road within that distance is its failure mode (see
  the README);
* the limit's own evidence, whatever the road: the trail-to-lateral-utilisation curve (the brush model's
  monotone curve measured on the car's own tyres, :attr:`GripParams.util_at_trail`, see
  ``tools/grip_study.py``) where the trail is read (for this evidence also under a longitudinal force up to
  :attr:`GripParams.evidence_long_ratio` times the load, where the friction is not read), and the front
  wheels' longitudinal slip over ``kappa_limit`` (a spinning or locking driven wheel is at the limit; the slip
  against the front axle's own speed in a turn, in the direction of the longitudinal force, beyond what the
  signals' resolution can carry: :meth:`GripEstimator._slip`);
* the utilisation ``u``: ``n / mu_ref``, with ``mu_ref`` the latest given friction plus its pooled error (1
  until one is given), or the evidence where that is higher; clipped to [0, 1];
* the warning's evidence also holds the floor ``n / mu_road_max``: whatever the road (the car is rated up to
  ``mu_road_max``), the axle uses at least that share of its grip, so a hard combined-slip corner on a dry road
  (the trail gated off) is seen coming by the force it already uses; with :attr:`GripParams.evidence_mu_held`,
  while a friction is held, the same force ratio over the held friction plus its pooled error (the wet road's
  combined-slip corner, seen by the share it uses of the grip measured there);
* the warning: on when the evidence (plus, for :attr:`GripParams.mu_hold_s` after a friction was given,
  ``n / mu_ref``) reaches ``warn_on``, or, above ``warn_off``, is predicted to reach it rising at its rate for
  ``warn_horizon_s``, or when ``demand_weight`` times the driver's demand reaches it (:meth:`GripEstimator.
  _demand`: the linear car's lateral force for this steering angle and speed with this tick's longitudinal
  force, as the more used front tyre's force ratio, over the rated ``mu_road_max`` or, if
  ``demand_mu_held``, the held friction): the steering asks for the force before the tyres deliver it; off
  when it stays below ``warn_off`` for ``warn_hold_s``. (The shipped calibration: the floor and the demand
  against the rated friction; no look-ahead along either rate, no force over the held friction: those gave
  more false warnings than the fit's budget, see the README.)

The numbers of a car (mass, geometry, drive, the calibrated curves) are :class:`GripParams`, read from the JSON
shipped with the package (:func:`load_params`, the catalogue car). The per-tick code uses the standard library
only; numpy serves :func:`estimate_run` (the daemon imports this module: no scipy, no scikit-learn).
"""

from __future__ import annotations

import bisect
import json
import math
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from importlib.resources import as_file, files
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor.errors import UserError
from virtsensor.signals import SIGNALS

__all__ = ["GRIP_INPUTS", "PRESSURE_INPUTS", "GripParams", "GripEstimator", "GripState", "estimate_run",
           "reads_pressure", "front_pressure", "load_params", "PARAMS_FILE"]

#: the catalogue car's grip parameters, package data beside this module
PARAMS_FILE = "grip_car.json"
#: the most pressures whose knots and curves an estimator keeps (:meth:`GripEstimator.set_front_pressure`; the mean
#: of two TPMS readings at 0.005 bar a bit takes a few dozen values in a drive)
CURVE_CACHE_SIZE = 256
#: the estimator inputs :meth:`GripEstimator.step` reads, in its argument order (after the two SATs)
GRIP_INPUTS = ("ax_mps2", "ay_mps2", "vx_mps", "yaw_rate_radps", "steer_angle_rad", "motor_torque_nm",
               "wheel_speed_fl_radps", "wheel_speed_fr_radps")
#: the front tyres' TPMS pressures the estimate reads the trail at, where the bus carries them
PRESSURE_INPUTS = ("tyre_pressure_fl_pa", "tyre_pressure_fr_pa")
G = 9.81
#: the held friction's median is retaken after this many new given estimates (0.25 s of them at 20 Hz)
MEDIAN_EVERY = 5


@dataclass(frozen=True)
class GripParams:
    """A car's numbers for the grip estimate (SI units; curves as knots, linear in between, held beyond).

    Attributes:
        mass_kg, wheelbase_m, front_load_fraction, cg_height_m, yaw_inertia_kgm2: the rigid car.
        gear_ratio, rolling_radius_m: motor torque (Nm) -> front drive force ``T * gear_ratio / r`` (N).
        brake_front_share: the front axle's share of the brakes' force.
        drag_n_per_m2ps2: the air drag per squared speed, ``rho Cd A / 2`` (N s^2/m^2): the brakes' force is what
            the deceleration ``m ax`` leaves after the drive force and the drag.
        filter_s: time constant of the first-order low-pass on SAT sum and axle forces (s).
        min_force_ratio: ``n`` below which the trail is not used (too little lateral force to divide by).
        trail_m: ascending trail knots (m); util_at_trail: the front utilisation at each (non-increasing).
        use_at_trail: the axle force ratio per unit of road friction, ``n / mu``, at each trail knot.
        rel_err90_at_trail: the 90th percentile of |mu error| / mu at each trail knot (calibration).
        mu_bands: ascending upper edges of the bands of the friction estimate (the last one holds the rest).
        abs_err90_at_trail: per band, the 90th percentile of |mu error| at each trail knot, pooled over the
            calibration's samples: the gate ``halfwidth_max`` reads it (the error is partly a noise floor, partly
            proportional to mu: a band each).
        interval_at_trail: per band, the published interval's half-width at each trail knot: the 90th percentile of
            |mu error| on the calibration's worst road (each campaign and road friction on its own; never below the
            pooled one), meant to hold the true friction in 9 of 10 samples on every road, not only pooled over a
            mix that is mostly easy (empty: ``abs_err90_at_trail``, the older files' meaning).
        interval_max: the friction is given, or held, only where its published half-width (a held one's widened as
            held) is at most this: an interval wider than that says the trail cannot tell the road there (unknown,
            not a guess; inf: no such limit, the older files' meaning).
        evidence_long_ratio: the trail's utilisation curve, the limit's evidence (not the friction), is also read
            while the longitudinal force is up to this times the load (above ``max_long_ratio``, where the friction
            is not read): a trail that collapses under drive or braking still says the tyres near their limit
            (the curve of pure side slip reads the total utilisation low there up to about 0.35, and high beyond
            under drive: see the README). At most ``max_long_ratio`` (0, the older files' meaning): the trail counts
            no further than where the friction is read.
        max_force_rate: the friction is given only while the axle force ratio changes slower than this (1/s):
            in a fast transient the force from the accelerations and the SAT are not in step.
        max_long_ratio: the trail is read for the friction only while the axle's longitudinal force is at most this
            times its load (the brush model's trail is that of pure side slip; drive or brake torque moves it; the
            warning's evidence reads it further, ``evidence_long_ratio``).
        steer_ratio, understeer_s2pm2: the linear car (steering ratio; understeer gradient K, s^2/m^2): the
            lateral acceleration the steering asks for, ``vx^2 delta / (L (1 + K vx^2))``.
        kappa_limit: front longitudinal slip (wheel speeds against the front axle's speed, see
            :meth:`GripEstimator._slip`) taken as the longitudinal limit.
        rel_err_max: largest calibrated relative friction error (at the trail) with which it is given.
        halfwidth_max: the friction is given (and held) only where the pooled error ``abs_err90_at_trail`` (widened
            as held) is at most this.
        mu_max: the friction estimate is clipped to [0.05, mu_max].
        warn_on, warn_off: utilisation thresholds of the warning (hysteresis).
        warn_horizon_s: the warning looks this far ahead along the utilisation's rate of rise.
        warn_hold_s: the warning stays on at least this long below ``warn_off``.
        mu_hold_s: for this long after a friction is given, the force used against it (``n / mu_ref``) counts
            for the warning too (the road may change after that).
        demand_weight: the warning also looks at the driver's demand (:meth:`GripEstimator._demand`) times this
            (0: not).
        hold_count, hold_m, hold_widen_per_m, hold_min_use: the held friction (see the module docstring): the
            median of this many latest given estimates, given on for this many metres after the latest (0: not
            held), its half-width grown this much per metre, while ``n >= hold_min_use * mu``.
        hold_err90: per band of ``mu_bands``, the 90th percentile of the held friction's absolute error on the
            calibration's data (the median of ``hold_count`` readings errs less than one reading): the gate
            ``halfwidth_max`` reads it, widened as held, for a held friction. Empty (the older files' meaning): the
            gate reads the latest given reading's pooled error instead.
        mu_road_max: the highest road friction the car is rated for; ``n / mu_road_max`` is a floor of the
            warning's evidence (0: none), and the friction the driver's demand is set against where none is held.
        demand_lead_s: the steering's lateral demand looks this far ahead along its rate (s; 0: the steady state
            of the present steering only); default 0 keeps older calibration files' meaning.
        demand_mu_held: 1: the demand is set against the held friction plus its pooled error while held (else the
            rated ``mu_road_max``); 0: always against ``mu_road_max`` (a wrong held friction then cannot raise a
            warning through the demand).
        load_transfer: the load each front tyre gains (outer) or loses (inner) per newton of front lateral force
            (measured on the fit data from the simulator's wheel loads): the force floor and the demand are those
            of the more used tyre (0: the axle's, as older files).
        evidence_mu_held: 1: while a friction is held, the more used tyre's force ratio over the held friction plus
            its pooled error is evidence of the limit too (a wet road once measured: the combined-slip
            corner the trail cannot read is seen by the force it already uses of that road's grip); 0: not (the
            older files' meaning).
        pressure_nominal_pa, trail_pressure_coeff: the front tyres' inflation pressure (gauge, Pa) of the
            calibration's data, and the pneumatic trail's relative change per relative pressure change (MF 6.1
            ``PPZ1``: the trail's peak ``Dt`` scales with ``1 - PPZ1 dpi``, ``dpi = (p - p0) / p0``). Where the
            front pressures are known (TPMS), the measured trail is read at the calibration's pressure,
            ``t / (1 - PPZ1 dpi)``; unknown, or a coefficient of 0 (the older files' meaning): as measured.
        pressure_grid_pa, trail_at_pressure, peak_at_pressure: the front tyre's own curves at other pressures (from
            its property file, not fitted; empty: the older files' ``PPZ1`` scale above). Per ascending pressure
            (gauge, Pa), the trail (m) at which the tyre is in the same slip state as at each knot of ``trail_m``
            at the calibration's pressure (strictly ascending), and its peak lateral force relative to the
            calibration's. The pressure moves the trail's length (``PPZ1``) and the cornering stiffness
            (``PPY1``, ``PPY2``: the slip angle, hence how far the trail has collapsed, at a given share of the
            peak) and the peak friction (``PPY3``, ``PPY4``). Where the front pressures are known and the SAT model
            reads them (its SATs then carry the pressure's whole effect on the trail), the trail is located on that
            pressure's knots (linear between grid pressures, held beyond the grid) and the utilisation and
            force-ratio curves are scaled by its peak. A model that does not read them carries only part of it
            (it learns the trail of the pressures it was trained on, at the slip its inputs show): for its SATs the
            ``PPZ1`` scale above (see the README, "The tyre pressure").
        source: where the numbers come from (free text).
    """

    mass_kg: float
    wheelbase_m: float
    front_load_fraction: float
    cg_height_m: float
    yaw_inertia_kgm2: float
    gear_ratio: float
    rolling_radius_m: float
    brake_front_share: float
    drag_n_per_m2ps2: float
    filter_s: float
    min_force_ratio: float
    max_force_rate: float
    max_long_ratio: float
    steer_ratio: float
    understeer_s2pm2: float
    kappa_limit: float
    trail_m: tuple[float, ...]
    util_at_trail: tuple[float, ...]
    use_at_trail: tuple[float, ...]
    rel_err90_at_trail: tuple[float, ...]
    mu_bands: tuple[float, ...]
    abs_err90_at_trail: tuple[tuple[float, ...], ...]
    rel_err_max: float
    halfwidth_max: float
    mu_max: float
    warn_on: float
    warn_off: float
    warn_horizon_s: float
    warn_hold_s: float
    demand_weight: float
    mu_hold_s: float
    mu_road_max: float
    hold_m: float
    hold_widen_per_m: float
    hold_min_use: float
    hold_count: float
    demand_lead_s: float = 0.0
    demand_mu_held: float = 0.0
    load_transfer: float = 0.0
    evidence_mu_held: float = 0.0
    interval_at_trail: tuple[tuple[float, ...], ...] = ()
    interval_max: float = math.inf
    evidence_long_ratio: float = 0.0
    pressure_nominal_pa: float = 0.0
    trail_pressure_coeff: float = 0.0
    pressure_grid_pa: tuple[float, ...] = ()
    trail_at_pressure: tuple[tuple[float, ...], ...] = ()
    peak_at_pressure: tuple[float, ...] = ()
    hold_err90: tuple[float, ...] = ()
    source: str = ""

    def __post_init__(self) -> None:
        k = len(self.trail_m)
        if k < 2 or any(len(c) != k for c in (self.util_at_trail, self.use_at_trail, self.rel_err90_at_trail)):
            raise ValueError("grip params: trail_m and its curves need >= 2 knots each, as many of each")
        if not self.mu_bands or len(self.abs_err90_at_trail) != len(self.mu_bands) or any(
                len(c) != k for c in self.abs_err90_at_trail):
            raise ValueError("grip params: one abs_err90_at_trail curve per mu band, a value per trail knot")
        if self.interval_at_trail and (len(self.interval_at_trail) != len(self.mu_bands) or any(
                len(c) != k for c in self.interval_at_trail)):
            raise ValueError("grip params: interval_at_trail needs a curve per mu band, a value per trail knot")
        if any(not 0.0 <= x < math.inf for c in self.interval_at_trail for x in c):
            raise ValueError("grip params: interval_at_trail values must be finite and >= 0")
        if self.hold_err90 and (len(self.hold_err90) != len(self.mu_bands) or any(
                isinstance(x, bool) or not 0.0 <= x < math.inf for x in self.hold_err90)):
            raise ValueError("grip params: hold_err90 needs a finite value >= 0 per mu band")
        if not self.interval_max > 0.0:  # (also refuses nan)
            raise ValueError("grip params: interval_max must be > 0 (inf: no limit)")
        if not (0.0 <= self.trail_pressure_coeff < 2.0 and 0.0 <= self.pressure_nominal_pa < math.inf) or (
                self.trail_pressure_coeff > 0.0 and self.pressure_nominal_pa <= 0.0):
            raise ValueError("grip params: need 0 <= trail_pressure_coeff < 2 and a pressure_nominal_pa > 0 with it")
        self._check_pressure_curves(k)
        if not 0.0 <= self.evidence_long_ratio < math.inf:  # (also refuses nan)
            raise ValueError("grip params: evidence_long_ratio must be finite and >= 0")
        if min(self.use_at_trail) <= 0:
            raise ValueError("grip params: use_at_trail must be > 0")
        if any(b <= a for a, b in zip(self.trail_m, self.trail_m[1:], strict=False)):
            raise ValueError("grip params: trail_m must be strictly ascending")
        if any(b > a for a, b in zip(self.util_at_trail, self.util_at_trail[1:], strict=False)):
            raise ValueError("grip params: util_at_trail must not increase with the trail")
        if not 0.0 < self.warn_off <= self.warn_on <= 1.0:
            raise ValueError("grip params: need 0 < warn_off <= warn_on <= 1")
        if self.filter_s < 0 or self.mass_kg <= 0 or self.wheelbase_m <= 0 or not 0 < self.front_load_fraction < 1:
            raise ValueError("grip params: filter_s >= 0, mass and wheelbase > 0, 0 < front_load_fraction < 1")

    def _check_pressure_curves(self, k: int) -> None:
        g, rows, peaks = self.pressure_grid_pa, self.trail_at_pressure, self.peak_at_pressure
        if not (g or rows or peaks):
            return
        if len(g) < 2 or len(rows) != len(g) or len(peaks) != len(g) or any(len(r) != k for r in rows):
            raise ValueError("grip params: pressure_grid_pa needs >= 2 pressures, a trail_at_pressure row (a value "
                             "per trail knot) and a peak_at_pressure value each")
        if not (all(0.0 < x < math.inf for x in g) and all(b > a for a, b in zip(g, g[1:], strict=False))):
            raise ValueError("grip params: pressure_grid_pa must be finite, > 0 and strictly ascending")
        if not all(0.0 < x < math.inf for x in peaks):
            raise ValueError("grip params: peak_at_pressure values must be finite and > 0")
        if any(isinstance(x, bool) for x in (*g, *peaks, *(v for r in rows for v in r))):
            raise ValueError("grip params: pressure_grid_pa, trail_at_pressure and peak_at_pressure hold numbers, "
                             "not true/false")
        j = next((i for i, x in enumerate(g) if abs(x - self.pressure_nominal_pa) <= 1e-6 * x), None)
        if j is None or abs(peaks[j] - 1.0) > 1e-6 or any(
                abs(a - b) > 1e-9 for a, b in zip(rows[j], self.trail_m, strict=True)):
            raise ValueError("grip params: pressure_grid_pa must hold pressure_nominal_pa, where the curves are the "
                             "calibration's own (trail_at_pressure the trail_m knots, peak_at_pressure 1)")
        if not all(math.isfinite(a) and math.isfinite(b) and b > a
                   for r in rows for a, b in zip(r, r[1:], strict=False)):
            raise ValueError("grip params: each trail_at_pressure row must be finite and strictly ascending")

    @classmethod
    def from_json(cls, doc: Mapping[str, Any], where: str = "grip params") -> GripParams:
        """Parameters from a JSON object (every field, lists for the curves). Raises UserError naming ``where``."""
        try:
            kw: dict[str, Any] = {f.name: _tuples(doc[f.name]) for f in fields(cls)
                                  if f.name in doc or f.name not in _OPTIONAL}
            return cls(**kw)
        except (KeyError, TypeError, ValueError) as exc:
            raise UserError(f"{where}: not usable grip parameters ({exc})") from None

    def to_json(self) -> dict[str, Any]:
        """The parameters as a JSON object (strict JSON: an unlimited ``interval_max`` is left out, its default)."""
        doc = asdict(self)
        if math.isinf(doc["interval_max"]):
            del doc["interval_max"]
        return json.loads(json.dumps(doc, allow_nan=False))  # (tuples -> lists)


#: fields a parameter file may leave out (their defaults: the older files' meaning)
_OPTIONAL = ("source", "demand_lead_s", "demand_mu_held", "load_transfer", "evidence_mu_held", "interval_at_trail",
             "interval_max", "evidence_long_ratio", "pressure_nominal_pa", "trail_pressure_coeff", "pressure_grid_pa",
             "trail_at_pressure", "peak_at_pressure", "hold_err90")


def _tuples(v: Any) -> Any:
    """JSON lists (nested) as tuples of floats; other values as they are."""
    return tuple(_tuples(x) for x in v) if isinstance(v, list) else (float(v) if isinstance(v, int) and
                                                                      not isinstance(v, bool) else v)


def load_params(path: str | Path | None = None) -> GripParams:
    """The grip parameters in ``path`` (JSON), or the catalogue car's shipped with the package."""
    if path is None:
        with as_file(files("virtsensor") / PARAMS_FILE) as p:
            return load_params(Path(p))
    from virtsensor.fileio import read_json

    return GripParams.from_json(read_json(path, "grip parameters"), str(path))


def _locate(x: float, xs: Sequence[float]) -> tuple[int, float]:
    """``(i, w)`` with ``x`` at ``xs[i] + w (xs[i + 1] - xs[i])``, ``0 <= w <= 1``, held beyond the ends: every
    curve on the knots ``xs`` is then ``ys[i] + w (ys[i + 1] - ys[i])`` (one search for all of them)."""
    if x <= xs[0]:
        return 0, 0.0
    if x >= xs[-1]:
        return len(xs) - 2, 1.0
    i = bisect.bisect_right(xs, x) - 1
    return i, (x - xs[i]) / (xs[i + 1] - xs[i])


@dataclass
class GripState:
    """One tick's grip estimate.

    Attributes:
        util: front-axle friction utilisation in [0, 1] (nan before the first complete tick).
        mu: road friction, or nan when unknown (not excited enough). halfwidth: its interval half-width (nan
            with it). warning: the grip-limit warning. trail_m: the filtered axle trail where it is read for the
            friction (within ``max_long_ratio``; else nan, also where it serves the evidence only).
        force_ratio: ``|F| / Fz`` of the front axle (filtered).
        held: the friction given is the held one (read on earlier ticks), not one read on this tick.
    """

    util: float = math.nan
    mu: float = math.nan
    halfwidth: float = math.nan
    warning: bool = False
    trail_m: float = math.nan
    force_ratio: float = math.nan
    held: bool = False


class GripEstimator:
    """The per-tick grip estimate (see the module docstring). Feed :meth:`step` once per 20 Hz tick, in order.

    The returned :class:`GripState` is one object updated in place (no allocation per tick); copy what you keep.
    """

    def __init__(self, params: GripParams | None = None, dt: float = 0.05, sat_reads_pressure: bool = False) -> None:
        p = self.params = params if params is not None else load_params()
        #: the SATs come from a model that reads the front TPMS pressures: a known pressure is read on the tyre's own
        #: curves at that pressure (where the calibration has them), else by the ``PPZ1`` scale
        self.sat_reads_pressure = bool(sat_reads_pressure)
        self._curves = self.sat_reads_pressure and bool(p.pressure_grid_pa)
        self.dt = float(dt)
        L = p.wheelbase_m
        b = p.front_load_fraction * L  # CG to rear axle
        self._fy_ay = p.mass_kg * b / L
        self._fy_rdot = p.yaw_inertia_kgm2 / L
        self._fz0 = p.mass_kg * G * b / L
        self._fz_ax = p.mass_kg * p.cg_height_m / L
        self._drive = p.gear_ratio / p.rolling_radius_m
        self._steer_l = p.steer_ratio * L
        self._dem_rate = p.demand_lead_s / self.dt  # (the demand's look-ahead per tick difference)
        self._dem_held = p.demand_mu_held > 0.0
        self._ev_held = p.evidence_mu_held > 0.0
        self._lt = p.load_transfer
        #: the most the CAN resolutions put on the front axle's speed difference w r - v (m/s): half a step each
        self._slip_q = 0.5 * (p.rolling_radius_m * SIGNALS["wheel_speed_fl_radps"].resolution
                              + SIGNALS["vx_mps"].resolution)
        self._a = 1.0 - math.exp(-self.dt / p.filter_s) if p.filter_s > 0 else 1.0
        #: ticks back inside the model's envelope before a friction is read again: the filtered SAT then weighs the
        #: SATs from outside by at most exp(-3) (5 %)
        self.settle_ticks = math.ceil(3.0 * p.filter_s / self.dt - 1e-9) if p.filter_s > 0 else 0
        self._trail, self._util = tuple(p.trail_m), tuple(p.util_at_trail)
        self._err, self._use = tuple(p.rel_err90_at_trail), tuple(p.use_at_trail)
        self._nominal = self._trail, self._util, self._use  # (the calibration pressure's knots and curves)
        self._pressure = math.nan  # (the pressure the knots and curves are set for; nan: the calibration's)
        #: the tyre's peak lateral force at the pressure set relative to the calibration's (the curves' scale)
        self.peak_ratio = 1.0
        self._curve_cache: dict[float, tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...], float]] = {}
        self._bands, self._abs = tuple(p.mu_bands), tuple(tuple(c) for c in p.abs_err90_at_trail)
        self._pub = tuple(tuple(c) for c in p.interval_at_trail) if p.interval_at_trail else self._abs
        self.state = GripState()
        self._trail_gain = 1.0
        self.reset()

    @property
    def forces(self) -> tuple[float, float, float, float]:
        """The filtered front-axle forces of the latest tick: ``(Fx, Fy, Fz)`` (N) and the SAT sum ``Mz`` (Nm), ISO
        body axes (nan before the first tick); what the trail and the gates read."""
        return self._fx, self._fy, self._fz, self._mz

    def reset(self) -> None:
        """Forget the filters and the warning (after an invalid tick); keeps the last given friction."""
        self._mz = self._fy = self._fx = self._fz = math.nan
        self._settle = 0  # (ticks before a friction is read again: the SAT filter still holds extrapolated SATs)
        self._r_prev = math.nan
        self._ay_lin_prev = math.nan
        self._u_prev = math.nan
        self._rate = 0.0
        self._below = 0.0
        self.state.warning = False
        if not hasattr(self, "mu_ref"):
            #: the friction assumed for the utilisation where the trail cannot tell: the latest given one plus its
            #: pooled error (1 until one is given)
            self.mu_ref = 1.0
            self._mu_age = math.inf
            #: the latest given friction, its half-width and the distance travelled since (m)
            self._mu_held, self._hw_held, self._held_m = math.inf, math.inf, math.inf
            self._hwp_held = math.inf  # (the published half-width of the latest given)
            self._err_held = math.inf  # (the held median's calibrated error, hold_err90 of its band)
            self._recent: deque[float] = deque(maxlen=max(int(self.params.hold_count), 1))
            self._fresh = MEDIAN_EVERY  # (given estimates since the held median was last taken)

    def set_front_pressure(self, pressure_pa: float) -> None:
        """The front tyres' mean inflation pressure (gauge, Pa; nan: unknown) for the following steps. For SATs of a
        model that reads the pressures (``sat_reads_pressure``) and a calibration with the tyre's own curves
        (``GripParams.pressure_grid_pa``): the trail is located on that pressure's knots and the curves scaled by
        its peak (set again only when the pressure changes). Else the measured trail is read at the calibration's
        pressure, ``t / (1 - PPZ1 dpi)`` (``GripParams.trail_pressure_coeff``, ``pressure_nominal_pa``; the factor
        ``1 - PPZ1 dpi`` held at 0.25 or more, a tyre far above its rated pressure). Unknown, or a calibration
        with neither: the trail as measured, on the calibration's curves."""
        p = self.params
        if self._curves:
            if pressure_pa != self._pressure and (pressure_pa > 0.0 or self._pressure == self._pressure):
                self._set_curves(pressure_pa if pressure_pa > 0.0 else math.nan)
            return
        if p.trail_pressure_coeff > 0.0 and pressure_pa > 0.0:  # (nan fails the comparison: unknown)
            f = 1.0 - p.trail_pressure_coeff * (pressure_pa - p.pressure_nominal_pa) / p.pressure_nominal_pa
            self._trail_gain = 1.0 / max(f, 0.25)
        else:
            self._trail_gain = 1.0

    def _set_curves(self, pressure_pa: float) -> None:
        """The knots and curves at ``pressure_pa`` (nan: the calibration's), linear between grid pressures; kept
        per pressure (a TPMS reports few distinct values: a tick that sees one again computes nothing)."""
        self._pressure = pressure_pa
        if pressure_pa != pressure_pa:
            self._trail, self._util, self._use = self._nominal
            self.peak_ratio = 1.0
            return
        got = self._curve_cache.get(pressure_pa)
        if got is None:
            p = self.params
            j, w = _locate(pressure_pa, p.pressure_grid_pa)
            lo, hi = p.trail_at_pressure[j], p.trail_at_pressure[j + 1]
            r = p.peak_at_pressure[j] + w * (p.peak_at_pressure[j + 1] - p.peak_at_pressure[j])
            got = (tuple(a + w * (b - a) for a, b in zip(lo, hi, strict=True)),
                   tuple(r * u for u in self._nominal[1]), tuple(r * u for u in self._nominal[2]), r)
            if len(self._curve_cache) >= CURVE_CACHE_SIZE:
                self._curve_cache.clear()
            self._curve_cache[pressure_pa] = got
        self._trail, self._util, self._use, self.peak_ratio = got

    def _nominal_trail(self, t: float, i: int, w: float) -> float:
        """The trail ``t`` (m), located at ``(i, w)`` on the present knots, as the tyre at the calibration's pressure
        has it in the same slip state (beyond the knots: the same distance to the end knot)."""
        k, kp = self._nominal[0], self._trail
        if t <= kp[0] or t >= kp[-1]:
            e = 0 if t <= kp[0] else -1
            return t - kp[e] + k[e]
        return k[i] + w * (k[i + 1] - k[i])

    def _lp(self, prev: float, x: float) -> float:
        return x if prev != prev else prev + self._a * (x - prev)  # (prev != prev: nan, the first tick)

    def step(self, sat_fl: float, sat_fr: float, ax: float, ay: float, vx: float, yaw_rate: float,
             steer_angle: float, motor_torque: float, wheel_fl: float, wheel_fr: float,
             outside: bool = False) -> GripState:
        """One tick: estimated SATs (Nm, ISO-W), ``ax``/``ay`` (m/s^2), ``vx`` (m/s), yaw rate (rad/s),
        steering-wheel angle (rad), motor torque (Nm), front wheel speeds (rad/s); ``outside``: the SATs' model
        read inputs outside its validity envelope this tick (an extrapolation).

        A non-finite SAT or input gives a state of nans (no warning) and restarts the filters. From SATs
        ``outside`` no friction is read (a friction held from before is still given), nor for
        :attr:`settle_ticks` ticks back inside, while the SAT filter still weighs them (more than 5 %); the trail
        still counts as the limit's evidence for the warning throughout (the filter runs on: a restart would read
        one tick's raw SAT)."""
        s = self.state
        mz = sat_fl + sat_fr
        if not math.isfinite(mz + ax + ay + vx + yaw_rate + steer_angle + motor_torque + wheel_fl + wheel_fr):
            self.reset()
            s.util = s.mu = s.halfwidth = s.trail_m = s.force_ratio = math.nan
            s.held = False
            return s
        p = self.params
        rdot = 0.0 if self._r_prev != self._r_prev else (yaw_rate - self._r_prev) / self.dt
        self._r_prev = yaw_rate
        fx = motor_torque * self._drive  # the front drive (or regenerative) force; then the brakes' front share
        fx += p.brake_front_share * min(p.mass_kg * ax + p.drag_n_per_m2ps2 * vx * vx - fx, 0.0)
        fx_now = fx
        fy_prev = self._fy
        if outside:
            blocked, self._settle = True, self.settle_ticks
        else:
            blocked, self._settle = self._settle > 0, max(self._settle - 1, 0)
        self._mz = mz = self._lp(self._mz, mz)
        self._fy = fy = self._lp(self._fy, self._fy_ay * ay + self._fy_rdot * rdot)
        self._fx = fx = self._lp(self._fx, fx)
        self._fz = fz = self._lp(self._fz, max(self._fz0 - self._fz_ax * ax, 0.2 * self._fz0))
        n = math.sqrt(fx * fx + fy * fy) / fz
        s.force_ratio = n
        steady = fy_prev == fy_prev and abs(fy - fy_prev) <= p.max_force_rate * fz * self.dt
        lateral = abs(fx) <= p.max_long_ratio * fz  # (under drive or braking the trail reads combined slip)
        ev = 0.0  # the limit's own evidence, whatever the road: the trail's collapse, the wheels' slip
        if lateral and abs(fy) >= p.min_force_ratio * fz and not blocked:
            ev = self._read_trail(n, -mz / fy * self._trail_gain, steady)
        else:
            s.trail_m = s.mu = s.halfwidth = math.nan
            if abs(fx) <= p.evidence_long_ratio * fz and abs(fy) >= p.min_force_ratio * fz:
                ev = self._evidence(-mz / fy * self._trail_gain)[2]  # (combined slip: the evidence only, no friction)
        self._held_m += abs(vx) * self.dt  # (the distance driven, reversing included)
        s.held = False
        if s.mu != s.mu and self._held_m <= p.hold_m and n >= p.hold_min_use * self._mu_held:
            widen = p.hold_widen_per_m * self._held_m  # (the road met since may differ)
            err = self._err_held if p.hold_err90 else self._hw_held
            if err + widen <= p.halfwidth_max and self._hwp_held + widen <= p.interval_max:
                s.mu, s.halfwidth, s.held = self._mu_held, self._hwp_held + widen, True
        ev = max(ev, self._slip(vx, yaw_rate, steer_angle, wheel_fl + wheel_fr, fx_now))
        self._mu_age += self.dt
        u_force = n / self.mu_ref
        if self._mu_age <= p.mu_hold_s:  # a friction given lately: the force used against it is evidence too
            ev = max(ev, u_force)
        tyre = self._tyre_ratio(fx, fy, fz)
        if p.mu_road_max > 0.0:  # whatever the road, the more used tyre uses at least n_tyre / mu_road_max of it
            ev = max(ev, tyre / p.mu_road_max)
        if self._ev_held and self._held_m <= p.hold_m:  # and of a road measured lately, its held upper end's share
            ev = max(ev, tyre / (self._mu_held + self._hw_held + p.hold_widen_per_m * self._held_m))
        ev = min(ev, 1.0)
        u = min(max(u_force, ev), 1.0)
        s.util = u
        self._warn(ev, self._demand(vx, steer_angle, fx_now, fz))
        return s

    def _slip(self, vx: float, yaw_rate: float, steer_angle: float, wheels: float, fx: float) -> float:
        """The front wheels' longitudinal slip as evidence of the limit (a driven wheel spinning or a wheel locking),
        ``max(|kappa| - e, 0) / kappa_limit`` where the slip is in the direction of this tick's front longitudinal
        force ``fx`` (N; spin under drive, lock under braking: a wheel that runs ahead of the car while no torque
        drives it, as in its spin-up oscillation when the brakes release, is no tyre at its limit), 0 otherwise or
        where it cannot be read.

        ``kappa = w r / v_w - 1`` with ``w`` the mean front wheel speed (``wheels`` is the sum of the two, rad/s) and
        ``v_w = vx cos(d) + L r sin(d)`` the front axle's speed along its wheels (``d`` the road-wheel angle, the
        steering angle over the steering ratio; a rigid car whose rear axle, where the ESC's ``vx`` is measured,
        rolls along its heading): in a tight turn the front axle runs on a wider circle than the rear, ``1 / cos d``
        faster (4 % at 0.28 rad), which is no slip. ``e = (r q_w + q_v) / (2 v_w)`` is the most the signals' CAN
        resolutions (``q_w`` wheel speed, ``q_v`` speed, :mod:`virtsensor.signals`) can put on ``kappa``; the slip
        is read only where that floor is below ``kappa_limit`` (moving forward)."""
        p = self.params
        d = steer_angle / p.steer_ratio
        vw = vx * math.cos(d) + p.wheelbase_m * yaw_rate * math.sin(d)
        floor = self._slip_q / vw if vw > 0.0 else math.inf
        if floor >= p.kappa_limit:
            return 0.0
        kappa = 0.5 * wheels * p.rolling_radius_m / vw - 1.0
        if kappa * fx <= 0.0:
            return 0.0
        return max(abs(kappa) - floor, 0.0) / p.kappa_limit

    def _tyre_ratio(self, fx: float, fy: float, fz: float) -> float:
        """The force ratio of the more used front tyre: the lateral load transfer ``load_transfer * |fy|`` off the
        inner tyre, the lateral force shared in proportion to load (the same ratio on both), the longitudinal one
        evenly (one brake pressure, an open differential), so the inner tyre's ratio is
        ``sqrt((fx / 2 / fz_in)^2 + (fy / fz)^2)`` (the axle's ``n`` without load transfer or longitudinal force)."""
        fz_in = max(0.5 * fz - self._lt * abs(fy), 0.05 * fz)
        a, b = 0.5 * fx / fz_in, fy / fz
        return math.sqrt(a * a + b * b)

    def _demand(self, vx: float, steer_angle: float, fx: float, fz: float) -> float:
        """The driver's demand on the front axle against the friction it may have: the linear car's steady-state
        lateral acceleration for this steering at this speed, ``ay_lin = vx^2 delta / (L (1 + K vx^2))``, looked
        ``demand_lead_s`` ahead along its rate (the tyres' force lags the steering by their relaxation and the
        car's yaw and sideslip), as front lateral force ``m b / L ay``, combined with this tick's longitudinal
        force ``fx`` (the motor torque's drive at once, the brakes' share), as the more used tyre's force ratio
        (:meth:`_tyre_ratio`, from the axle load ``fz``), over the friction:
        the held one's upper end while held if ``demand_mu_held``, else the rated ``mu_road_max`` (a road never
        measured is not assumed wet: the demand then warns only of what no road gives)."""
        v2 = vx * vx
        ay_lin = v2 * steer_angle / (self._steer_l * (1.0 + self.params.understeer_s2pm2 * v2))
        prev, self._ay_lin_prev = self._ay_lin_prev, ay_lin
        if prev == prev:  # (nan on the first tick: no rate yet)
            ay_lin += self._dem_rate * (ay_lin - prev)
        mu = self.mu_ref if self._dem_held and self._held_m <= self.params.hold_m else self.params.mu_road_max
        return self._tyre_ratio(fx, self._fy_ay * ay_lin, fz) / mu if mu > 0.0 else 0.0

    def _evidence(self, t: float) -> tuple[int, float, float]:
        """``(i, w, u)``: the trail ``t`` (m) located on the knots (:func:`_locate`) and the lateral utilisation the
        calibrated curve gives there (the limit's evidence)."""
        i, w = _locate(t, self._trail)
        c = self._util
        return i, w, c[i] + w * (c[i + 1] - c[i])

    def _read_trail(self, n: float, t: float, steady: bool) -> float:
        """The trail ``t`` (m) read: sets the state's trail and friction (given or nan), returns the evidence
        (the lateral utilisation at that trail)."""
        p, s = self.params, self.state
        i, w, ev = self._evidence(t)
        s.trail_m = t if self._trail is self._nominal[0] else self._nominal_trail(t, i, w)
        c = self._use
        mu = n / (c[i] + w * (c[i + 1] - c[i]))
        c = self._err
        rel = c[i] + w * (c[i + 1] - c[i])
        b = min(bisect.bisect_left(self._bands, mu), len(self._abs) - 1)
        c = self._abs[b]
        hw = c[i] + w * (c[i + 1] - c[i])
        if steady and rel <= p.rel_err_max and hw <= p.halfwidth_max and mu <= p.mu_max and (
                (hwp := self._pub[b][i] + w * (self._pub[b][i + 1] - self._pub[b][i])) <= p.interval_max):
            s.mu, s.halfwidth = mu, hwp
            self.mu_ref = mu + hw  # (the upper end of the pooled error: a utilisation not overstated by it)
            self._mu_age = 0.0
            r = self._recent
            r.append(mu)
            self._fresh += 1
            self._hw_held, self._hwp_held, self._held_m = hw, s.halfwidth, 0.0
            if len(r) == r.maxlen and self._fresh >= MEDIAN_EVERY:  # hold the median of the latest given (robust
                self._mu_held, self._fresh = sorted(r)[len(r) // 2], 0  # to a stray one; sorted every few ticks)
                self.mu_ref = self._mu_held + hw
                if p.hold_err90:
                    self._err_held = p.hold_err90[min(bisect.bisect_left(self._bands, self._mu_held),
                                                      len(self._bands) - 1)]
        else:
            s.mu = s.halfwidth = math.nan
        return ev

    def _warn(self, u: float, demand: float) -> None:
        p, s = self.params, self.state
        if self._u_prev == self._u_prev:
            self._rate += self._a * ((u - self._u_prev) / self.dt - self._rate)
        self._u_prev = u
        rise = max(self._rate, 0.0) * p.warn_horizon_s if u >= p.warn_off else 0.0  # (look ahead near the limit)
        ahead = max(u + rise, demand * p.demand_weight)
        if ahead >= p.warn_on:
            s.warning = True
            self._below = 0.0
        elif s.warning and u < p.warn_off:
            self._below += self.dt
            if self._below >= p.warn_hold_s:
                s.warning = False
        else:
            self._below = 0.0


def reads_pressure(model_signals: Iterable[str]) -> bool:
    """Whether a SAT model with these input signals reads both front TPMS pressures (:data:`PRESSURE_INPUTS`)."""
    have = set(model_signals)
    return all(s in have for s in PRESSURE_INPUTS)


def front_pressure(table: Mapping[str, Any], n: int) -> np.ndarray:
    """Per row, the mean of a run's two front TPMS pressures (gauge, Pa; :data:`PRESSURE_INPUTS`), nan where either
    is unknown or the table has none (the estimate then reads the trail as measured)."""
    if not all(k in table for k in PRESSURE_INPUTS):
        return np.full(n, np.nan)
    return 0.5 * (np.asarray(table[PRESSURE_INPUTS[0]], float) + np.asarray(table[PRESSURE_INPUTS[1]], float))


def estimate_run(table: Mapping[str, np.ndarray], sat_fl: np.ndarray, sat_fr: np.ndarray,
                 params: GripParams | None = None, sat_reads_pressure: bool = False,
                 outside: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The grip estimate over one run's 20 Hz table (rows in time order), tick by tick with the daemon's code.

    Args:
        table: the run's columns of the estimator inputs :meth:`GripEstimator.step` reads (catalogue names), and
            the front TPMS pressures where it has them (:func:`front_pressure`).
        sat_fl, sat_fr: the estimated front SATs per row (Nm; nan where the model gave none).
        sat_reads_pressure: the SATs come from a model that reads the front TPMS pressures
            (:func:`reads_pressure`; :class:`GripEstimator`).
        outside: per row, the SATs' model read inputs outside its validity envelope (as the daemon judges it,
            :func:`virtsensor.learning.gripscore.model_outside`; None: never): no friction is read there.

    Returns:
        ``util``, ``mu``, ``halfwidth`` (nan where unknown), ``warning`` and ``held`` (bool: the friction given is
        the held one, :attr:`GripState.held`), ``trail_m``, ``force_ratio``, and
        ``peak_ratio``: the tyre's peak lateral force at the tick's pressure relative to the calibration's (1 where
        the pressure is unknown, the SATs' model does not read it or the calibration has no curves at other
        pressures; what the curves were scaled by, :meth:`GripEstimator.set_front_pressure`).
    """
    est = GripEstimator(params, sat_reads_pressure=sat_reads_pressure)
    ax, ay, vx, r, sw, tm, wl, wr = (np.asarray(table[k], dtype=float).tolist() for k in GRIP_INPUTS)
    n = len(sat_fl)
    press = front_pressure(table, n).tolist()
    out = {k: np.full(n, np.nan) for k in ("util", "mu", "halfwidth", "trail_m", "force_ratio", "peak_ratio")}
    warn, held = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
    fl, fr = np.asarray(sat_fl, float).tolist(), np.asarray(sat_fr, float).tolist()
    out_rows = [False] * n if outside is None else np.asarray(outside, dtype=bool).tolist()
    for i in range(n):
        est.set_front_pressure(press[i])
        s = est.step(fl[i], fr[i], ax[i], ay[i], vx[i], r[i], sw[i], tm[i], wl[i], wr[i], out_rows[i])
        out["util"][i], out["mu"][i], out["halfwidth"][i] = s.util, s.mu, s.halfwidth
        out["trail_m"][i], out["force_ratio"][i], out["peak_ratio"][i] = s.trail_m, s.force_ratio, est.peak_ratio
        warn[i], held[i] = s.warning, s.held
    out["warning"], out["held"] = warn, held
    return out
