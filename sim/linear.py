"""The linear single-track (bicycle) model built from the same parameters.

Used to size open-loop steering amplitudes (the steering-wheel angle that gives
a wanted lateral acceleration) and as the reference the full model must match
in the linear range (understeer gradient, acceptance test).

Axle cornering stiffnesses come from the MF 6.1 tyre at the static wheel loads,
static camber and inflation pressure (slope of Fy at zero slip). The model also
carries the two linear effects the full model has at small lateral
acceleration: the pneumatic trails (the tyres' aligning torque moves each
axle's lateral force behind the axle) and roll camber (the body's roll leans
the wheels, whose camber thrust adds to the slip force).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim.tyre import MagicFormula61
from sim.vehicle import tyre_for


@dataclass(frozen=True)
class LinearModel:
    """Linear single-track model; all stiffnesses positive, SI units.

    Attributes:
        mass_kg, wheelbase_m, a_m, b_m: mass, wheelbase, CG to front/rear axle.
        c_front, c_rear: axle cornering stiffness (N/rad), both tyres.
        trail_front_m, trail_rear_m: pneumatic trail at zero slip (m).
        camber_thrust_front, camber_thrust_rear: lateral force per m/s^2 of
            lateral acceleration from roll camber, whole axle (N s^2/m), + outward.
        alignment_front, alignment_rear: lateral force per m/s^2 from the static
            toe and camber forces of the two tyres, which no longer cancel once
            lateral load transfer loads the outer tyre (N s^2/m), + inward.
        rolling_moment: yaw moment per m/s^2 from rolling resistance under lateral
            load transfer (the loaded outer wheels roll harder), + out of the turn (N m s^2/m).
        roll_gradient: body roll per lateral acceleration (rad per m/s^2).
        ratio: steering ratio (steering-wheel angle / road-wheel angle).
    """

    mass_kg: float
    wheelbase_m: float
    a_m: float
    b_m: float
    c_front: float
    c_rear: float
    trail_front_m: float
    trail_rear_m: float
    camber_thrust_front: float
    camber_thrust_rear: float
    alignment_front: float
    alignment_rear: float
    rolling_moment: float
    roll_gradient: float
    ratio: float

    @property
    def understeer_gradient(self) -> float:
        """K in rad of road-wheel angle per m/s^2: delta = L/R + K * ay (steady state)."""
        af = self.a_m - self.trail_front_m
        br = self.b_m + self.trail_rear_m
        lp = af + br
        # yaw balance af * Fyf - br * Fyr = rolling_moment, lateral balance Fyf + Fyr = m ay
        fyf = (self.mass_kg * br + self.rolling_moment) / lp
        fyr = (self.mass_kg * af - self.rolling_moment) / lp
        per_ay_front = (fyf + self.camber_thrust_front - self.alignment_front) / self.c_front
        per_ay_rear = (fyr + self.camber_thrust_rear - self.alignment_rear) / self.c_rear
        return per_ay_front - per_ay_rear

    def road_wheel_angle(self, speed_mps: np.ndarray | float, ay_mps2: np.ndarray | float) -> np.ndarray:
        """Steady-state mean road-wheel angle (rad) for ``ay`` at ``speed``."""
        v = np.maximum(np.asarray(speed_mps, dtype=float), 1.0)
        ay = np.asarray(ay_mps2, dtype=float)
        return self.wheelbase_m * ay / (v * v) + self.understeer_gradient * ay

    def steering_wheel_angle(self, speed_mps: np.ndarray | float, ay_mps2: np.ndarray | float) -> np.ndarray:
        """Steady-state steering-wheel angle (rad) for ``ay`` at ``speed``."""
        return self.ratio * self.road_wheel_angle(speed_mps, ay_mps2)


def _alignment_load_sensitivity(tyre: MagicFormula61, fz: float, toe_in: float, camber: float,
                                pressure: float, kappa: float = 0.0) -> float:
    """d(axle lateral force)/d(load transfer) at zero slip from static toe and camber (N/N).

    The outer (here: right) tyre gains the load the inner one loses. Both tyres,
    the left one mirrored, see the right-hand tyre at alpha = -toe_in and the
    static camber; their static forces cancel only at equal loads.
    """
    dfz = 50.0
    f = np.array([fz + dfz, fz - dfz])
    out = tyre.steady_state(f, np.full(2, kappa), np.full(2, -toe_in), np.full(2, camber), np.full(2, 20.0),
                            np.full(2, pressure), 1.0)
    return float((out.fy[0] - out.fy[1]) / (2 * dfz)) * 2.0


def _axle_properties(tyre: MagicFormula61, fz: float, camber: float, pressure: float,
                     kappa: float = 0.0) -> tuple[float, float, float]:
    """(cornering stiffness N/rad, camber stiffness N/rad, pneumatic trail m) of one axle
    at longitudinal slip ``kappa`` (the drive slip of a driven axle)."""
    da = 2e-3
    a = np.array([-da, da])
    k = np.full(2, kappa)
    out = tyre.steady_state(np.full(2, fz), k, a, np.full(2, camber), np.full(2, 20.0),
                            np.full(2, pressure), 1.0)
    c = -(out.fy[1] - out.fy[0]) / (2 * da)  # ISO-W: Fy = -C * alpha
    cm = (out.mz[1] - out.mz[0]) / (2 * da)
    trail = cm / c
    dg = 2e-3
    g = np.array([camber - dg, camber + dg])
    outg = tyre.steady_state(np.full(2, fz), k, np.zeros(2), g, np.full(2, 20.0),
                             np.full(2, pressure), 1.0)
    c_gamma = (outg.fy[1] - outg.fy[0]) / (2 * dg)
    return 2.0 * c, 2.0 * c_gamma, trail


def linear_model(params: Mapping[str, Any], tyre: MagicFormula61 | None = None, *,
                 speed_mps: float = 15.0, accel_mps2: float = 0.0) -> LinearModel:
    """Build the linear single-track model of a parameter tree.

    The model is linearised about straight driving at ``speed_mps`` while
    accelerating at ``accel_mps2``: the front (driven) tyres then carry the
    traction for drag, rolling resistance and acceleration, and their drive slip
    changes their side-force and camber stiffnesses (MF combined slip).
    """
    v, s, ty, st = params["vehicle"], params["suspension"], params["tyres"], params["steering"]
    tyre_r = tyre or tyre_for(params, "rear")
    tyre = tyre or tyre_for(params)
    g = params["simulation"]["gravity_mps2"]
    m, L, frac = v["mass_kg"], v["wheelbase_m"], v["front_axle_load_fraction"]
    a, b = L * (1 - frac), L * frac
    fz_f = m * g * frac / 2
    aero = params["aero"]
    traction = (0.5 * aero["air_density_kgpm3"] * aero["drag_coefficient"] * aero["frontal_area_m2"] * speed_mps**2
                + float(tyre.params.get("QSY1", 0.01)) * m * g + m * accel_mps2)
    kxk, *_ = tyre.stiffnesses(fz_f, ty["pressure_front_pa"], ty["static_camber_front_rad"])
    kappa_f = float(traction / 2.0 / kxk)
    cf, cgf, tf = _axle_properties(tyre, fz_f, ty["static_camber_front_rad"], ty["pressure_front_pa"], kappa_f)
    cr, cgr, tr = _axle_properties(tyre_r, m * g * (1 - frac) / 2, ty["static_camber_rear_rad"],
                                   ty["pressure_rear_pa"])
    # roll gradient of the sprung mass about the roll axis
    mu_f, mu_r = v["unsprung_mass_front_kg"], v["unsprung_mass_rear_kg"]
    R0 = float(tyre.params["UNLOADED_RADIUS"])
    ms = m - 2 * (mu_f + mu_r)
    hs = (m * v["cg_height_m"] - 2 * (mu_f + mu_r) * R0) / ms
    hra = (v["roll_centre_height_front_m"] * b + v["roll_centre_height_rear_m"] * a) / L
    tf_w, tr_w = v["track_front_m"], v["track_rear_m"]
    k_roll = ((s["wheel_rate_front_npm"] + 2 * s["arb_front_npm"]) * tf_w**2
              + (s["wheel_rate_rear_npm"] + 2 * s["arb_rear_npm"]) * tr_w**2) / 2.0
    roll_grad = ms * (hs - hra) / (k_roll - ms * g * (hs - hra))
    # Roll leans both wheels' tops outward of the turn by f*phi. ISO-W: positive
    # camber tilts the top to -y and the thrust follows the lean (dFy/dgamma < 0),
    # so for both wheels the thrust points outward: it adds to the force the slip
    # angles must make.
    thrust_f = -cgf * s["camber_roll_factor_front"] * roll_grad
    thrust_r = -cgr * s["camber_roll_factor_rear"] * roll_grad
    # lateral load transfer per axle per m/s^2: elastic (roll stiffness share), geometric
    # (roll centre) and unsprung-mass parts, as in the full model
    k_f = (s["wheel_rate_front_npm"] + 2 * s["arb_front_npm"]) * tf_w**2 / 2.0
    k_r = (s["wheel_rate_rear_npm"] + 2 * s["arb_rear_npm"]) * tr_w**2 / 2.0
    lp = (a - tf) + (b + tr)
    fy_f, fy_r = m * (b + tr) / lp, m * (a - tf) / lp
    lt_f = (k_f * roll_grad + fy_f * v["roll_centre_height_front_m"] + 2 * mu_f * R0) / tf_w
    lt_r = (k_r * roll_grad + fy_r * v["roll_centre_height_rear_m"] + 2 * mu_r * R0) / tr_w
    al_f = _alignment_load_sensitivity(tyre, fz_f, ty["toe_in_front_rad"], ty["static_camber_front_rad"],
                                       ty["pressure_front_pa"], kappa_f) * lt_f / 2.0
    al_r = _alignment_load_sensitivity(tyre_r, m * g * (1 - frac) / 2, ty["toe_in_rear_rad"],
                                       ty["static_camber_rear_rad"], ty["pressure_rear_pa"]) * lt_r / 2.0
    f_rr = float(tyre.params.get("QSY1", 0.0))  # rolling resistance force / load
    rolling = f_rr * (tf_w * lt_f + tr_w * lt_r)
    return LinearModel(m, L, a, b, cf, cr, tf, tr, thrust_f, thrust_r, al_f, al_r, rolling, roll_grad, st["ratio"])
