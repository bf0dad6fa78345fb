"""Candidate effects: what a real car may do that the nominal simulator does not.

Each effect is a one-parameter extension of the simulator, expressed as
parameter overrides (``sim.params``), so that the same catalogue serves three
purposes:

* the hidden-effect generator makes "measured" runs of a car that has one of
  them (:mod:`virtsensor.diagnose.hidden`);
* the diagnosis identifies each one's parameter from measured data and names the
  best explanation (:mod:`virtsensor.diagnose.identify`);
* the calibration re-simulates the training campaign with the identified value.

The parameter of each effect is in engineering units (bar, kg, Nm, s, a factor),
with its nominal value (the default car), the bounds of the search and the
range a hidden effect is drawn from (realistic magnitudes: a tyre 0.4-0.8 bar off
its placard, a payload of two passengers and luggage, a steering-angle sensor
a few degrees off centre after an alignment, a gateway adding 40-200 ms...).

Sensor effects act on one of the 12 estimator inputs (``signal``); the reference
SAT (wheel-force transducers) is the yardstick and is taken as right.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim.params import apply_overrides

#: the catalogue before the steering ratio joined it: seeded draws made from it (the diagnosis study's cases, the
#: hidden-effect test) keep hiding what they hid
FIRST_CAUSES = ("tyre_pressure", "sensor_delay", "sensor_offset", "sensor_gain", "vehicle_mass",
                "steering_friction", "road_friction", "relaxation_length")
#: the causes, in report order (``none`` is the answer when nothing explains the data)
CAUSES = (*FIRST_CAUSES, "steering_ratio")

#: signals a sensor effect may sit on: the 12 estimator inputs (Table II order)
SENSOR_SIGNALS = ("ax_mps2", "ay_mps2", "vx_mps", "yaw_rate_radps", "steer_angle_rad", "steer_torque_nm",
                  "assist_torque_nm", "motor_torque_nm", "susp_defl_fl_m", "susp_defl_fr_m",
                  "wheel_speed_fl_radps", "wheel_speed_fr_radps")

#: realistic offset magnitudes per signal (lo, hi), in the signal's unit: a mounting
#: tilt of 1-2.5 deg for the IMU, a mis-centred steering-angle sensor, a torque
#: sensor's zero drift, a ride-height sensor re-fitted a few mm off...
OFFSET_RANGE: dict[str, tuple[float, float]] = {
    "ax_mps2": (0.15, 0.4), "ay_mps2": (0.15, 0.4), "vx_mps": (0.3, 0.8),
    "yaw_rate_radps": (0.006, 0.02), "steer_angle_rad": (0.02, 0.07), "steer_torque_nm": (0.3, 1.0),
    "assist_torque_nm": (0.6, 2.0), "motor_torque_nm": (6.0, 20.0), "susp_defl_fl_m": (0.003, 0.010),
    "susp_defl_fr_m": (0.003, 0.010), "wheel_speed_fl_radps": (0.4, 1.2), "wheel_speed_fr_radps": (0.4, 1.2),
}
GAIN_RANGE = (0.06, 0.15)      # |gain - 1|: a scale or tyre-radius calibration error
DELAY_RANGE = (0.05, 0.20)     # s: a gateway, a slow filter, a second-hand signal

#: signals the re-simulation is driven by: their sensor effects need a re-simulation
DRIVE_SIGNALS = ("steer_angle_rad", "vx_mps", "motor_torque_nm")

#: where a payload sits: behind the front axle (m, rear seats and boot) and its height
PAYLOAD_X_M = 2.0
PAYLOAD_Z_M = 0.55


@dataclass(frozen=True)
class Effect:
    """One candidate effect.

    Attributes:
        cause: its name in :data:`CAUSES`.
        unit: unit of the parameter.
        what: one line saying what the parameter is.
        nominal: the parameter's value in the default car (no effect).
        bounds: search bounds of the identification.
        hidden: (lo, hi) ranges of |value - nominal| a hidden effect is drawn from
            (sensor offsets: per signal, see :data:`OFFSET_RANGE`).
        floor: smallest deviation from nominal that matters (practical significance:
            a smaller estimate is not reported as a cause).
        tolerance: (absolute, relative) accuracy the diagnosis states for its estimate.
        sign: +1 / -1 if a hidden effect only goes one way, 0 if both.
    """

    cause: str
    unit: str
    what: str
    nominal: float
    bounds: tuple[float, float]
    hidden: tuple[float, float]
    floor: float
    tolerance: tuple[float, float]
    sign: int = 0

    def within_tolerance(self, estimate: float, truth: float) -> bool:
        """Whether ``estimate`` is within the stated tolerance of ``truth``."""
        a, r = self.tolerance
        return abs(estimate - truth) <= max(a, r * abs(truth - self.nominal))


EFFECTS: dict[str, Effect] = {
    e.cause: e
    for e in (
        Effect("tyre_pressure", "bar", "inflation pressure of all four tyres (gauge)", 2.2, (1.2, 3.4),
               (0.4, 0.8), 0.12, (0.12, 0.25)),
        # at 20 Hz a re-simulated torque can lag its measurement by up to ~30 ms of
        # unmodelled steering dynamics: a delay counts from 35 ms, and is stated to +-30 ms
        Effect("sensor_delay", "s", "extra delay of one signal", 0.0, (0.0, 0.4), DELAY_RANGE, 0.035,
               (0.03, 0.2), +1),
        Effect("sensor_offset", "signal unit", "offset of one signal", 0.0, (-np.inf, np.inf), (0.0, 0.0),
               0.0, (0.0, 0.25)),
        Effect("sensor_gain", "1", "gain of one signal (1 = exact)", 1.0, (0.7, 1.3), GAIN_RANGE, 0.02,
               (0.02, 0.2)),
        Effect("vehicle_mass", "kg", f"payload {PAYLOAD_X_M} m behind the front axle", 0.0, (-150.0, 600.0),
               (120.0, 350.0), 40.0, (40.0, 0.3), +1),
        Effect("steering_friction", "Nm", "Coulomb friction of rack and gear, column-referred", 1.4, (0.2, 8.0),
               (1.5, 3.5), 0.5, (0.4, 0.25), +1),
        Effect("road_friction", "1", "friction of the test road relative to the nominal mu", 1.0, (0.4, 1.2),
               (0.15, 0.35), 0.05, (0.05, 0.3), -1),
        Effect("relaxation_length", "1", "scale of the tyres' relaxation lengths", 1.0, (0.25, 4.0),
               (0.8, 1.5), 0.3, (0.3, 0.35), +1),
        # another rack (or pinion) than the car's: the road wheels turn 1/value as far for a steering-wheel angle,
        # and the kingpin moments reach the column 1/value as large. Measured on the column, it looks like a
        # steering-angle gain and a steering-torque gain at once (what the diagnosis named before it was here)
        Effect("steering_ratio", "1", "steering ratio (steering-wheel per road-wheel angle) relative to the car's",
               1.0, (0.7, 1.4), (0.10, 0.18), 0.03, (0.03, 0.25)),
    )
}


def responding_range(cause: str, params: Mapping[str, Any]) -> tuple[float, float]:
    """The values of ``cause`` (its unit) that the simulator of the car ``params`` tells apart: a value beyond
    either end re-simulates exactly as that end. MF 6.1 clips the inflation pressure to the tyre property file's
    PRESMIN..PRESMAX, so the tyre pressure's range is its tyres' (in bar; the union of the two axles' when they
    differ, since the pressure is set on all four). Every other cause: the whole line."""
    if cause != "tyre_pressure":
        return (-np.inf, np.inf)
    from sim.vehicle import tyre_for

    ps = [tyre_for(params, axle).params for axle in ("front", "rear")]
    lo, hi = min(p["PRESMIN"] for p in ps), max(p["PRESMAX"] for p in ps)
    return (float(lo) / 1e5 if lo > 0 else -np.inf, float(hi) / 1e5 if np.isfinite(hi) and hi > 0 else np.inf)


def offset_floor(signal: str) -> float:
    """Smallest offset of ``signal`` that matters (a third of the smallest realistic one)."""
    return OFFSET_RANGE[signal][0] / 3.0


def effect_overrides(cause: str, value: float, params: Mapping[str, Any], signal: str | None = None
                     ) -> dict[str, Any]:
    """``{"section.name": value}`` overrides that give the car ``cause`` at ``value``.

    ``params`` is the car the effect is added to (a payload moves its CG and adds
    yaw inertia relative to it). Sensor causes need ``signal``.
    """
    if cause.startswith("sensor_"):
        if signal not in SENSOR_SIGNALS:
            raise ValueError(f"{cause} needs one of the 12 input signals, got {signal!r}")
        key = {"sensor_delay": "delay_s", "sensor_offset": "offset", "sensor_gain": "gain"}[cause]
        return {f"sensor_errors.{signal}.{key}": float(value)}
    if cause == "tyre_pressure":
        pa = float(value) * 1e5
        return {"tyres.pressure_front_pa": pa, "tyres.pressure_rear_pa": pa}
    if cause == "vehicle_mass":
        return _payload(float(value), params)
    if cause == "steering_friction":
        return {"steering.coulomb_friction_nm": float(value)}
    if cause == "road_friction":
        return {"tyres.friction_scale": float(value)}
    if cause == "relaxation_length":
        return {"tyres.relaxation_scale": float(value)}
    if cause == "steering_ratio":
        return {"steering.ratio": float(value) * float(params["steering"]["ratio"])}
    raise ValueError(f"unknown cause {cause!r} (one of {', '.join(CAUSES)})")


def _payload(mp: float, params: Mapping[str, Any]) -> dict[str, Any]:
    """A point payload ``mp`` kg (negative: removed) at PAYLOAD_X_M behind the front
    axle: new mass, axle load split, CG height and yaw/pitch inertia (parallel axes)."""
    v = params["vehicle"]
    m, L = v["mass_kg"], v["wheelbase_m"]
    frac, h = v["front_axle_load_fraction"], v["cg_height_m"]
    x_cg = (1.0 - frac) * L  # CG behind the front axle
    m2 = m + mp
    if m2 <= 0.5 * m:
        raise ValueError(f"payload {mp:g} kg leaves less than half the car's mass")
    x2 = (m * x_cg + mp * PAYLOAD_X_M) / m2
    h2 = (m * h + mp * PAYLOAD_Z_M) / m2
    dI = m * (x2 - x_cg) ** 2 + mp * (PAYLOAD_X_M - x2) ** 2
    dIy = dI + m * (h2 - h) ** 2 + mp * (PAYLOAD_Z_M - h2) ** 2
    return {
        "vehicle.mass_kg": m2,
        "vehicle.front_axle_load_fraction": 1.0 - x2 / L,
        "vehicle.cg_height_m": h2,
        "vehicle.yaw_inertia_kgm2": v["yaw_inertia_kgm2"] + dI,
        "vehicle.pitch_inertia_sprung_kgm2": v["pitch_inertia_sprung_kgm2"] + dIy,
    }


def with_effect(params: Mapping[str, Any], cause: str, value: float, signal: str | None = None) -> dict[str, Any]:
    """A copy of ``params`` with the effect applied."""
    return apply_overrides(params, effect_overrides(cause, value, params, signal))


@dataclass(frozen=True)
class Hidden:
    """A hidden effect: cause, value (the parameter, see :data:`EFFECTS`) and signal."""

    cause: str
    value: float
    signal: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"cause": self.cause, "value": self.value, "signal": self.signal}


def draw_hidden(rng: np.random.Generator, causes: tuple[str, ...] = CAUSES) -> Hidden:
    """One effect drawn at random, at a random realistic magnitude."""
    cause = str(rng.choice(causes))
    e = EFFECTS[cause]
    signal = str(rng.choice(SENSOR_SIGNALS)) if cause.startswith("sensor_") else None
    lo, hi = OFFSET_RANGE[signal] if cause == "sensor_offset" else e.hidden
    size = float(rng.uniform(lo, hi))
    sign = e.sign if e.sign else (1 if rng.random() < 0.5 else -1)
    value = e.nominal + sign * size
    if cause == "relaxation_length" and rng.random() < 0.5:
        value = 1.0 / value  # x1.8-2.5 shorter instead of longer
    return Hidden(cause, round(value, 6), signal)
