"""Sensors: the car's signals as its ECUs deliver them, built from the truth.

Each sensor samples the true quantity at its own update rate (with a random
phase per run), after a pure latency, applies a gain error, a bias and white
noise, quantises to its resolution and holds the value until its next update.
A fault of one signal (``[sensor_errors]``: extra delay, offset, gain) comes on
top of its sensor model: that is how a car whose signals differ from the
simulator's is modelled.
The result is a set of *streams* on the 100 Hz base grid: what the CAN writer
encodes at each message's cycle time. The canonical 20 Hz table is not made
here: it is what a receiver on the bus samples from those frames
(:func:`virtsensor.recordings.canlog.simulated_recording`), so the simulator's tables
and its CAN logs carry the same values, and the trainer sees what the runtime sees.

What each catalogue input is made of (ISO 8855 signs, see virtsensor.signals):

* ``ax_mps2``/``ay_mps2``: IMU specific force at the CG, gravity through pitch/roll included;
* ``vx_mps``: the ESC's reference speed: mean rear (undriven) wheel speed times the
  ESC's calibrated rolling radius (the effective radius at static load), so it
  carries the real tyre-radius errors and cornering geometry of a production ESC;
* ``steer_angle_rad``: steering-wheel angle sensor at the top of the column;
* ``steer_torque_nm``: the torsion bar; ``assist_torque_nm``: EPAS motor torque estimate;
* ``motor_torque_nm``: the inverter's torque estimate;
* ``susp_defl_*_m``: ride-height sensors (compression from design height);
* ``wheel_speed_*_radps``: ABS wheel-speed sensors; ``tyre_pressure_*_pa``: TPMS;
* ``sat_*_nm``: the test equipment's wheel-force transducers (the reference).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

#: catalogue signal -> (sensor spec key in [sensors], truth channel)
SOURCES: dict[str, tuple[str, str]] = {
    "ax_mps2": ("ax_mps2", "ax_true_mps2"),
    "ay_mps2": ("ay_mps2", "ay_true_mps2"),
    "yaw_rate_radps": ("yaw_rate_radps", "yaw_rate_true_radps"),
    "vx_mps": ("vx_mps", "esc_speed_mps"),
    "steer_angle_rad": ("steer_angle_rad", "steer_angle_true_rad"),
    "steer_torque_nm": ("steer_torque_nm", "steer_torque_true_nm"),
    "assist_torque_nm": ("assist_torque_nm", "assist_torque_true_nm"),
    "motor_torque_nm": ("motor_torque_nm", "motor_torque_true_nm"),
    **{f"susp_defl_{w}_m": ("susp_defl_m", f"comp_{w}") for w in ("fl", "fr", "rl", "rr")},
    **{f"wheel_speed_{w}_radps": ("wheel_speed_radps", f"omega_{w}") for w in ("fl", "fr", "rl", "rr")},
    **{f"tyre_pressure_{w}_pa": ("tyre_pressure_pa", f"pressure_{w}") for w in ("fl", "fr", "rl", "rr")},
    "sat_fl_nm": ("sat_nm", "sat_fl"),
    "sat_fr_nm": ("sat_nm", "sat_fr"),
}

#: truth columns appended to the 20 Hz table (catalogue name -> truth channel)
TRUTH_COLUMNS: dict[str, str] = {
    **{f"{q}_{w}_{u}": f"{q}_{w}" for w in ("fl", "fr") for q, u in
       (("alpha", "rad"), ("kappa", "1"), ("fz", "n"), ("fy", "n"), ("fx", "n"), ("delta", "rad"))},
    "vy_mps": "vy_mps",
    "roll_rad": "roll_rad",
    "road_mu": "road_mu",
    "util_fl_1": "util_fl",
    "util_fr_1": "util_fr",
    "steer_angle_cmd_rad": "steer_angle_cmd_rad",
    "x_m": "x_m",
    "y_m": "y_m",
}

SPEC_KEYS = ("rate_hz", "latency_s", "noise", "bias", "gain", "resolution")
ERROR_KEYS = ("delay_s", "offset", "gain")


def check_specs(params: Mapping[str, Any]) -> None:
    """Validate the [sensors] section: every spec complete and physically meaningful (rate in (0, 100] Hz,
    latency in [0, 1] s, noise and resolution >= 0, gain in (0, 10]); and [sensor_errors]: delay in [0, 2] s,
    gain in (0, 10] (offsets: any finite value, in the signal's unit)."""
    sensors = params["sensors"]
    for key in {k for k, _ in SOURCES.values()}:
        if key not in sensors:
            raise ValueError(f"sensors.{key}: missing sensor specification")
        spec = sensors[key]
        missing = [k for k in SPEC_KEYS if k not in spec]
        if missing:
            raise ValueError(f"sensors.{key}: missing {', '.join(missing)}")
        if not 0.0 < spec["rate_hz"] <= 100.0:
            raise ValueError(f"sensors.{key}.rate_hz must be in (0, 100], got {spec['rate_hz']}")
        if spec["latency_s"] < 0 or spec["noise"] < 0 or spec["resolution"] < 0:
            raise ValueError(f"sensors.{key}: latency, noise and resolution must be >= 0")
        if spec["latency_s"] > 1.0:
            raise ValueError(f"sensors.{key}.latency_s must be in [0, 1] s, got {spec['latency_s']}")
        if not 0.0 < spec["gain"] <= 10.0:
            raise ValueError(f"sensors.{key}.gain must be in (0, 10], got {spec['gain']}")
    for name, err in params.get("sensor_errors", {}).items():
        if name not in SOURCES:
            raise ValueError(f"sensor_errors.{name}: not a signal the sensors deliver")
        missing = [k for k in ERROR_KEYS if k not in err]
        if missing:
            raise ValueError(f"sensor_errors.{name}: missing {', '.join(missing)}")
        if not 0.0 <= err["delay_s"] <= 2.0:
            raise ValueError(f"sensor_errors.{name}.delay_s must be in [0, 2] s, got {err['delay_s']}")
        if not 0.0 < err["gain"] <= 10.0:
            raise ValueError(f"sensor_errors.{name}.gain must be in (0, 10], got {err['gain']}")


def _sensor(t: np.ndarray, x: np.ndarray, spec: Mapping[str, float], rng: np.random.Generator,
            error: Mapping[str, float] | None = None) -> np.ndarray:
    """One sensor's held output on the base grid ``t`` from the true signal ``x``;
    ``error`` (``delay_s``, ``offset``, ``gain``) is a fault of this one signal on top."""
    delay, offset, gain = (0.0, 0.0, 1.0) if error is None else (
        error["delay_s"], error["offset"], error["gain"])
    dt = t[1] - t[0] if len(t) > 1 else 0.01
    every = max(1, int(round(1.0 / (spec["rate_hz"] * dt))))
    phase = int(rng.integers(every))
    upd = np.arange(phase, len(t), every)
    if upd.size == 0 or upd[0] != 0:
        upd = np.concatenate([[0], upd])  # the first value is known from t = 0
    ts = t[upd] - spec["latency_s"] - delay
    val = (np.interp(ts, t, x) * spec["gain"] + spec["bias"]) * gain + offset
    if spec["noise"] > 0:
        val = val + rng.normal(0.0, spec["noise"], size=val.shape)
    res = spec["resolution"]
    if res > 0:
        val = np.round(val / res) * res
    hold = np.searchsorted(upd, np.arange(len(t)), side="right") - 1
    return val[hold]


def make_streams(run: Mapping[str, np.ndarray], params: Mapping[str, Any], seed: int) -> dict[str, np.ndarray]:
    """The car's signals on the base grid (``run`` is one run of a BatchResult).

    Returns a dict with ``time_s`` and every catalogue signal of :data:`SOURCES`.
    """
    t = run["time_s"]
    truth = dict(run)
    # the ESC's reference speed from the undriven wheels and its calibrated radius
    r_cal = 0.5 * (run["re_rl"][0] + run["re_rr"][0])
    truth["esc_speed_mps"] = 0.5 * (run["omega_rl"] + run["omega_rr"]) * r_cal
    rng = np.random.default_rng(seed)
    errors = params.get("sensor_errors", {})
    streams = {"time_s": t}
    for name, (key, src) in SOURCES.items():
        streams[name] = _sensor(t, truth[src], params["sensors"][key], rng, errors.get(name))
    return streams


def truth_at(run: Mapping[str, np.ndarray], times: np.ndarray) -> dict[str, np.ndarray]:
    """The truth columns of :data:`TRUTH_COLUMNS` at ``times`` (s, run clock), linearly
    interpolated on the base grid (exact at grid instants such as 20 Hz ticks)."""
    t = run["time_s"]
    return {name: np.interp(times, t, run[src]) for name, src in TRUTH_COLUMNS.items()}
