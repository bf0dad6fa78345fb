"""The one catalogue of signals: canonical names, SI units, signs, ranges, CAN mapping.

Every part of the project (simulator, CAN codec, trainer, runtime, diagnosis)
names a quantity by its canonical name from this module and nowhere else
restates its unit, sign or range.

Sign conventions (written once, here)
-------------------------------------
Vehicle axes follow ISO 8855: x forward, y to the left, z up, origin at the
centre of gravity projected on the ground. Angles and angular rates about z
are positive counter-clockwise seen from above, so a **left turn** has positive
yaw rate, positive steering-wheel angle and positive lateral acceleration.

* ``ax_mps2``/``ay_mps2`` are what a body-fixed accelerometer measures (specific
  force): they include the components of gravity that body roll and pitch put
  on the sensor axes.
* ``steer_angle_rad`` is the steering-wheel angle (not the road-wheel angle).
* ``steer_torque_nm`` is the torsion-bar torque (the EPAS torque sensor),
  positive when the driver turns the wheel to the left.
* ``assist_torque_nm`` is the EPAS motor torque referred to the steering column
  (pinion) axis, positive in the same sense as ``steer_torque_nm``.
* ``motor_torque_nm`` is the traction-motor shaft torque, positive propelling.
* ``susp_defl_*_m`` is suspension compression (bump) from the static design
  position, positive when the wheel moves up relative to the body.
* ``wheel_speed_*_radps`` is the wheel spin rate, positive rolling forward.
* ``sat_*_nm`` is the tyre self-aligning torque: Mz of the tyre at the contact
  centre about the wheel's vertical axis (ISO-W, z up). It opposes the slip
  angle, so in a left turn both front SATs are **negative**.
* Tyre slip angles follow ISO-W: ``alpha = atan(v_y / |v_x|)`` of the wheel
  centre in wheel axes, so in a left turn the front slip angles are negative
  and the lateral forces positive.

Roles
-----
``input``  the 12 estimator inputs of the paper's Table II (in that order);
``output`` the two estimated quantities (front SATs);
``aux``    other signals a car carries on CAN (rear wheel speeds, TPMS, ...);
``truth``  simulator-only ground truth that explains the outputs;
``grip``   what the virtual sensor derives from its SAT estimate and publishes in ``VS_Grip``
           (friction utilisation, road friction; :mod:`virtsensor.grip`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Literal

Role = Literal["input", "output", "aux", "truth", "time", "grip"]


@dataclass(frozen=True)
class Signal:
    """One canonical signal.

    Attributes:
        name: canonical name, suffixed with its unit (``_mps2``, ``_nm``, ...).
        unit: SI unit as printed in tables and the DBC.
        description: what it is, with its sign convention where one applies.
        role: see module docstring.
        minimum, maximum: valid physical range in ``unit``; values outside are
            implausible and a receiver rejects them.
        resolution: the smallest step the CAN encoding carries (``unit``).
        message: DBC message that carries it (None: not on CAN).
        dbc_signal: signal name inside that message.
        critical: for inputs, True when the estimate cannot be trusted without
            it (INVALID), False when a held or substituted value only degrades it.
    """

    name: str
    unit: str
    description: str
    role: Role
    minimum: float
    maximum: float
    resolution: float
    message: str | None = None
    dbc_signal: str | None = None
    critical: bool = False


@dataclass(frozen=True)
class Message:
    """One CAN message of the matrix (the DBC is generated from these facts).

    Attributes:
        name: DBC message name.
        frame_id: 11-bit identifier.
        sender: sending ECU node.
        cycle_s: transmission period in seconds (``GenMsgCycleTime``).
        data_id: AUTOSAR E2E data ID mixed into the CRC.
    """

    name: str
    frame_id: int
    sender: str
    cycle_s: float
    data_id: int


MESSAGES: Mapping[str, Message] = MappingProxyType(
    {
        m.name: m
        for m in (
            Message("IMU_Motion", 0x080, "ACU", 0.010, 0x0801),
            Message("EPAS_Steering", 0x0A0, "EPAS", 0.010, 0x0A01),
            Message("PT_Torque", 0x0C0, "PCU", 0.010, 0x0C01),
            Message("ESC_WheelSpeeds_F", 0x100, "ESC", 0.020, 0x1001),
            Message("ESC_WheelSpeeds_R", 0x102, "ESC", 0.020, 0x1021),
            Message("ESC_VehicleSpeed", 0x101, "ESC", 0.020, 0x1011),
            Message("CHS_Suspension", 0x120, "CHS", 0.020, 0x1201),
            Message("TPMS_Pressures", 0x3A0, "TPMS", 1.000, 0x3A01),  # slow, as production TPMS: 1 frame/s
            Message("SAT_FRONT", 0x200, "VSENS", 0.050, 0x2001),
            Message("VS_Health", 0x201, "VSENS", 0.050, 0x2011),
            Message("VS_Grip", 0x202, "VSENS", 0.050, 0x2021),
            Message("TE_WheelForceTransducer", 0x600, "TESTEQ", 0.010, 0x6001),
        )
    }
)


def _s(*args, **kwargs) -> Signal:
    return Signal(*args, **kwargs)


_ALL: tuple[Signal, ...] = (
    _s("time_s", "s", "Time since the start of the run.", "time", 0.0, 1e7, 1e-6),
    # ---- the 12 inputs of Table II, in the paper's order -------------------------
    _s("ax_mps2", "m/s^2", "Longitudinal specific force at the IMU, body x, + forward.",
       "input", -20.0, 20.0, 0.01, "IMU_Motion", "AccelLong", critical=False),
    _s("ay_mps2", "m/s^2", "Lateral specific force at the IMU, body y, + left.",
       "input", -20.0, 20.0, 0.01, "IMU_Motion", "AccelLat", critical=True),
    _s("vx_mps", "m/s", "Longitudinal vehicle speed from the ESC, + forward.",
       "input", -20.0, 90.0, 0.01, "ESC_VehicleSpeed", "VehSpeed", critical=True),
    _s("yaw_rate_radps", "rad/s", "Yaw rate about body z, + counter-clockwise.",
       "input", -2.0, 2.0, 0.0005, "IMU_Motion", "YawRate", critical=True),
    _s("steer_angle_rad", "rad", "Steering-wheel angle, + left (counter-clockwise).",
       "input", -13.0, 13.0, 0.001, "EPAS_Steering", "SteerWheelAngle", critical=True),
    _s("steer_torque_nm", "Nm", "Torsion-bar (driver) torque, + turning left.",
       "input", -40.0, 40.0, 0.01, "EPAS_Steering", "TorsionBarTorque", critical=True),
    _s("assist_torque_nm", "Nm", "EPAS assist torque referred to the column, + left.",
       "input", -100.0, 100.0, 0.01, "EPAS_Steering", "AssistTorque", critical=True),
    _s("motor_torque_nm", "Nm", "Traction motor shaft torque, + propelling.",
       "input", -400.0, 400.0, 0.1, "PT_Torque", "MotorTorque", critical=False),
    _s("susp_defl_fl_m", "m", "Front-left suspension compression from design height.",
       "input", -0.15, 0.15, 0.0001, "CHS_Suspension", "SuspDefl_FL", critical=False),
    _s("susp_defl_fr_m", "m", "Front-right suspension compression from design height.",
       "input", -0.15, 0.15, 0.0001, "CHS_Suspension", "SuspDefl_FR", critical=False),
    _s("wheel_speed_fl_radps", "rad/s", "Front-left wheel spin rate, + forward.",
       "input", -50.0, 300.0, 0.01, "ESC_WheelSpeeds_F", "WhlSpd_FL", critical=False),
    _s("wheel_speed_fr_radps", "rad/s", "Front-right wheel spin rate, + forward.",
       "input", -50.0, 300.0, 0.01, "ESC_WheelSpeeds_F", "WhlSpd_FR", critical=False),
    # ---- outputs ---------------------------------------------------------------
    _s("sat_fl_nm", "Nm", "Front-left self-aligning torque (tyre Mz, ISO-W); < 0 in a left turn.",
       "output", -300.0, 300.0, 0.02, "TE_WheelForceTransducer", "Mz_FL"),
    _s("sat_fr_nm", "Nm", "Front-right self-aligning torque (tyre Mz, ISO-W); < 0 in a left turn.",
       "output", -300.0, 300.0, 0.02, "TE_WheelForceTransducer", "Mz_FR"),
    # ---- other signals a car carries -------------------------------------------
    _s("wheel_speed_rl_radps", "rad/s", "Rear-left wheel spin rate, + forward.",
       "aux", -50.0, 300.0, 0.01, "ESC_WheelSpeeds_R", "WhlSpd_RL"),
    _s("wheel_speed_rr_radps", "rad/s", "Rear-right wheel spin rate, + forward.",
       "aux", -50.0, 300.0, 0.01, "ESC_WheelSpeeds_R", "WhlSpd_RR"),
    _s("susp_defl_rl_m", "m", "Rear-left suspension compression from design height.",
       "aux", -0.15, 0.15, 0.0001, "CHS_Suspension", "SuspDefl_RL"),
    _s("susp_defl_rr_m", "m", "Rear-right suspension compression from design height.",
       "aux", -0.15, 0.15, 0.0001, "CHS_Suspension", "SuspDefl_RR"),
    _s("tyre_pressure_fl_pa", "Pa", "Front-left tyre inflation pressure (TPMS, gauge; SNA: sensor missing).",
       "aux", 0.0, 510000.0, 500.0, "TPMS_Pressures", "Pressure_FL"),
    _s("tyre_pressure_fr_pa", "Pa", "Front-right tyre inflation pressure (TPMS, gauge; SNA: sensor missing).",
       "aux", 0.0, 510000.0, 500.0, "TPMS_Pressures", "Pressure_FR"),
    _s("tyre_pressure_rl_pa", "Pa", "Rear-left tyre inflation pressure (TPMS, gauge; SNA: sensor missing).",
       "aux", 0.0, 510000.0, 500.0, "TPMS_Pressures", "Pressure_RL"),
    _s("tyre_pressure_rr_pa", "Pa", "Rear-right tyre inflation pressure (TPMS, gauge; SNA: sensor missing).",
       "aux", 0.0, 510000.0, 500.0, "TPMS_Pressures", "Pressure_RR"),
    # ---- simulator truth: the tyre states that explain the SAT --------------------
    *(
        _s(f"{q}_{w}_{u}", unit, f"{text} of the {wname} tyre (truth).", "truth", lo, hi, res)
        for w, wname in (("fl", "front-left"), ("fr", "front-right"),
                         ("rl", "rear-left"), ("rr", "rear-right"))
        for q, u, unit, text, lo, hi, res in (
            ("alpha", "rad", "rad", "Slip angle (ISO-W, lagged by relaxation)", -1.6, 1.6, 1e-5),
            ("kappa", "1", "1", "Longitudinal slip ratio (lagged)", -1.0, 1.0, 1e-5),
            ("fz", "n", "N", "Vertical load", 0.0, 30000.0, 0.1),
            ("fy", "n", "N", "Lateral force in wheel axes, + left", -30000.0, 30000.0, 0.1),
            ("fx", "n", "N", "Longitudinal force in wheel axes, + forward", -30000.0, 30000.0, 0.1),
            ("delta", "rad", "rad", "Road-wheel steer angle, + left", -1.0, 1.0, 1e-6),
        )
    ),
    _s("sat_rl_nm", "Nm", "Rear-left self-aligning torque (truth).", "truth", -300.0, 300.0, 0.02),
    _s("sat_rr_nm", "Nm", "Rear-right self-aligning torque (truth).", "truth", -300.0, 300.0, 0.02),
    _s("vy_mps", "m/s", "Lateral velocity at the CG, body y (truth).", "truth", -30.0, 30.0, 1e-4),
    _s("x_m", "m", "Global x position of the CG (truth).", "truth", -1e6, 1e6, 1e-3),
    _s("y_m", "m", "Global y position of the CG (truth).", "truth", -1e6, 1e6, 1e-3),
    _s("yaw_rad", "rad", "Heading angle, + counter-clockwise (truth).", "truth", -1e4, 1e4, 1e-6),
    _s("roll_rad", "rad", "Body roll angle about x; + right side down (truth).", "truth", -0.3, 0.3, 1e-6),
    _s("pitch_rad", "rad", "Body pitch angle about y; + nose down (truth).", "truth", -0.3, 0.3, 1e-6),
    _s("road_mu", "1", "Road friction coefficient under the car (truth).", "truth", 0.0, 1.5, 1e-3),
    *(_s(f"util_{w}_1", "1", f"Friction utilisation sqrt(Fx^2 + Fy^2) / (road_mu Fz) of the {wname} tyre "
         "(truth; 1 = at the road's friction, saturated at 2 when the wheel unloads).", "truth", 0.0, 2.0, 1e-4)
      for w, wname in (("fl", "front-left"), ("fr", "front-right"))),
    # ---- the grip estimate (VS_Grip; laid out by dbcgen like SAT_FRONT, so no message here) ---------------
    _s("grip_util_front_1", "1", "Front-axle friction utilisation: the share of the road's friction the "
       "front tyres use, sqrt(Fx^2 + Fy^2) / (mu Fz) of the more used tyre; 1 = at the limit.",
       "grip", 0.0, 1.0, 0.005),
    _s("grip_mu_1", "1", "Estimated road friction coefficient under the front tyres; unknown (SNA) while "
       "the tyres are not excited enough to tell.", "grip", 0.0, 1.5, 0.005),
    _s("grip_mu_halfwidth_1", "1", "Half-width of the interval around grip_mu_1 that holds the true road "
       "friction in 9 of 10 samples.", "grip", 0.0, 1.0, 0.005),
    _s("steer_angle_cmd_rad", "rad", "Steering-wheel angle the driver/robot commands (truth).",
       "truth", -13.0, 13.0, 1e-4),
)

SIGNALS: Mapping[str, Signal] = MappingProxyType({s.name: s for s in _ALL})

#: The 12 estimator inputs, in the paper's Table II order.
INPUTS: tuple[str, ...] = tuple(s.name for s in _ALL if s.role == "input")
#: The two estimated outputs (front-left, front-right SAT).
OUTPUTS: tuple[str, ...] = tuple(s.name for s in _ALL if s.role == "output")
#: Columns of the canonical 20 Hz table: time, inputs, outputs.
TABLE_COLUMNS: tuple[str, ...] = ("time_s", *INPUTS, *OUTPUTS)
#: The grip estimate's physical signals (utilisation, friction, its interval half-width), VS_Grip order.
GRIP: tuple[str, ...] = tuple(s.name for s in _ALL if s.role == "grip")
#: Signals that travel on CAN (inputs, reference outputs, aux).
CAN_SIGNALS: tuple[str, ...] = tuple(s.name for s in _ALL if s.message is not None)
#: The TPMS pressures (Pa, gauge), front then rear. Optional in a table: a recording of a car without TPMS
#: (or made before the TPMS was on the bus) has no such column, or NaN where a sensor is missing (its SNA).
TPMS_SIGNALS: tuple[str, ...] = tuple(f"tyre_pressure_{w}_pa" for w in ("fl", "fr", "rl", "rr"))
#: The front pressures, the ones a front-SAT estimator reads.
TPMS_FRONT: tuple[str, ...] = TPMS_SIGNALS[:2]
#: The canonical table rate of the paper (Hz).
TABLE_RATE_HZ = 20.0
#: One tick of the canonical table (s): the step between its rows, the period of the daemon's clock.
TABLE_TICK_S = 1.0 / TABLE_RATE_HZ
#: An input message is stale after this many of its DBC cycles without a usable frame: the daemon's default
#: (``RuntimeConfig.timeout_cycles``; a value is fresh while ``0 <= age <= timeout``) and the rule the offline
#: tables apply (:func:`virtsensor.recordings.canlog.decode_recording`): a tick the daemon would find stale holds no
#: value there either, so a model neither learns from nor is scored on it.
INPUT_TIMEOUT_CYCLES = 3.0


@dataclass(frozen=True)
class BoostCurve:
    """The EPAS boost curve: assist torque (column-referred, Nm) for a torsion-bar torque ``t`` (Nm) at vehicle
    speed ``v`` (m/s), on a column at rest: ``g(v) * t * |t| / (|t| + knee_nm)`` limited to ``+-max_nm``, with
    ``g`` interpolated linearly in ``gains`` over ``speeds_mps`` (held beyond their ends)."""

    speeds_mps: tuple[float, ...]
    gains: tuple[float, ...]
    knee_nm: float
    max_nm: float


@dataclass(frozen=True)
class SteadyTurn:
    """When a car turns with grip: the yaw rate ``r`` lies within ``[lo, hi]`` times the kinematic yaw rate
    ``r_kin = vx * steer_angle / (steer_ratio * wheelbase_m)`` (rad/s), and ``|r_kin| >= min_yaw_radps``.
    An understeering car with grip turns at ``r_kin / (1 + K vx^2)``; a car sliding wide, spinning or driving
    straight is outside."""

    steer_ratio: float
    wheelbase_m: float
    min_yaw_radps: float = 0.05
    lo: float = 0.5
    hi: float = 1.3


@dataclass(frozen=True)
class Redundancy:
    """A plausibility check between redundant signals: ``subject`` (or, with ``minus``, the difference
    ``subject - minus``: both are then under test) must agree with the value its ``references`` predict within
    ``tolerance_abs + tolerance_rel * |subject| + sum(c * |signal| for signal, c in tolerance_per)`` (in the
    subject's unit). The prediction, by
    ``relation``: ``"mean"``, ``scale`` times the mean of the references; ``"product"``, ``scale`` times their
    product; ``"ratio"``, ``scale`` times the first over the second (judged only where ``above`` keeps the
    second away from 0); ``"difference"``, ``scale`` times the first minus the second; ``"boost"``, the
    :class:`BoostCurve` ``boost`` of references ``(torsion-bar torque, speed)``.

    The subject (and ``minus``) are estimator inputs. A signal a check reads that the model does not (a *check
    reference*, such as the rear wheel speeds) is read by the daemon for the check alone: when it is stale the
    check is not judged, and the estimate's status does not change.

    A receiver judges the check only on ticks where none of the signals it reads is stale, each ``steady``
    signal moved by at most its rate (unit/s) since the previous tick, each ``within`` signal is at most its
    bound in magnitude, each ``above`` signal is at least its bound (signed), the prediction is at least
    ``min_expected`` and at most ``max_expected`` in magnitude and, with ``turn``, the car turns with grip
    (:class:`SteadyTurn`, references ``(yaw rate, vx)`` and the steering angle). With ``window == 0`` it flags
    the subject implausible after ``debounce_ticks`` consecutive failing judged 20 Hz ticks and clears it after
    as many passing ones, an unjudged tick holding
    the verdict and restarting the count (a skid or a wheel spin of a few ticks is not a fault); with
    ``window > 0``, once ``debounce_ticks`` of the last ``window`` judged ticks failed (cleared once as many
    passed), unjudged ticks neither counting nor restarting.

    Attributes:
        name: the check's name (logs, counters). subject: the signal under test.
        references: the signals that should agree with it. scale: references -> subject unit.
    """

    name: str
    subject: str
    references: tuple[str, ...]
    scale: float
    tolerance_abs: float
    tolerance_rel: float
    debounce_ticks: int = 3
    relation: Literal["mean", "product", "ratio", "difference", "boost"] = "mean"
    steady: tuple[tuple[str, float], ...] = ()
    within: tuple[tuple[str, float], ...] = ()
    above: tuple[tuple[str, float], ...] = ()
    turn: SteadyTurn | None = None
    boost: BoostCurve | None = None
    max_expected: float = math.inf
    min_expected: float = 0.0
    window: int = 0
    minus: str | None = None
    tolerance_per: tuple[tuple[str, float], ...] = ()

    @property
    def subjects(self) -> tuple[str, ...]:
        """The signals under test: ``subject``, and ``minus`` when set (a failed check marks both implausible)."""
        return (self.subject,) if self.minus is None else (self.subject, self.minus)

    @property
    def reads(self) -> tuple[str, ...]:
        """Every signal the check reads (compared, steady, bounded and, for a turn, the steering angle), once."""
        return tuple(dict.fromkeys((*self.subjects, *self.references,
                                    *(g for g, _ in (*self.steady, *self.within, *self.above, *self.tolerance_per)),
                                    *(("steer_angle_rad",) if self.turn is not None else ()))))


#: Rolling radius (m) the redundancy of vehicle speed and front wheel speeds assumes: the catalogue car's
#: tyre loaded statically (the simulator's effective rolling radius is 0.304-0.307 m in its manoeuvres).
ROLLING_RADIUS_M = 0.305

#: The catalogue car's EPAS calibration (its supplier's boost curve; the simulator's ``[steering]`` assist
#: parameters are the same numbers). Another car must state its own here.
EPAS_BOOST = BoostCurve(speeds_mps=(0.0, 8.0, 15.0, 22.0, 30.0, 45.0), gains=(10.0, 6.0, 4.0, 3.0, 2.4, 2.0),
                        knee_nm=1.0, max_nm=60.0)
#: The catalogue car's steering ratio (steering-wheel / mean road-wheel angle) and wheelbase (m).
STEADY_TURN = SteadyTurn(steer_ratio=14.8, wheelbase_m=2.685)
#: The catalogue car's front and rear track (m): the lateral distance between an axle's wheel centres.
TRACK_FRONT_M = 1.55
TRACK_REAR_M = 1.52
#: The largest difference of the two rear tyres' rolling radii (a share of the radius) the yaw-rate check allows
#: for without calling it a fault: a rear tyre 0.6 bar below its partner rolls about 0.9 % smaller (a campaign
#: draws one wheel in four down by 0.2-0.6 bar); ESCs learn this difference, the daemon does not.
REAR_RADIUS_MISMATCH = 0.01

#: Plausibility checks between redundant signals on the bus.
REDUNDANCIES: tuple[Redundancy, ...] = (
    # the ESC speed against the front wheels: 15 % covers wheel slip under traction/braking and the
    # outer/inner wheel paths in a turn; 1.5 m/s covers the quantisation and lags at walking speed. The car
    # has no ABS or traction control: judged only while neither brakes nor drive can lock or spin the driven
    # front wheels (|ax| <= 1 m/s^2; |motor torque| <= 30 Nm, which cruises at up to 130 km/h; wheel speeds
    # changing by at most 2 m/s^2)
    Redundancy("vx_vs_front_wheel_speed", "vx_mps", ("wheel_speed_fl_radps", "wheel_speed_fr_radps"),
               ROLLING_RADIUS_M, tolerance_abs=1.5, tolerance_rel=0.15,
               steady=(("wheel_speed_fl_radps", 2.0 / ROLLING_RADIUS_M),
                       ("wheel_speed_fr_radps", 2.0 / ROLLING_RADIUS_M)),
               within=(("ax_mps2", 1.0), ("motor_torque_nm", 30.0))),
    # the IMU's lateral acceleration against yaw rate x speed (ay = r vx + dvy/dt: equal in a steady turn); the
    # body roll puts g sin(roll), about 8 % of ay, on the sensor axis; judged only in steady turns with grip
    # (steering within 0.25 rad/s, yaw rate within 0.2 rad/s^2 per tick), for 1 s, so that a slide or the
    # onset of a spin (where dvy/dt is large) is never taken for a sensor fault; and only while r vx is at most
    # 11 m/s^2 (1.1 g), which no road car sustains in a turn: a car yawing faster is spinning, whatever its yaw
    # rate against the steering says (a fishhook on mu 1 spun with r vx at 12-16 m/s^2 and ay at 9 for 1 s)
    Redundancy("ay_vs_yaw_rate_times_speed", "ay_mps2", ("yaw_rate_radps", "vx_mps"), 1.0,
               tolerance_abs=1.0, tolerance_rel=0.25, debounce_ticks=20, relation="product",
               steady=(("steer_angle_rad", 0.25), ("yaw_rate_radps", 0.2)), turn=STEADY_TURN, max_expected=11.0),
    # the EPAS assist torque against the torsion-bar torque through the boost curve (the catalogue carries no
    # separate EPAS motor torque: assist_torque_nm is that motor's torque referred to the column); judged while
    # the steering wheel moves slower than 0.25 rad/s (the EPAS damping and back-EMF limit act on column speed)
    # and the car brakes or accelerates at most 4 m/s^2: the car has no ABS, and a hard stop locks wheels so
    # that the ESC's speed, which sets the gain the check expects, reads a third below the car's (braking in a
    # turn at 120 km/h on mu 1 tripped it in 4 of 1160 simulated runs)
    Redundancy("assist_vs_boosted_steer_torque", "assist_torque_nm", ("steer_torque_nm", "vx_mps"), 1.0,
               tolerance_abs=2.0, tolerance_rel=0.2, debounce_ticks=10, relation="boost",
               steady=(("steer_angle_rad", 0.25),), within=(("ax_mps2", 4.0),), boost=EPAS_BOOST),
    # the same judged only where the boost is 3 Nm or more (near zero torque a gain of the assist is invisible:
    # the check above, at 10 ticks in a row, sees an offset there but almost never a gain), on 8 of the last 10
    # judged ticks (unjudged ticks do not restart it, so a steering that rests now and then still adds up)
    Redundancy("assist_vs_boost_above_3nm", "assist_torque_nm", ("steer_torque_nm", "vx_mps"), 1.0,
               tolerance_abs=2.0, tolerance_rel=0.2, debounce_ticks=8, window=10, relation="boost",
               steady=(("steer_angle_rad", 0.25),), within=(("ax_mps2", 4.0),), boost=EPAS_BOOST, min_expected=3.0),
    # the steering-wheel angle against the yaw rate when the car drives straight: the kinematic angle
    # ``i L r / vx`` is then near 0, and a car held straight (|r| <= 0.05 rad/s, |ay| <= 0.5 m/s^2, steering
    # within 0.25 rad/s and the yaw rate within 0.1 rad/s^2, at 8 m/s or more) by a road wheel turned 1.4 deg
    # (0.35 rad at the wheel) would need a road with no grip at all. Road crown, crosswind and the sensor's zero
    # take a few degrees; 0.35 rad is three times the largest residual of the simulated campaigns (0.12 rad,
    # mu 0.2 to 1, circuits included). It catches a steering-angle sensor's offset (or a wrong zero after a
    # wheel alignment) whenever the car drives straight, which the turn checks cannot: such an offset puts the
    # car outside "turning with grip" for good
    Redundancy("steer_angle_vs_straight_yaw", "steer_angle_rad", ("yaw_rate_radps", "vx_mps"),
               STEADY_TURN.steer_ratio * STEADY_TURN.wheelbase_m, tolerance_abs=0.35, tolerance_rel=0.0,
               debounce_ticks=10, relation="ratio", steady=(("steer_angle_rad", 0.25), ("yaw_rate_radps", 0.1)),
               within=(("yaw_rate_radps", 0.05), ("ay_mps2", 0.5)), above=(("vx_mps", 8.0),)),
    # the yaw rate against the rear wheel speeds' difference: the rear wheels are undriven and unsteered, so
    # (w_rr - w_rl) r / track is the yaw rate whatever the side-slip. Judged at 5 m/s or more, braking or
    # accelerating at most 1.5 m/s^2 (no ABS: braked rear wheels slip apart, and lock), cornering at most 4 m/s^2
    # (the outer tyre's load shrinks its rolling radius: the rear-wheel yaw reads high by about 6e-4 x ay x vx, and
    # an unloaded inner wheel of a car spinning on mu 1 slows down), with the yaw rate changing by at most
    # 1 rad/s^2 (the wheel speeds lag the IMU by some 80 ms) and each rear wheel by at most 2 m/s^2. Tolerance:
    # 0.08 rad/s + 15 % + the yaw rate a 1 % difference of the rear rolling radii reads at vx. Debounced on 8 of
    # the last 10 judged ticks: unjudged ticks do not restart it. A rear wheel-speed message that is missing
    # leaves it unjudged, never the estimate INVALID
    Redundancy("yaw_rate_vs_rear_wheel_speeds", "yaw_rate_radps", ("wheel_speed_rr_radps", "wheel_speed_rl_radps"),
               ROLLING_RADIUS_M / TRACK_REAR_M, tolerance_abs=0.08, tolerance_rel=0.15,
               tolerance_per=(("vx_mps", REAR_RADIUS_MISMATCH / TRACK_REAR_M),), debounce_ticks=8, window=10,
               relation="difference",
               steady=(("yaw_rate_radps", 1.0), ("wheel_speed_rl_radps", 2.0 / ROLLING_RADIUS_M),
                       ("wheel_speed_rr_radps", 2.0 / ROLLING_RADIUS_M)),
               within=(("ax_mps2", 1.5), ("ay_mps2", 4.0)), above=(("vx_mps", 5.0),)),
    # the front suspension's roll against the rear's: a rigid body rolls as one, so the front deflections'
    # difference is the rear's times the ratio of the tracks. Tolerance 8 mm + 20 % (tyres' compliance under the
    # lateral load transfer, which the simulator does not have); judged at 8 m/s or more (a car standing with a
    # wheel on a kerb twists its body); debounced on 8 of the last 10 judged ticks (a bump under one wheel twists
    # it for a tick or two). Both front deflections are under test
    Redundancy("front_roll_vs_rear_roll", "susp_defl_fr_m", ("susp_defl_rr_m", "susp_defl_rl_m"),
               TRACK_FRONT_M / TRACK_REAR_M, tolerance_abs=0.008, tolerance_rel=0.2, debounce_ticks=8, window=10,
               relation="difference", minus="susp_defl_fl_m", above=(("vx_mps", 8.0),)),
)


def signal(name: str) -> Signal:
    """Return the catalogue entry for ``name``.

    Raises:
        KeyError: with the list of close names when ``name`` is not catalogued.
    """
    try:
        return SIGNALS[name]
    except KeyError:
        import difflib

        close = difflib.get_close_matches(name, SIGNALS.keys(), n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        raise KeyError(f"unknown signal {name!r}{hint}") from None


def by_message(message: str) -> tuple[Signal, ...]:
    """The catalogued signals carried by DBC message ``message``."""
    return tuple(s for s in _ALL if s.message == message)


assert len(INPUTS) == 12, INPUTS
assert OUTPUTS == ("sat_fl_nm", "sat_fr_nm"), OUTPUTS
assert all(n in SIGNALS for r in REDUNDANCIES for n in r.reads), REDUNDANCIES
assert all(SIGNALS[s].role == "input" for r in REDUNDANCIES for s in r.subjects), REDUNDANCIES
assert all(0 <= r.window and (r.window == 0 or r.debounce_ticks <= r.window) for r in REDUNDANCIES), REDUNDANCIES
assert all((r.relation == "boost") == (r.boost is not None) and len(r.references) == 2 or r.relation == "mean"
           for r in REDUNDANCIES), REDUNDANCIES
assert all(r.relation != "ratio" or any(g == r.references[1] and b > 0 for g, b in r.above)
           for r in REDUNDANCIES), REDUNDANCIES
