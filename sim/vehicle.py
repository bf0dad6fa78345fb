"""Vehicle dynamics: sprung body, suspension corners, wheel spin, EPAS column.

One :class:`Vehicle` advances a *batch* of B independent runs at once: every
state is an array whose first axis is the run, so one call of
:meth:`Vehicle.derivatives` evaluates the whole batch with numpy.

Frames and signs (ISO 8855): body axes x forward, y left, z up at the centre
of gravity; yaw, steer and yaw rate positive counter-clockwise seen from above;
roll ``phi`` positive right side down (a left turn rolls the body to the
right, phi > 0); pitch ``theta`` positive nose down (braking, theta > 0).
Wheels are indexed FL, FR, RL, RR. Suspension compression is positive in bump.

Degrees of freedom (29 states per run, see the ``I*`` indices):

* planar body: global x, y, heading psi, body-frame vx, vy and yaw rate r;
* sprung mass: heave z (up), roll phi and pitch theta with their rates, moving
  on linear springs, dampers, anti-roll bars and progressive bump stops at the
  four corners; lateral and longitudinal tyre forces reach the body at the
  roll-centre and pitch-centre heights (geometric load transfer);
* four wheel spins omega (drive torque through an open differential to the
  front wheels, brake torques with a front/rear balance, rolling resistance);
* four lagged slip angles and four lagged slip ratios: MF 6.1 first-order
  transient slip with relaxation lengths sigma = K / C from the tyre model;
* the EPAS column (paper eq. 1 in spirit): steering-wheel angle and rate,
  pinion angle and rate. The assist motor's current loop (about 1 kHz) is
  far faster than anything here, so the assist torque is the boost curve's
  output on the present torsion-bar torque (no lag state). The torsion bar
  between them is the torque sensor; the rack force comes from both front
  tyres' Mz plus their Fy (caster trail) and Fx (scrub radius for brake forces,
  kingpin offset at the wheel centre for drive forces) moment arms about the
  kingpin axes, with kingpin-inclination lifting torque, Ackermann geometry,
  Coulomb and viscous friction;
* travelled distance (for road friction that changes along the road).

Wheel loads are not a static formula: they are the static loads plus the
suspension corner forces (springs, dampers, bars, stops), the geometric
transfer through the roll and pitch centres and the unsprung masses' inertia.
The geometric part uses the tyre forces of the previous integration step (a
2 ms lag on 10-20 % of the transfer) to avoid an algebraic loop.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim.params import resolve_data_file
from sim.tir import TirError, read_tir
from sim.tyre import MagicFormula61, TyreOutput, overflow_problem

# ---- state layout -----------------------------------------------------------------
IX, IY, IPSI, IVX, IVY, IR = range(6)
IZ, IZD, IPHI, IP, ITH, IQ = range(6, 12)
IOM = slice(12, 16)
IAL = slice(16, 20)
IKA = slice(20, 24)
ISW, ISWD, IPN, IPND, IS = range(24, 29)
NSTATE = 29

WHEELS = ("fl", "fr", "rl", "rr")
#: +1 for left wheels (y > 0), -1 for right wheels
SIDE = np.array([1.0, -1.0, 1.0, -1.0])
#: the tyre file describes a right-hand tyre: left tyres are evaluated mirrored
#: (slip angle negated in, lateral force and aligning torque negated out)
MIRROR = -SIDE


@dataclass
class Inputs:
    """Actuator inputs of one control step, shape (B,) or (B, 4).

    All are held over the step except the robot's steering reference, which
    ramps at ``steer_cmd_rate`` (see ``steer_lead_s``).

    Attributes:
        steer_cmd: steering-wheel angle the robot/driver commands (rad).
        steer_cmd_rate: its rate (rad/s).
        hands_off: True where the driver applies no torque at all (free steer).
        drive_torque: wheel torque from the motor, per wheel (Nm, (B, 4)).
        brake_torque: brake torque magnitude per wheel (Nm, (B, 4), >= 0).
        mu: road friction coefficient under the car (B,).
        steer_lead_s: time of the evaluation relative to the end of the control
            step (s, -CONTROL_DT..0): the robot's reference is ``steer_cmd +
            steer_cmd_rate * steer_lead_s``, a ramp from the previous command to
            this one. A servo interpolates its set-points; a reference held
            constant over the step, with the rate feed-forward saying it moves,
            kicked the column with a 100 Hz saw-tooth (up to 190 Nm at the
            fishhook's 720 deg/s).
    """

    steer_cmd: np.ndarray
    steer_cmd_rate: np.ndarray
    hands_off: np.ndarray
    drive_torque: np.ndarray
    brake_torque: np.ndarray
    mu: np.ndarray
    steer_lead_s: float = 0.0


@functools.lru_cache(maxsize=8)
def _load_tyre(path: str, mtime: float) -> MagicFormula61:
    """The model of a property file; TirError names what is wrong, as well a model that overflows in the
    tyre's usual range (:func:`sim.tyre.overflow_problem`: it could only make the simulation diverge)."""
    tir = read_tir(path)
    model = MagicFormula61(tir, source=tir.path)
    problem = overflow_problem(model, tir)
    if problem is not None:
        raise TirError(problem)
    return model


def tyre_files(params: Mapping[str, Any]) -> tuple[str, str]:
    """(front, rear) tyre property files: ``tyres.file_front`` / ``tyres.file_rear``, "" or absent -> ``tyres.file``."""
    ty = params["tyres"]
    return ty.get("file_front") or ty["file"], ty.get("file_rear") or ty["file"]


def tyre_for(params: Mapping[str, Any], axle: str = "front") -> MagicFormula61:
    """The tyre model of one axle (``"front"`` or ``"rear"``, see :func:`tyre_files`; loaded once per file version)."""
    path = resolve_data_file(tyre_files(params)[0 if axle == "front" else 1])
    try:
        mtime = path.stat().st_mtime
    except OSError:
        mtime = -1.0  # let the reader report the missing file with its own message
    return _load_tyre(str(path), mtime)


class AxleTyres:
    """Different tyres on the front and rear axles, with the interface of :class:`MagicFormula61`
    for arrays whose last axis is the wheel (FL, FR, RL, RR).

    Inputs with a last axis of 4 are split into front (FL, FR) and rear (RL, RR) columns;
    other inputs (scalars, (B, 1) columns) go to both tyres. ``params`` are the front tyre's.
    """

    def __init__(self, front: MagicFormula61, rear: MagicFormula61) -> None:
        self.front, self.rear = front, rear
        self.params = front.params

    def per_wheel(self, key: str, default: float) -> np.ndarray:
        """(4,) value of a coefficient for FL, FR, RL, RR."""
        f, r = (float(t.params.get(key, default)) for t in (self.front, self.rear))  # type: ignore[arg-type]
        return np.array([f, f, r, r])

    @staticmethod
    def _split(args: Sequence[Any]) -> tuple[list[Any], list[Any]]:
        def part(x: Any, sl: slice) -> Any:
            return x[..., sl] if isinstance(x, np.ndarray) and x.ndim and x.shape[-1] == 4 else x

        return [part(a, slice(0, 2)) for a in args], [part(a, slice(2, 4)) for a in args]

    def steady_state(self, *args: Any, **kwargs: Any) -> TyreOutput:
        """:meth:`MagicFormula61.steady_state` of each axle, joined along the wheel axis."""
        fa, ra = self._split(args)
        kf, kr = self._split(list(kwargs.values()))
        f = self.front.steady_state(*fa, **dict(zip(kwargs, kf, strict=True)))
        r = self.rear.steady_state(*ra, **dict(zip(kwargs, kr, strict=True)))
        return TyreOutput._make(None if a is None else np.concatenate([a, b], axis=-1)
                                for a, b in zip(f, r, strict=True))

    def effective_rolling_radius(self, *args: Any) -> np.ndarray:
        fa, ra = self._split(args)
        return np.concatenate([self.front.effective_rolling_radius(*fa), self.rear.effective_rolling_radius(*ra)],
                              axis=-1)

    def relaxation_lengths(self, *args: Any) -> tuple[np.ndarray, np.ndarray]:
        fa, ra = self._split(args)
        f, r = self.front.relaxation_lengths(*fa), self.rear.relaxation_lengths(*ra)
        return np.concatenate([f[0], r[0]], axis=-1), np.concatenate([f[1], r[1]], axis=-1)


def _col(values: Sequence[float]) -> np.ndarray:
    return np.asarray(values, dtype=float)


class Vehicle:
    """A batch of B cars, one parameter tree per run (trees may differ).

    The effective rolling radii and relaxation lengths depend on the wheel loads
    only; they are evaluated at the first stage of each integration step and held
    over its other stages (call :meth:`new_step` before each step).

    Args:
        trees: one parameter tree per run (see :mod:`sim.params`). Trees may
            differ in any numeric value; they must share the tyre file.
        tyre: an already-loaded tyre model of all four wheels (default: the trees' tyre files).

    Front and rear axles may carry different tyres (:func:`tyre_files`); the body geometry
    (unsprung masses' centre height) then uses the front tyre's unloaded radius, the wheel
    spin each axle's own.
    """

    SIGMA_MIN = 0.12  # m, floor of the relaxation lengths

    def __init__(self, trees: Sequence[Mapping[str, Any]], tyre: MagicFormula61 | None = None):
        if not trees:
            raise ValueError("need at least one parameter tree")
        files = {tyre_files(t) for t in trees}
        if len(files) != 1:
            raise ValueError(f"runs of one batch must share their tyre files, got {sorted(files)}")
        front = tyre if tyre is not None else tyre_for(trees[0])
        rear = tyre if tyre is not None else tyre_for(trees[0], "rear")
        self.tyre: MagicFormula61 | AxleTyres = front if rear is front else AxleTyres(front, rear)
        self.B = len(trees)
        self._build(trees)
        self._fy_axle = np.zeros((self.B, 2))  # previous step's lateral force per axle (body y)
        self._fx_total = np.zeros(self.B)  # previous step's total longitudinal force (body x)
        self._acc = np.zeros((self.B, 2))  # previous step's (ax, ay) kinematic accelerations
        self._slow: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    # ---- parameters ------------------------------------------------------------
    def _build(self, trees: Sequence[Mapping[str, Any]]) -> None:
        def p(section: str, key: str) -> np.ndarray:
            return _col([t[section][key] for t in trees])

        g = self.g = p("simulation", "gravity_mps2")
        self.m = p("vehicle", "mass_kg")
        L = self.L = p("vehicle", "wheelbase_m")
        frac = p("vehicle", "front_axle_load_fraction")
        self.a = L * (1.0 - frac)  # CG to front axle
        self.b = L * frac  # CG to rear axle
        self.h = p("vehicle", "cg_height_m")
        tf, tr = p("vehicle", "track_front_m"), p("vehicle", "track_rear_m")
        self.track = np.stack([tf, tf, tr, tr], axis=1)
        self.xw = np.stack([self.a, self.a, -self.b, -self.b], axis=1)
        self.yw = self.track * 0.5 * SIDE
        self.Iz = p("vehicle", "yaw_inertia_kgm2")
        self.Ixs = p("vehicle", "roll_inertia_sprung_kgm2")
        self.Iys = p("vehicle", "pitch_inertia_sprung_kgm2")
        muf, mur = p("vehicle", "unsprung_mass_front_kg"), p("vehicle", "unsprung_mass_rear_kg")
        self.mu_axle = np.stack([2 * muf, 2 * mur], axis=1)
        self.ms = self.m - 2 * muf - 2 * mur
        self.R0 = float(self.tyre.params["UNLOADED_RADIUS"])  # the front tyre's
        # unloaded radius and vertical stiffness of each wheel (scalars when all four tyres are alike)
        self._r0w, self._czw = (self.R0, float(self.tyre.params.get("VERTICAL_STIFFNESS", 2.0e5)))
        if isinstance(self.tyre, AxleTyres):
            self._r0w, self._czw = self.tyre.per_wheel("UNLOADED_RADIUS", 2.0e5), \
                self.tyre.per_wheel("VERTICAL_STIFFNESS", 2.0e5)
        self.hs = (self.m * self.h - (2 * muf + 2 * mur) * self.R0) / self.ms
        self.hrc = np.stack([p("vehicle", "roll_centre_height_front_m"),
                             p("vehicle", "roll_centre_height_rear_m")], axis=1)
        self.hra = (self.hrc[:, 0] * self.b + self.hrc[:, 1] * self.a) / L  # roll axis height at the CG
        self.hpc = p("vehicle", "pitch_centre_height_m")

        # static wheel loads: axle share, split left/right
        wf = self.m * g * frac * 0.5
        wr = self.m * g * (1 - frac) * 0.5
        self.fz_static = np.stack([wf, wf, wr, wr], axis=1)

        s = "suspension"
        kf, kr = p(s, "wheel_rate_front_npm"), p(s, "wheel_rate_rear_npm")
        cf, cr = p(s, "damping_front_nspm"), p(s, "damping_rear_nspm")
        self.k_w = np.stack([kf, kf, kr, kr], axis=1)
        self.c_w = np.stack([cf, cf, cr, cr], axis=1)
        self.k_arb = np.stack([p(s, "arb_front_npm"), p(s, "arb_rear_npm")], axis=1)
        self.stop_gap = p(s, "bump_stop_travel_m")[:, None]
        self.stop_k = p(s, "bump_stop_rate_npm")[:, None]
        crf, crr = p(s, "camber_roll_factor_front"), p(s, "camber_roll_factor_rear")
        self.camber_roll = np.stack([crf, crf, crr, crr], axis=1)

        self.drag = 0.5 * p("aero", "air_density_kgpm3") * p("aero", "drag_coefficient") * p(
            "aero", "frontal_area_m2"
        )

        pt = "powertrain"
        self.motor_tmax = p(pt, "motor_max_torque_nm")
        self.motor_pmax = p(pt, "motor_max_power_w")
        self.motor_wmax = p(pt, "motor_max_speed_radps")
        self.gear = p(pt, "gear_ratio")
        self.eta = p(pt, "efficiency")
        self.motor_tau = p(pt, "torque_time_constant_s")
        self.brake_front_max = p("brakes", "max_wheel_torque_front_nm")
        self.brake_share = p("brakes", "front_share")
        self.brake_tau = p("brakes", "pressure_time_constant_s")
        jf, jr = p("wheels", "spin_inertia_front_kgm2"), p("wheels", "spin_inertia_rear_kgm2")
        self.Iw = np.stack([jf, jf, jr, jr], axis=1)

        ty = "tyres"
        pf, pr = p(ty, "pressure_front_pa"), p(ty, "pressure_rear_pa")
        # per wheel: the axle's pressure -+ half its left-right difference (a tree without the key: equal sides)
        df, dr = (np.array([float(t[ty].get(k, 0.0)) for t in trees]) * 0.5
                  for k in ("pressure_left_right_front_pa", "pressure_left_right_rear_pa"))
        self.pressure = np.stack([pf + df, pf - df, pr + dr, pr - dr], axis=1)
        cfr, crr_ = p(ty, "static_camber_front_rad"), p(ty, "static_camber_rear_rad")
        self.camber0 = np.stack([cfr, cfr, crr_, crr_], axis=1)
        tif, tir = p(ty, "toe_in_front_rad"), p(ty, "toe_in_rear_rad")
        # toe-in: left wheel points right (negative steer), right wheel points left
        self.toe = -SIDE * np.stack([tif, tif, tir, tir], axis=1)
        self.relax_scale = p(ty, "relaxation_scale")[:, None]
        self.friction_scale = p(ty, "friction_scale")

        st = "steering"
        self.ratio = p(st, "ratio")
        self.ack = p(st, "ackermann_fraction") * tf / (2.0 * L)
        self.J_sw = p(st, "wheel_inertia_kgm2")
        self.c_sw = p(st, "wheel_damping_nmsprad")
        self.k_tb = p(st, "torsion_bar_stiffness_nmprad")
        self.c_tb = p(st, "torsion_bar_damping_nmsprad")
        self.J_p = p(st, "lower_inertia_kgm2")
        self.c_p = p(st, "lower_damping_nmsprad")
        self.f_c = p(st, "coulomb_friction_nm")
        self.f_v = p(st, "friction_velocity_radps")
        self.trail = p(st, "caster_trail_m")
        self.scrub = p(st, "scrub_radius_m")
        self.offset_wc = p(st, "kingpin_offset_wheel_centre_m")
        self.kpi_lift = self.offset_wc * np.sin(p(st, "kingpin_inclination_rad"))
        self.assist_v = np.array([t[st]["assist_speeds_mps"] for t in trees], dtype=float)
        self.assist_g = np.array([t[st]["assist_gains"] for t in trees], dtype=float)
        if self.assist_v.shape != self.assist_g.shape:
            raise ValueError("steering.assist_speeds_mps and steering.assist_gains differ in length")
        if np.any(np.diff(self.assist_v, axis=1) <= 0):
            raise ValueError("steering.assist_speeds_mps must increase strictly")
        self.assist_knee = p(st, "assist_knee_nm")
        self.assist_max = p(st, "assist_max_nm")
        self.assist_w0 = p(st, "assist_noload_speed_radps")
        self.assist_damping = p(st, "assist_damping_nmsprad")

        dr = "driver"
        self.k_robot = p(dr, "robot_stiffness_nmprad")
        self.c_robot = p(dr, "robot_damping_nmsprad")

    # ---- helpers ------------------------------------------------------------------
    def assist_gain(self, vx: np.ndarray) -> np.ndarray:
        """Speed-dependent boost gain (assist / torsion-bar torque), per run."""
        v = np.clip(vx, self.assist_v[:, 0], self.assist_v[:, -1])
        # piecewise-linear interpolation, vectorised over runs
        idx = np.clip((self.assist_v <= v[:, None]).sum(axis=1) - 1, 0, self.assist_v.shape[1] - 2)
        r = np.arange(self.B)
        v0, v1 = self.assist_v[r, idx], self.assist_v[r, idx + 1]
        g0, g1 = self.assist_g[r, idx], self.assist_g[r, idx + 1]
        return g0 + (g1 - g0) * (v - v0) / (v1 - v0)

    def boost(self, t_bar: np.ndarray, vx: np.ndarray, pinion_rate: np.ndarray | float = 0.0) -> np.ndarray:
        """Assist torque of the EPAS (column-referred Nm).

        Boost curve ``G(v) * T * |T| / (|T| + knee)`` (quadratic for small
        torsion-bar torque, tending to the speed-dependent gain G(v)), minus the
        active damping on the column speed, limited by the motor's torque-speed
        curve (full torque at rest, none at the no-load speed).
        """
        a = np.abs(t_bar)
        demand = self.assist_gain(vx) * t_bar * a / (a + self.assist_knee) - self.assist_damping * pinion_rate
        limit = self.assist_max * np.clip(1.0 - np.abs(pinion_rate) / self.assist_w0, 0.0, 1.0)
        return np.clip(demand, -limit, limit)

    def road_wheel_angles(self, pinion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road-wheel steer angles (B, 4) and d(delta)/d(pinion) of the fronts (B, 2).

        The rack moves both knuckles; a share of perfect Ackermann makes the inner
        wheel steer more: |delta_in| - |delta_out| ~ ackermann * track/L * delta^2.
        """
        d = pinion / self.ratio
        # even in d: in a left turn (d > 0) the left wheel is inside and steers more,
        # in a right turn (d < 0) the right wheel does
        extra = self.ack * d * d
        delta = np.empty((self.B, 4))
        delta[:, 0] = d + extra
        delta[:, 1] = d - extra
        delta[:, 2:] = 0.0
        delta += self.toe
        dd = 2.0 * self.ack * d
        ddelta = np.stack([(1.0 + dd) / self.ratio, (1.0 - dd) / self.ratio], axis=1)
        return delta, ddelta

    def static_rolling_radius(self, speed: np.ndarray) -> np.ndarray:
        """(B, 4) effective rolling radius (m) of each wheel at its static load, rolling at ``speed`` (m/s)."""
        return self.tyre.effective_rolling_radius(self.fz_static, speed[:, None] / self._r0w, self.pressure)

    def initial_state(self, speed: np.ndarray, heading: np.ndarray | float = 0.0) -> np.ndarray:
        """Straight-line steady driving at ``speed`` (m/s), springs at static height."""
        x = np.zeros((self.B, NSTATE))
        x[:, IVX] = speed
        x[:, IPSI] = heading
        x[:, IOM] = speed[:, None] / self.static_rolling_radius(speed)
        self._fy_axle[:] = 0.0
        self._fx_total[:] = 0.0
        self._acc[:] = 0.0
        return x

    # ---- equations of motion -------------------------------------------------------
    def derivatives(self, x: np.ndarray, u: Inputs) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """State derivative dx/dt (B, 30) and the auxiliary outputs at state x."""
        g = self.g
        vx, vy, r = x[:, IVX], x[:, IVY], x[:, IR]
        phi, p_rate, th, q_rate = x[:, IPHI], x[:, IP], x[:, ITH], x[:, IQ]
        z, zd = x[:, IZ], x[:, IZD]
        omega = x[:, IOM]
        alpha_l = x[:, IAL]
        kappa_l = x[:, IKA]

        # --- suspension corners and wheel loads --------------------------------
        xw, yw = self.xw, self.yw
        comp = -(z[:, None] + yw * phi[:, None] - xw * th[:, None])
        comp_rate = -(zd[:, None] + yw * p_rate[:, None] - xw * q_rate[:, None])
        f_susp = self.k_w * comp + self.c_w * comp_rate
        diff_f = comp[:, 0] - comp[:, 1]
        diff_r = comp[:, 2] - comp[:, 3]
        f_susp[:, 0] += self.k_arb[:, 0] * diff_f
        f_susp[:, 1] -= self.k_arb[:, 0] * diff_f
        f_susp[:, 2] += self.k_arb[:, 1] * diff_r
        f_susp[:, 3] -= self.k_arb[:, 1] * diff_r
        over = np.abs(comp) - self.stop_gap
        f_susp += np.where(over > 0.0, self.stop_k * over * over / 0.01 * np.sign(comp), 0.0)

        ax_prev, ay_prev = self._acc[:, 0], self._acc[:, 1]
        # geometric (roll-centre) lateral transfer and unsprung inertia, per axle
        lat = (self._fy_axle * self.hrc + self.mu_axle * ay_prev[:, None] * self.R0) / self.track[:, ::2]
        lon = (self._fx_total * self.hpc + self.mu_axle.sum(axis=1) * ax_prev * self.R0) / self.L
        fz = self.fz_static + f_susp
        fz[:, 0] -= lat[:, 0]
        fz[:, 1] += lat[:, 0]
        fz[:, 2] -= lat[:, 1]
        fz[:, 3] += lat[:, 1]
        fz[:, :2] -= 0.5 * lon[:, None]
        fz[:, 2:] += 0.5 * lon[:, None]
        np.maximum(fz, 0.0, out=fz)

        # --- steering column --------------------------------------------------------
        sw, swd, pn, pnd = x[:, ISW], x[:, ISWD], x[:, IPN], x[:, IPND]
        delta, ddelta = self.road_wheel_angles(pn)

        # --- wheel kinematics and slips ----------------------------------------------
        vxi = vx[:, None] - r[:, None] * yw
        vyi = vy[:, None] + r[:, None] * xw
        cd, sd = np.cos(delta), np.sin(delta)
        vcx = vxi * cd + vyi * sd
        vcy = -vxi * sd + vyi * cd
        avx = np.maximum(np.abs(vcx), 0.5)
        if self._slow is None:  # first stage of a step: load-dependent lengths, held over the step
            re = self.tyre.effective_rolling_radius(fz, omega, self.pressure)
            sig_k, sig_a = self.tyre.relaxation_lengths(fz, self.pressure)
            # a floor keeps the lag finite when a wheel lifts off (sigma -> 0 with Fz)
            sig_k = np.maximum(sig_k * self.relax_scale, self.SIGMA_MIN)
            sig_a = np.maximum(sig_a * self.relax_scale, self.SIGMA_MIN)
            self._slow = (re, sig_k, sig_a)
        re, sig_k, sig_a = self._slow
        alpha_inst = np.arctan(vcy / avx)
        kappa_inst = (omega * re - vcx) / avx
        d_alpha = (avx / sig_a) * (alpha_inst - alpha_l)
        d_kappa = (avx / sig_k) * (kappa_inst - kappa_l)

        # --- tyres (left tyres are mirrored right-hand tyres) --------------------------
        camber = self.camber0 - SIDE * self.camber_roll * phi[:, None]
        mu = (u.mu * self.friction_scale)[:, None]
        out = self.tyre.steady_state(fz, kappa_l, alpha_l * MIRROR, camber, vcx, self.pressure, mu)
        fx = out.fx
        fy = out.fy * MIRROR
        mz = out.mz * MIRROR
        my = out.my

        # --- body forces -------------------------------------------------------------
        fxb = fx * cd - fy * sd
        fyb = fx * sd + fy * cd
        sum_fx = fxb.sum(axis=1)
        sum_fy = fyb.sum(axis=1)
        aero = self.drag * vx * np.abs(vx)
        ax_kin = (sum_fx - aero) / self.m
        ay_kin = sum_fy / self.m
        yaw_mom = (xw * fyb - yw * fxb).sum(axis=1) + mz.sum(axis=1)

        dx = np.empty_like(x)
        cpsi, spsi = np.cos(x[:, IPSI]), np.sin(x[:, IPSI])
        dx[:, IX] = vx * cpsi - vy * spsi
        dx[:, IY] = vx * spsi + vy * cpsi
        dx[:, IPSI] = r
        dx[:, IVX] = ax_kin + r * vy
        dx[:, IVY] = ay_kin - r * vx
        dx[:, IR] = yaw_mom / self.Iz

        # --- sprung mass: heave, roll about the roll axis, pitch about the pitch centre --
        fy_axle = np.stack([fyb[:, 0] + fyb[:, 1], fyb[:, 2] + fyb[:, 3]], axis=1)
        roll_arm = self.hs[:, None] - self.hrc
        roll_mom = ((fy_axle - self.mu_axle * ay_kin[:, None]) * roll_arm).sum(axis=1)
        roll_mom += self.ms * g * (self.hs - self.hra) * phi + (yw * f_susp).sum(axis=1)
        pitch_mom = -(sum_fx - self.mu_axle.sum(axis=1) * ax_kin) * (self.hs - self.hpc)
        pitch_mom += self.ms * g * (self.hs - self.hpc) * th - (xw * f_susp).sum(axis=1)
        dx[:, IZ] = zd
        dx[:, IZD] = f_susp.sum(axis=1) / self.ms
        dx[:, IPHI] = p_rate
        dx[:, IP] = roll_mom / self.Ixs
        dx[:, ITH] = q_rate
        dx[:, IQ] = pitch_mom / self.Iys

        # --- wheel spin ----------------------------------------------------------------
        r_loaded = self._r0w - fz / self._czw
        brake = u.brake_torque * np.tanh(omega / 8.0)  # smooth lock-up: no stiff sign switch
        dx[:, IOM] = (u.drive_torque - brake - r_loaded * fx - np.abs(my) * np.tanh(omega)) / self.Iw
        dx[:, IAL] = d_alpha
        dx[:, IKA] = d_kappa

        # --- steering: kingpin moments -> pinion torque ----------------------------------
        t_bar = self.k_tb * (sw - pn) + self.c_tb * (swd - pnd)
        sw_ref = u.steer_cmd + u.steer_cmd_rate * u.steer_lead_s  # the robot's ramped reference
        t_drv = np.where(u.hands_off, 0.0,
                         self.k_robot * (sw_ref - sw) + self.c_robot * (u.steer_cmd_rate - swd))
        drive_force = u.drive_torque[:, :2] / r_loaded[:, :2]
        side = SIDE[:2]
        m_kp = (mz[:, :2] - self.trail[:, None] * fy[:, :2]
                - side * (self.scrub[:, None] * (fx[:, :2] - drive_force) + self.offset_wc[:, None] * drive_force)
                - fz[:, :2] * self.kpi_lift[:, None] * np.sin(delta[:, :2] - self.toe[:, :2]))
        t_road = (m_kp * ddelta).sum(axis=1)
        t_fric = self.f_c * np.tanh(pnd / self.f_v)
        t_assist = self.boost(t_bar, vx, pnd)
        dx[:, ISW] = swd
        dx[:, ISWD] = (t_drv - t_bar - self.c_sw * swd) / self.J_sw
        dx[:, IPN] = pnd
        dx[:, IPND] = (t_bar + t_assist + t_road - self.c_p * pnd - t_fric) / self.J_p
        dx[:, IS] = vx

        aux = {
            "fz": fz, "fx": fx, "fy": fy, "mz": mz, "delta": delta,
            "alpha": alpha_l, "kappa": kappa_l, "comp": comp,
            "ax_kin": ax_kin, "ay_kin": ay_kin, "t_bar": t_bar, "t_assist": t_assist,
            "fy_axle": fy_axle, "sum_fx": sum_fx, "omega": omega, "re": re,
        }
        return dx, aux

    def new_step(self) -> None:
        """Mark the start of an integration step (slow load-dependent terms are re-evaluated)."""
        self._slow = None

    def commit(self, aux: Mapping[str, np.ndarray]) -> None:
        """Remember this step's forces for the next step's geometric load transfer."""
        self._fy_axle[:] = aux["fy_axle"]
        self._fx_total[:] = aux["sum_fx"]
        self._acc[:, 0] = aux["ax_kin"]
        self._acc[:, 1] = aux["ay_kin"]
