"""Physical parameters of the simulated car: defaults, overrides, validation.

The defaults live in ``sim/data/car_c_segment.toml``. A run may override any
leaf with ``section.name=value`` strings (the CLI's ``--set``) or with a TOML
file of the same shape. Overrides are validated against the defaults: an
unknown key, a value of the wrong type or a non-finite number raises
:class:`ParamError` naming the key (and the file, for TOML files). The whole
set is then checked against physical bounds (:func:`check_car`, which
:func:`car_parameters` and every simulation entry point run before any work).
"""

from __future__ import annotations

import copy
import difflib
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path
from typing import Any

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore[no-redef]

#: the simulator's data folder (package data of :mod:`sim`, found through :mod:`importlib.resources`)
DATA_DIR = Path(str(files("sim").joinpath("data")))
DEFAULT_CAR = DATA_DIR / "car_c_segment.toml"
#: road friction coefficients the simulator accepts (lowest, highest), the ``--mu`` range of every command
MU_RANGE = (0.1, 1.2)


class ParamError(ValueError):
    """A parameter override or file that cannot be used (message names key/file)."""


def resolve_data_file(name: str | Path) -> Path:
    """A data file named in the parameters: absolute, relative to the working
    directory if it exists there, else relative to the bundled ``sim/data``."""
    path = Path(name)
    if path.is_absolute() or path.exists():
        return path
    return DATA_DIR / path


def load_defaults(path: Path | str = DEFAULT_CAR) -> dict[str, Any]:
    """Read a car parameter TOML file into a nested dict."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except OSError as exc:
        raise ParamError(f"{path}: cannot read parameter file ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ParamError(f"{path}: not valid TOML ({exc})") from None
    except UnicodeDecodeError as exc:
        raise ParamError(f"{path}: not UTF-8 text (byte {exc.start}), as TOML must be") from None


def _leaves(tree: Mapping[str, Any], prefix: str = "") -> Iterable[tuple[str, Any]]:
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            yield from _leaves(value, name + ".")
        else:
            yield name, value


def leaf_keys(tree: Mapping[str, Any]) -> list[str]:
    """All dotted leaf keys of a parameter tree (``section.name``)."""
    return [k for k, _ in _leaves(tree)]


def _coerce(key: str, default: Any, value: Any, where: str) -> Any:
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
    elif isinstance(default, (int, float)):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(float(value)):
                raise ParamError(f"{where}{key}: value must be finite, got {value!r}")
            return float(value)
    elif isinstance(default, str):
        if isinstance(value, str):
            return value
    elif isinstance(default, list):
        if isinstance(value, list) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v)) for v in value
        ):
            return [float(v) for v in value]
    raise ParamError(
        f"{where}{key}: expected {type(default).__name__} like {default!r}, got {value!r}"
    )


def _set(tree: dict[str, Any], key: str, value: Any, where: str = "") -> None:
    parts = key.split(".")
    node: Any = tree
    for i, part in enumerate(parts):
        if not isinstance(node, dict) or part not in node:
            close = difflib.get_close_matches(key, leaf_keys(tree), n=3, cutoff=0.85)
            hint = f" (did you mean {', '.join(close)}?)" if close else ""
            raise ParamError(f"{where}unknown parameter {key!r}{hint}")
        if i == len(parts) - 1:
            if isinstance(node[part], dict):
                raise ParamError(f"{where}{key!r} is a section, not a parameter; set one of its keys")
            node[part] = _coerce(key, node[part], value, where)
        else:
            node = node[part]


def parse_assignment(text: str) -> tuple[str, Any]:
    """Parse ``section.name=value`` (value in TOML syntax; bare words are strings)."""
    if "=" not in text:
        raise ParamError(f"--set {text!r}: expected section.name=value")
    key, raw = (s.strip() for s in text.split("=", 1))
    if not key:
        raise ParamError(f"--set {text!r}: empty parameter name")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw  # a bare word, e.g. a file name
    return key, value


def apply_overrides(
    base: Mapping[str, Any],
    assignments: Iterable[str] | Mapping[str, Any] = (),
    files: Iterable[Path | str] = (),
) -> dict[str, Any]:
    """Return a copy of ``base`` with TOML files, then assignments, applied.

    Args:
        base: the default parameter tree.
        assignments: ``["section.name=value", ...]`` or ``{"section.name": value}``.
        files: TOML files with the same shape as the defaults (any subset).
    """
    return _applied(base, assignments, files)[0]


def _applied(
    base: Mapping[str, Any],
    assignments: Iterable[str] | Mapping[str, Any] = (),
    files: Iterable[Path | str] = (),
) -> tuple[dict[str, Any], dict[str, str]]:
    """:func:`apply_overrides`, and which file set each key it changed last (key -> ``"<file>: "``; keys an
    assignment set last are not listed: the assignment names its key and value itself)."""
    tree = copy.deepcopy(dict(base))
    origins: dict[str, str] = {}
    for f in files:
        patch = load_defaults(f)
        for key, value in _leaves(patch):
            _set(tree, key, value, where=f"{f}: ")
            origins[key] = f"{f}: "
    items = assignments.items() if isinstance(assignments, Mapping) else map(parse_assignment, assignments)
    for key, value in items:
        _set(tree, key, value)
        origins.pop(key, None)
    return tree, origins


def car_parameters(
    assignments: Iterable[str] | Mapping[str, Any] = (),
    files: Iterable[Path | str] = (),
    defaults: Path | str = DEFAULT_CAR,
) -> dict[str, Any]:
    """The default car with overrides applied and checked (the usual entry point; see :func:`check_car`)."""
    tree, origins = _applied(load_defaults(defaults), assignments, files)
    try:
        check_car(tree)
    except ParamError as exc:  # a value out of range that a file set: the message names the file too
        key = next((k for k in origins if any(f"car parameter {k}{c}" in str(exc) for c in "=[")), None)
        if key is None:
            raise
        raise ParamError(f"{origins[key]}{exc}") from None
    return tree


@dataclass(frozen=True)
class Bound:
    """The physical range of one scalar parameter: ``lo``..``hi`` in ``unit``; an open end excludes its value."""

    lo: float
    hi: float
    unit: str
    lo_open: bool = False
    hi_open: bool = False

    def holds(self, value: float) -> bool:
        above = value > self.lo if self.lo_open else value >= self.lo
        below = value < self.hi if self.hi_open else value <= self.hi
        return above and below

    def text(self) -> str:
        return (f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"
                f"{' ' + self.unit if self.unit else ''}")


#: The physical range of every scalar car parameter (sensors: :func:`sim.sensors.check_specs`). A
#: passenger car, from a 300 kg quadricycle to a 5 t van, on Earth: wide enough for every car the project
#: ships, its diagnosis searches (payload -150..600 kg, pressure 1.2-3.4 bar, relaxation x0.25-4, friction
#: x0.4-1.2, a steering friction to 8 Nm) and a rack 18 % quicker or slower; narrow enough that no value
#: divides by zero or makes the model meaningless (a mass, a ratio, an inertia or a time constant of 0...).
BOUNDS: dict[str, Bound] = {
    "vehicle.mass_kg": Bound(300.0, 5000.0, "kg"),
    "vehicle.wheelbase_m": Bound(1.5, 4.5, "m"),
    "vehicle.front_axle_load_fraction": Bound(0.0, 1.0, "", lo_open=True, hi_open=True),
    "vehicle.cg_height_m": Bound(0.2, 1.5, "m"),
    "vehicle.track_front_m": Bound(1.0, 2.2, "m"),
    "vehicle.track_rear_m": Bound(1.0, 2.2, "m"),
    "vehicle.yaw_inertia_kgm2": Bound(100.0, 20000.0, "kg m^2"),
    "vehicle.roll_inertia_sprung_kgm2": Bound(50.0, 5000.0, "kg m^2"),
    "vehicle.pitch_inertia_sprung_kgm2": Bound(100.0, 20000.0, "kg m^2"),
    "vehicle.unsprung_mass_front_kg": Bound(5.0, 150.0, "kg"),
    "vehicle.unsprung_mass_rear_kg": Bound(5.0, 150.0, "kg"),
    "vehicle.roll_centre_height_front_m": Bound(-0.2, 0.6, "m"),
    "vehicle.roll_centre_height_rear_m": Bound(-0.2, 0.6, "m"),
    "vehicle.pitch_centre_height_m": Bound(-0.2, 0.6, "m"),
    "suspension.wheel_rate_front_npm": Bound(5e3, 3e5, "N/m"),
    "suspension.wheel_rate_rear_npm": Bound(5e3, 3e5, "N/m"),
    "suspension.damping_front_nspm": Bound(100.0, 5e4, "N s/m"),
    "suspension.damping_rear_nspm": Bound(100.0, 5e4, "N s/m"),
    "suspension.arb_front_npm": Bound(0.0, 2e5, "N/m"),
    "suspension.arb_rear_npm": Bound(0.0, 2e5, "N/m"),
    "suspension.bump_stop_travel_m": Bound(0.01, 0.3, "m"),
    "suspension.bump_stop_rate_npm": Bound(1e4, 2e6, "N/m"),
    "suspension.camber_roll_factor_front": Bound(-0.5, 1.5, ""),
    "suspension.camber_roll_factor_rear": Bound(-0.5, 1.5, ""),
    "aero.drag_coefficient": Bound(0.1, 1.5, ""),
    "aero.frontal_area_m2": Bound(1.0, 6.0, "m^2"),
    "aero.air_density_kgpm3": Bound(0.7, 1.5, "kg/m^3"),
    "powertrain.motor_max_torque_nm": Bound(10.0, 2000.0, "Nm"),
    "powertrain.motor_max_power_w": Bound(5e3, 1e6, "W"),
    "powertrain.motor_max_speed_radps": Bound(100.0, 3000.0, "rad/s"),
    "powertrain.gear_ratio": Bound(1.0, 20.0, ""),
    "powertrain.efficiency": Bound(0.5, 1.0, ""),
    "powertrain.torque_time_constant_s": Bound(0.005, 1.0, "s"),
    "brakes.max_wheel_torque_front_nm": Bound(100.0, 10000.0, "Nm"),
    "brakes.front_share": Bound(0.0, 1.0, "", lo_open=True),
    "brakes.pressure_time_constant_s": Bound(0.005, 1.0, "s"),
    "wheels.spin_inertia_front_kgm2": Bound(0.1, 10.0, "kg m^2"),
    "wheels.spin_inertia_rear_kgm2": Bound(0.1, 10.0, "kg m^2"),
    "tyres.pressure_front_pa": Bound(0.5e5, 5e5, "Pa"),
    "tyres.pressure_rear_pa": Bound(0.5e5, 5e5, "Pa"),
    "tyres.pressure_left_right_front_pa": Bound(-4.5e5, 4.5e5, "Pa"),
    "tyres.pressure_left_right_rear_pa": Bound(-4.5e5, 4.5e5, "Pa"),
    "tyres.static_camber_front_rad": Bound(-0.1, 0.1, "rad"),
    "tyres.static_camber_rear_rad": Bound(-0.1, 0.1, "rad"),
    "tyres.toe_in_front_rad": Bound(-0.03, 0.03, "rad"),
    "tyres.toe_in_rear_rad": Bound(-0.03, 0.03, "rad"),
    "tyres.relaxation_scale": Bound(0.1, 10.0, ""),
    "tyres.friction_scale": Bound(0.05, 2.0, ""),
    "steering.ratio": Bound(5.0, 40.0, ""),
    "steering.ackermann_fraction": Bound(-1.0, 1.5, ""),
    "steering.max_road_wheel_angle_rad": Bound(0.05, 1.0, "rad"),
    "steering.wheel_inertia_kgm2": Bound(0.005, 0.5, "kg m^2"),
    "steering.wheel_damping_nmsprad": Bound(0.0, 5.0, "Nm s/rad"),
    "steering.torsion_bar_stiffness_nmprad": Bound(10.0, 2000.0, "Nm/rad"),
    "steering.torsion_bar_damping_nmsprad": Bound(0.0, 10.0, "Nm s/rad"),
    "steering.lower_inertia_kgm2": Bound(0.005, 2.0, "kg m^2"),
    "steering.lower_damping_nmsprad": Bound(0.0, 20.0, "Nm s/rad"),
    "steering.coulomb_friction_nm": Bound(0.0, 20.0, "Nm"),
    "steering.friction_velocity_radps": Bound(0.001, 1.0, "rad/s"),
    "steering.caster_trail_m": Bound(-0.05, 0.1, "m"),
    "steering.scrub_radius_m": Bound(-0.1, 0.1, "m"),
    "steering.kingpin_offset_wheel_centre_m": Bound(0.0, 0.2, "m"),
    "steering.kingpin_inclination_rad": Bound(0.0, 0.35, "rad"),
    "steering.assist_knee_nm": Bound(0.05, 10.0, "Nm"),
    "steering.assist_max_nm": Bound(0.0, 200.0, "Nm"),
    "steering.assist_noload_speed_radps": Bound(1.0, 200.0, "rad/s"),
    "steering.assist_damping_nmsprad": Bound(0.0, 20.0, "Nm s/rad"),
    "driver.robot_stiffness_nmprad": Bound(10.0, 1e5, "Nm/rad"),
    "driver.robot_damping_nmsprad": Bound(0.0, 1000.0, "Nm s/rad"),
    "driver.robot_max_rate_radps": Bound(0.5, 50.0, "rad/s"),
    "driver.command_time_constant_s": Bound(0.005, 2.0, "s"),
    "driver.steer_slip_margin_rad": Bound(0.0, 0.5, "rad"),
    "driver.preview_time_s": Bound(0.05, 5.0, "s"),
    "driver.preview_min_m": Bound(0.0, 50.0, "m"),
    "driver.lateral_integral_gain": Bound(0.0, 1.0, "rad/(m s)"),
    "driver.lateral_integral_speed_mps": Bound(1.0, 150.0, "m/s"),
    "driver.speed_gain_npmps": Bound(0.0, 1e5, "N s/m"),
    "driver.speed_integral_gain": Bound(0.0, 1e5, "N/m"),
    "simulation.step_s": Bound(0.0, 0.01, "s", lo_open=True),
    "simulation.record_rate_hz": Bound(20.0, 100.0, "Hz"),
    "simulation.gravity_mps2": Bound(9.5, 10.1, "m/s^2"),
}
#: keys a tree may lack (the simulator takes 0 for them: trees written before they existed)
OPTIONAL = ("tyres.pressure_left_right_front_pa", "tyres.pressure_left_right_rear_pa")
#: EPAS boost table: breakpoints (m/s) and gains (assist / torsion-bar torque)
ASSIST_SPEEDS = Bound(0.0, 100.0, "m/s")
ASSIST_GAINS = Bound(0.0, 50.0, "")
#: the driver's update period (s; :data:`sim.driver.CONTROL_DT` is this): the step divides it, the record
#: period is a whole number of it
CONTROL_PERIOD_S = 0.01


def step_counts(step_s: float, record_rate_hz: float) -> tuple[int, int]:
    """``(sub, every)``: integration steps per driver update and driver updates per recorded sample.

    Raises:
        ParamError: the step does not divide :data:`CONTROL_PERIOD_S`, or the record rate does not divide its
            rate (100 Hz).
    """
    sub = round(CONTROL_PERIOD_S / step_s)
    if sub < 1 or abs(sub * step_s - CONTROL_PERIOD_S) > 1e-12:
        raise ParamError(f"car parameter simulation.step_s={step_s:g} must divide the driver's "
                         f"{CONTROL_PERIOD_S:g} s update period (0.005, 0.0025, 0.002, 0.001... s)")
    every = round(1.0 / (record_rate_hz * CONTROL_PERIOD_S))
    if every < 1 or abs(every * CONTROL_PERIOD_S * record_rate_hz - 1.0) > 1e-9:
        raise ParamError(f"car parameter simulation.record_rate_hz={record_rate_hz:g} must divide the driver's "
                         f"{1.0 / CONTROL_PERIOD_S:g} Hz (100, 50, 25 or 20 Hz)")
    return sub, every


def _leaf(tree: Mapping[str, Any], key: str) -> Any:
    node: Any = tree
    for part in key.split("."):
        if not isinstance(node, Mapping) or part not in node:
            raise KeyError(key)
        node = node[part]
    return node


def _out_of_range(key: str, value: Any, bound: Bound, why: str = "") -> ParamError:
    shown = f"{value:g}" if isinstance(value, float) else repr(value)
    return ParamError(f"car parameter {key}={shown} is outside its physical range {bound.text()}{why}")


def check_car(tree: Mapping[str, Any]) -> None:
    """Refuse a car whose parameters are not physically meaningful, before any simulation.

    Each scalar must lie in its range of :data:`BOUNDS` (a passenger car on Earth: mass 300-5000 kg, ratios
    and inertias > 0, fractions in (0, 1), step in (0, 0.01] s, gravity 9.5-10.1 m/s^2 (9.81 +- 3 %)...), and:

    * every wheel's pressure (axle pressure -+ half the left-right difference) within 0.5-5 bar gauge;
    * the four corners' unsprung mass under three quarters of the car's mass (a body to carry);
    * ``simulation.step_s`` dividing the driver's 0.01 s update period, ``simulation.record_rate_hz`` dividing
      its 100 Hz and at least every sensor's rate (sensors are sampled on the record grid);
    * the EPAS boost table: at least two breakpoints, strictly increasing within 0-100 m/s, and as many gains,
      each within 0-50;
    * the sensors (:func:`sim.sensors.check_specs`).

    Raises:
        ParamError: one line naming the key, its value and the allowed range.
    """
    for key, bound in BOUNDS.items():
        try:
            value = _leaf(tree, key)
        except KeyError:
            if key in OPTIONAL:
                continue
            raise ParamError(f"car parameter {key} is missing") from None
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
            raise ParamError(f"car parameter {key}={value!r}: expected a finite number in {bound.text()}")
        if not bound.holds(float(value)):
            raise _out_of_range(key, float(value), bound)
    _check_consistency(tree)
    _check_assist(tree["steering"])
    from sim.sensors import check_specs

    try:
        check_specs(tree)
    except ValueError as exc:
        raise ParamError(str(exc)) from None


def _check_consistency(tree: Mapping[str, Any]) -> None:
    """The cross-checks of :func:`check_car` between parameters."""
    v, ty, sim = tree["vehicle"], tree["tyres"], tree["simulation"]
    wheel = Bound(0.5e5, 5e5, "Pa")
    for axle in ("front", "rear"):
        p, d = ty[f"pressure_{axle}_pa"], ty.get(f"pressure_left_right_{axle}_pa", 0.0)
        for side, pw in (("left", p + 0.5 * d), ("right", p - 0.5 * d)):
            if not wheel.holds(pw):
                raise ParamError(f"car parameter tyres.pressure_left_right_{axle}_pa={d:g} puts the {axle} {side} "
                                 f"tyre at {pw:g} Pa, outside its physical range {wheel.text()} (0.5-5 bar gauge)")
    unsprung = 2.0 * (v["unsprung_mass_front_kg"] + v["unsprung_mass_rear_kg"])
    if unsprung > 0.75 * v["mass_kg"]:
        raise ParamError(f"car parameter vehicle.mass_kg={v['mass_kg']:g} is too light for its unsprung masses "
                         f"(four corners {unsprung:g} kg): the unsprung mass must stay under 3/4 of the car's mass")
    rate = float(sim["record_rate_hz"])
    step_counts(float(sim["step_s"]), rate)
    fastest = max((float(s.get("rate_hz", 0.0)) for s in tree.get("sensors", {}).values()
                   if isinstance(s, Mapping)), default=0.0)
    if rate < fastest:
        raise ParamError(f"car parameter simulation.record_rate_hz={rate:g} must divide the driver's "
                         f"{1.0 / CONTROL_PERIOD_S:g} Hz (100, 50, 25 or 20 Hz) and be at least the fastest "
                         f"sensor's rate ({fastest:g} Hz)")


def _check_assist(steering: Mapping[str, Any]) -> None:
    """The EPAS boost table of :func:`check_car`."""
    speeds, gains = steering["assist_speeds_mps"], steering["assist_gains"]
    if not isinstance(speeds, list) or len(speeds) < 2:
        raise ParamError(f"car parameter steering.assist_speeds_mps={speeds!r}: expected a list of at least 2 "
                         f"speeds in {ASSIST_SPEEDS.text()}")
    if not isinstance(gains, list) or len(gains) != len(speeds):
        raise ParamError(f"car parameter steering.assist_gains={gains!r}: expected one gain per speed of "
                         f"steering.assist_speeds_mps ({len(speeds)} values)")
    for key, values, bound in (("steering.assist_speeds_mps", speeds, ASSIST_SPEEDS),
                               ("steering.assist_gains", gains, ASSIST_GAINS)):
        for i, x in enumerate(values):
            if not bound.holds(float(x)):
                raise _out_of_range(f"{key}[{i}]", float(x), bound)
    for i in range(1, len(speeds)):
        if not speeds[i] > speeds[i - 1]:
            raise ParamError(f"car parameter steering.assist_speeds_mps={speeds!r}: breakpoints must increase "
                             f"strictly (entry {i}, {speeds[i]:g}, is not above {speeds[i - 1]:g} m/s)")
