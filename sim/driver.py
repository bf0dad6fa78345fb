"""Drivers: the steering robot, a path follower and a speed controller, vectorised.

A manoeuvre is described per run by a :class:`Plan`: tables on the control
grid (100 Hz) that say, at each instant, how the steering is driven (an
open-loop steering-wheel angle, following a path, holding the last angle, or
hands off) and how the speed is driven (a speed target, open-loop motor and
brake commands, or coasting). :class:`Driver` runs all plans of a batch at
once: one :meth:`Driver.update` call computes every run's actuator inputs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from sim.linear import linear_model
from sim.params import CONTROL_PERIOD_S
from sim.vehicle import IKA, IOM, IPSI, IR, IS, ISW, IVX, IX, IY, Inputs, Vehicle

# steering modes
STEER_TABLE, STEER_PATH, STEER_HOLD, STEER_FREE = 0, 1, 2, 3
# longitudinal modes
SPEED_TARGET, SPEED_OPEN, SPEED_COAST = 0, 1, 2

CONTROL_DT = CONTROL_PERIOD_S  # s, the driver's update period


@dataclass
class Plan:
    """One run's driving programme on the control grid ``k * CONTROL_DT``.

    Attributes:
        name: manoeuvre name.
        duration_s: length of the run (s).
        speed0_mps: initial forward speed (the run starts in straight, steady driving).
        steer_mode: (N,) int8 of STEER_* per control step.
        steer_sw: (N,) steering-wheel angle for STEER_TABLE steps (rad, + left).
        speed_mode: (N,) int8 of SPEED_* per control step.
        speed_target: (N,) target speed (m/s) for SPEED_TARGET steps.
        motor_cmd: (N,) motor torque (Nm) for SPEED_OPEN steps.
        brake_cmd: (N,) front-wheel brake torque (Nm per wheel) for SPEED_OPEN steps;
            the rear gets the brake balance's share.
        path: (M, 2) path to follow (global x, y in m, starting at the origin
            heading +x), resampled at ``path_ds``; None when never followed.
        path_speed: (M,) optional target speed along the path (m/s); where given it
            replaces ``speed_target`` while following the path.
        mu_dist: distances (m) where the road friction changes (increasing).
        mu_values: friction before the first distance and after each one (len+1).
        label: free-form metadata kept with the run (speed, mu, amplitude...).
        motor_feedforward: (N,) motor torque (Nm) the speed controller starts from
            in SPEED_TARGET steps, its feedback adding what tracking the target
            still needs (re-simulating a recorded run: the car's own recorded
            motor torque carries its accelerations and resistances, so the speed
            is tracked without the feedback loop's lag); None: feedback only.
        path_grip: (drive, brake) shares of the road's friction ``mu * g`` (-) that the
            driver allows itself as longitudinal acceleration while following
            ``path_speed``: it feeds the profile's own acceleration forward (so it brakes
            where the profile brakes, not a speed error later) and never asks for more
            drive or brake force than these shares of the grip left beside the
            cornering (a driver feathering throttle and brake; the car has no
            traction control or ABS), letting the brakes off while a wheel starts to
            lock (:meth:`Driver._lock_relief`) and the motor torque while a driven wheel
            starts to spin (:meth:`Driver._spin_relief`). None: speed feedback only, uncapped.
        track_half_width_m: while following the path, the car has left the track once
            its centre is farther than this from the path (m); the run ends there
            (:meth:`Driver.off_track`). None: no limit.
        planned_distance_m: distance along ``path`` (m, from its start) the car must have
            covered when the plan's time runs out for the run to have driven what it
            planned (a circuit: its laps; a double lane change: through the exit gate);
            short of it the run ends ``behind-plan`` (:func:`sim.engine.simulate_batch`).
            None: the run is planned by time only.
    """

    name: str
    duration_s: float
    speed0_mps: float
    steer_mode: np.ndarray
    steer_sw: np.ndarray
    speed_mode: np.ndarray
    speed_target: np.ndarray
    motor_cmd: np.ndarray
    brake_cmd: np.ndarray
    path: np.ndarray | None = None
    path_speed: np.ndarray | None = None
    path_ds: float = 1.0
    mu_dist: Sequence[float] = ()
    mu_values: Sequence[float] = (1.0,)
    label: dict = field(default_factory=dict)
    motor_feedforward: np.ndarray | None = None
    path_grip: tuple[float, float] | None = None
    track_half_width_m: float | None = None
    planned_distance_m: float | None = None

    @property
    def n(self) -> int:
        return len(self.steer_mode)

    @staticmethod
    def grid(duration_s: float) -> np.ndarray:
        """The control-grid times (s) of a run of ``duration_s``."""
        return np.arange(int(round(duration_s / CONTROL_DT)) + 1) * CONTROL_DT

    def mirrored(self) -> Plan:
        """The same manoeuvre to the other side (steering and path y negated)."""
        path = None if self.path is None else self.path * np.array([1.0, -1.0])
        return Plan(
            self.name, self.duration_s, self.speed0_mps, self.steer_mode.copy(), -self.steer_sw,
            self.speed_mode.copy(), self.speed_target.copy(), self.motor_cmd.copy(), self.brake_cmd.copy(),
            path, None if self.path_speed is None else self.path_speed.copy(), self.path_ds,
            tuple(self.mu_dist), tuple(self.mu_values), {**self.label, "mirrored": True},
            None if self.motor_feedforward is None else self.motor_feedforward.copy(), self.path_grip,
            self.track_half_width_m, self.planned_distance_m,
        )


def _relief_share(slip: np.ndarray, relief: tuple[float, float], acting: np.ndarray) -> np.ndarray:
    """(B,) share (0..1) of a command a driver keeps while a wheel slips ``slip`` ((B,), -): 1 up to
    ``relief[0]``, 0 from ``relief[1]``, linear in between; exactly 1.0 where not ``acting``."""
    on, off = relief
    return np.where(acting, np.clip((off - slip) / (off - on), 0.0, 1.0), 1.0)


def _pad(rows: Sequence[np.ndarray], n: int, fill: str = "edge") -> np.ndarray:
    out = np.empty((len(rows), n), dtype=np.asarray(rows[0]).dtype)
    for i, row in enumerate(rows):
        k = min(len(row), n)
        out[i, :k] = row[:k]
        out[i, k:] = row[k - 1] if fill == "edge" else 0
    return out


class Driver:
    """Runs a batch of plans against a :class:`Vehicle` (all runs at once)."""

    WINDOW = 40  # path points searched ahead of the last nearest point
    REACQUIRE_M = 8.0  # lateral distance beyond which the nearest point is searched along the whole path
    #: braking slip (-) of the more slipping wheel of an axle at which the track driver starts letting
    #: brakes off, and at which they are fully off (:meth:`_lock_relief`): the rear brakes by the rear
    #: wheels, the pedal by the front wheels. Braking straight at the plan's 0.5 g (0.8 g), a rear tyre
    #: slips 0.9 % (1.7 %); at 3.5 % and 4.5 deg of slip angle it has lost about a tenth of its side force. A
    #: tyre's braking force peaks at 10-12 % slip (12-24 % with slip angle): 15 % is a wheel locking.
    REAR_SLIP_RELIEF = (0.035, 0.05)
    FRONT_SLIP_RELIEF = (0.15, 0.25)
    #: drive slip (-) of the more spinning front (driven) wheel at which the track driver starts feathering the
    #: motor torque, and at which it is fully off (:meth:`_spin_relief`). The car's front tyre drives hardest at
    #: 7.5-9 % slip going straight (1.25-1.30 Fz at 4 and 2 kN) and past it only spins; with 0.05-0.08 rad of slip
    #: angle, 10 % of drive slip has cost it a quarter to a third of its side force and 15 % 40-45 %. Accelerating
    #: straight at the plan's 0.4 g a front tyre slips about 2 %.
    FRONT_SPIN_RELIEF = (0.08, 0.15)

    def __init__(self, vehicle: Vehicle, plans: Sequence[Plan], params: Sequence[dict]):
        if len(plans) != vehicle.B:
            raise ValueError("one plan per run")
        self.v = vehicle
        self.plans = plans
        self.n = max(p.n for p in plans)
        B = vehicle.B
        self.steer_mode = _pad([p.steer_mode for p in plans], self.n)
        self.steer_sw = _pad([p.steer_sw for p in plans], self.n)
        self.speed_mode = _pad([p.speed_mode for p in plans], self.n)
        self.speed_target = _pad([p.speed_target for p in plans], self.n)
        self.motor_cmd = _pad([p.motor_cmd for p in plans], self.n)
        self.brake_cmd = _pad([p.brake_cmd for p in plans], self.n)
        self.has_ff = np.array([p.motor_feedforward is not None for p in plans], dtype=bool)
        # a recorded speed is the ESC's: rear wheel spin times their radius at the start
        # (static load); with a recording, the loop compares like with like
        speed0 = np.array([p.speed0_mps for p in plans], dtype=float)
        re0 = vehicle.static_rolling_radius(speed0)
        self.r_esc = 0.5 * (re0[:, 2] + re0[:, 3])
        self.motor_ff = _pad([p.motor_feedforward if p.motor_feedforward is not None else np.zeros(p.n)
                              for p in plans], self.n)

        def dp(key: str) -> np.ndarray:
            return np.array([t["driver"][key] for t in params], dtype=float)

        self.preview_time = dp("preview_time_s")
        self.preview_min = dp("preview_min_m")
        self.k_lat_i = dp("lateral_integral_gain")
        self.v_lat_i = dp("lateral_integral_speed_mps")
        self.k_v = dp("speed_gain_npmps")
        self.k_vi = dp("speed_integral_gain")
        self.sw_lock = np.array([t["steering"]["ratio"] * t["steering"]["max_road_wheel_angle_rad"] for t in params])
        self.max_rate = dp("robot_max_rate_radps")
        self.cmd_tau = dp("command_time_constant_s")
        self.slip_margin = dp("steer_slip_margin_rad")
        self.follow_sw = np.zeros(B)

        # paths, padded to one length; runs without a path get a straight line
        m = max((len(p.path) for p in plans if p.path is not None), default=2)
        self.path = np.zeros((B, m, 2))
        self.path_speed = np.full((B, m), np.nan)
        self.path_len = np.zeros(B, dtype=int)
        self.path_ds = np.array([p.path_ds for p in plans])
        for i, p in enumerate(plans):
            if p.path is None:
                pts = np.stack([np.arange(m) * 1.0, np.zeros(m)], axis=1)
            else:
                pts = p.path
                pts = np.concatenate([pts, np.repeat(pts[-1:], m - len(pts), axis=0)])
                if p.path_speed is not None:
                    self.path_speed[i, : len(p.path_speed)] = p.path_speed
                    self.path_speed[i, len(p.path_speed):] = p.path_speed[-1]
            self.path[i] = pts
            self.path_len[i] = len(pts) if p.path is None else len(p.path)
        # the profile's own acceleration along the path, v dv/ds (m/s^2), at the vertices
        # (centred differences; read at the car's place between them, like the speed)
        self.path_accel = np.zeros((B, m))
        v2 = np.nan_to_num(self.path_speed) ** 2
        if m > 2:
            self.path_accel[:, 1:-1] = (v2[:, 2:] - v2[:, :-2]) / (4.0 * self.path_ds[:, None])
        grip = [p.path_grip if p.path_grip is not None and p.path_speed is not None else (np.inf, np.inf)
                for p in plans]
        self.grip_drive = np.array([g[0] for g in grip], dtype=float)
        self.grip_brake = np.array([g[1] for g in grip], dtype=float)
        self.graded = np.isfinite(self.grip_drive)
        # the track driver knows its car's understeer gradient (rad per m/s^2; 0: the kinematic gain only), one
        # linear model per distinct parameter tree (a campaign's runs share one)
        k_us_of: dict[int, float] = {}
        for t, g in zip(params, self.graded, strict=True):
            if g and id(t) not in k_us_of:
                k_us_of[id(t)] = linear_model(t).understeer_gradient
        self.k_us = np.array([k_us_of[id(t)] if g else 0.0 for t, g in zip(params, self.graded, strict=True)])
        self.off_limit = np.array([np.inf if p.track_half_width_m is None else p.track_half_width_m for p in plans])
        self.ax_ff = np.zeros(B)
        seg = np.diff(self.path, axis=1)
        heading = np.arctan2(seg[..., 1], seg[..., 0])
        self.path_heading = np.concatenate([heading, heading[:, -1:]], axis=1)
        dh = np.angle(np.exp(1j * np.diff(self.path_heading, axis=1)))
        curv = dh / np.maximum(np.hypot(seg[..., 0], seg[..., 1]), 1e-9)
        self.path_curv = np.concatenate([curv, curv[:, -1:]], axis=1)

        k_mu = max(len(p.mu_dist) for p in plans)
        self.mu_dist = np.full((B, max(k_mu, 1)), np.inf)
        self.mu_step = np.zeros((B, max(k_mu, 1)))
        self.mu0 = np.array([p.mu_values[0] for p in plans], dtype=float)
        for i, p in enumerate(plans):
            for j, d in enumerate(p.mu_dist):
                self.mu_dist[i, j] = d
                self.mu_step[i, j] = p.mu_values[j + 1] - p.mu_values[j]

        self.idx = np.zeros(B, dtype=int)
        self.lat_int = np.zeros(B)
        self.v_int = np.zeros(B)
        self.held_sw = np.zeros(B)
        self.cmd_sw = np.zeros(B)
        self.cmd_rate = np.zeros(B)
        self.motor = np.zeros(B)
        self.brake = np.zeros(B)
        self.rear_relief = np.ones(B)  # share of the balance's rear brake torque applied (1: none let off)
        self.lat_err = np.zeros(B)
        self.station_m = np.zeros(B)  #: (B,) each car's foot on its path (m from its start), last update
        self._rows = np.arange(B)

    def reset(self, x: np.ndarray) -> None:
        """Start from state ``x``: commands equal the current steering angle."""
        self.cmd_sw[:] = x[:, ISW]
        self.held_sw[:] = x[:, ISW]

    def off_track(self, k: int) -> np.ndarray:
        """(B,) bool: runs following their path at control step ``k`` whose car is farther
        from it than their plan's ``track_half_width_m`` (at the last path-following update)."""
        following = self.steer_mode[:, min(k, self.n - 1)] == STEER_PATH
        return following & (np.abs(self.lat_err) > self.off_limit)

    # ---- helpers -------------------------------------------------------------------
    def road_mu(self, s: np.ndarray) -> np.ndarray:
        """Road friction under each car at travelled distance ``s`` (m)."""
        return self.mu0 + (self.mu_step * (s[:, None] >= self.mu_dist)).sum(axis=1)

    def _follow(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pure-pursuit steering with integral action, plus the car's understeer ``K_us v^2 kappa`` of the path
        ahead for runs that follow a speed profile; returns (steering-wheel angle (rad), target speed (m/s))."""
        v = self.v
        rows = self._rows
        pos = x[:, [IX, IY]]
        win = self.idx[:, None] + np.arange(self.WINDOW)[None, :]
        win = np.minimum(win, (self.path_len - 1)[:, None])
        pts = self.path[rows[:, None], win]
        d2 = ((pts - pos[:, None, :]) ** 2).sum(axis=2)
        self.idx = win[rows, np.argmin(d2, axis=1)]
        lost = d2.min(axis=1) > self.REACQUIRE_M**2
        if lost.any():  # far from the path (a spin, a wide line): search the whole path again
            full = ((self.path[lost] - pos[lost, None, :]) ** 2).sum(axis=2)
            ahead = np.arange(self.path.shape[1])[None, :] < self.path_len[lost, None]
            self.idx[lost] = np.argmin(np.where(ahead, full, np.inf), axis=1)
        # the car's place along the path is continuous, not the nearest vertex: project it
        # onto the segment before and the one after that vertex and keep the nearer foot
        # (a vertex-quantised target jumps every path_ds / v seconds, 22 Hz at 40 km/h,
        # and the robot passes each jump to the column as a torque kick)
        last = self.path_len - 1
        fwd = self._foot(pos, self.idx, np.minimum(self.idx + 1, last))
        back = self._foot(pos, np.maximum(self.idx - 1, 0), self.idx)
        use_fwd = fwd[2] <= back[2]
        start = np.where(use_fwd, self.idx, np.maximum(self.idx - 1, 0))
        frac = np.where(use_fwd, fwd[0], back[0])
        foot = np.where(use_fwd[:, None], fwd[1], back[1])
        hd = self.path_heading[rows, start]
        err = -(pos[:, 0] - foot[:, 0]) * np.sin(hd) + (pos[:, 1] - foot[:, 1]) * np.cos(hd)
        self.lat_err = err  # + left of the path
        speed = np.maximum(x[:, IVX], 1.0)
        ld = np.maximum(self.preview_min, self.preview_time * speed)
        s_car = start + frac
        tgt = self._at(self.path, np.minimum(s_car + ld / self.path_ds, last))
        psi = x[:, IPSI]
        dxg, dyg = tgt[:, 0] - pos[:, 0], tgt[:, 1] - pos[:, 1]
        y_local = -dxg * np.sin(psi) + dyg * np.cos(psi)
        dist2 = np.maximum(dxg * dxg + dyg * dyg, 1.0)
        curvature = 2.0 * y_local / dist2
        # pure pursuit's loop gain does not change with speed (its preview grows with it: 2 v^2 / ld^2), the
        # integral's grows with v^2 (lateral acceleration per road-wheel angle): above the speed it was validated at,
        # it gathers the error at (v_ref / v)^2, keeping the weight it has there (at the full gain a dry Baku lap at
        # 200 km/h weaved off its straight); gathered, not applied, so that slowing down adds no steering
        self.lat_int += err * CONTROL_DT * np.minimum(1.0, (self.v_lat_i / speed) ** 2)
        # the track driver steers the path's own curvature (one command lag ahead) with its car's understeer too:
        # pure pursuit's kinematic gain alone holds a corner at speed only off the line, on the outside, by as
        # much as the missing K_us v^2 kappa asks for
        under = self.k_us * speed * speed
        kappa_ff = self._at(self.path_curv, np.minimum(s_car + speed * self.cmd_tau / self.path_ds, last))
        delta = np.arctan(v.L * curvature) + under * kappa_ff - self.k_lat_i * self.lat_int
        # a driver does not wind the wheels far past the tyres' grip: at most the
        # kinematic angle of the sharpest curvature over the search window ahead, plus a margin that also covers
        # the understeer term (K_us a_y, a few hundredths of a radian at the car's grip)
        self.station_m = s_car * self.path_ds
        k_ahead = self._max_abs_along(self.path_curv, s_car, np.minimum(s_car + self.WINDOW - 1, last))
        limit = np.arctan(v.L * np.maximum(k_ahead, np.abs(curvature))) + self.slip_margin
        delta = np.clip(delta, -limit, limit)
        # the speed target at the car's place along the path, not at its nearest vertex
        # (vertex by vertex it steps every path_ds / v seconds, and the speed loop's gain
        # turns each step into a drive-torque kick)
        vt = self._lerp(self.path_speed, start, frac)
        self.ax_ff = self._lerp(self.path_accel, start, frac)
        return delta * v.ratio, vt

    def _lerp(self, profile: np.ndarray, j: np.ndarray, f: np.ndarray) -> np.ndarray:
        """``profile`` (B, M, ...) given at the path vertices, per run at vertex ``j`` plus
        the fraction ``f`` (0..1) of the segment to the next vertex (linear in between)."""
        nxt = np.minimum(j + 1, self.path_len - 1)
        f = f.reshape(f.shape + (1,) * (profile.ndim - 2))
        return (1.0 - f) * profile[self._rows, j] + f * profile[self._rows, nxt]

    def _at(self, profile: np.ndarray, s: np.ndarray) -> np.ndarray:
        """``profile`` (B, M, ...) at each run's fractional path index ``s`` (0..its last vertex; linear between
        vertices)."""
        j = np.clip(np.floor(s).astype(int), 0, np.maximum(self.path_len - 2, 0))
        return self._lerp(profile, j, np.clip(s - j, 0.0, 1.0))

    def _max_abs_along(self, profile: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
        """Largest |profile| between fractional path indices ``s0 <= s1`` (one pair per run).

        The profile (B, M), given at the vertices, is taken as linear between them, so
        the result is its largest vertex value inside the span or its value at either
        end: it varies continuously as the span slides along the path (a max over whole
        vertices would step each time a vertex enters or leaves the span).
        """
        last = self.path_len - 1
        j = np.floor(s0).astype(int)[:, None] + 1 + np.arange(self.WINDOW)[None, :]
        inside = j < s1[:, None]
        vals = np.abs(profile[self._rows[:, None], np.minimum(j, last[:, None])])
        inner = np.where(inside, vals, 0.0).max(axis=1)
        return np.maximum(inner, np.maximum(np.abs(self._at(profile, s0)), np.abs(self._at(profile, s1))))

    def _foot(self, pos: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Foot of ``pos`` on each run's path segment a->b: (fraction 0..1, point, squared distance)."""
        pa, pb = self.path[self._rows, a], self.path[self._rows, b]
        d = pb - pa
        t = np.clip(((pos - pa) * d).sum(axis=1) / np.maximum((d * d).sum(axis=1), 1e-12), 0.0, 1.0)
        q = pa + t[:, None] * d
        return t, q, ((pos - q) ** 2).sum(axis=1)

    def _graded_force(self, x: np.ndarray, feedback: np.ndarray) -> np.ndarray:
        """Longitudinal force demand (N) of a driver following a speed profile with ``path_grip``.

        The profile's acceleration is fed forward (``m * v dv/ds`` at the car's place) on
        top of the speed feedback; the sum is held within the plan's drive and brake shares
        of the friction left beside the car's lateral acceleration (friction ellipse on
        ``mu * g`` with ``ay = vx * yaw rate``), plus the air drag and rolling resistance
        that the drive force overcomes first.
        """
        v = self.v
        vx = x[:, IVX]
        mu_g = self.road_mu(x[:, IS]) * v.g
        used = np.clip(np.abs(vx * x[:, IR]) / mu_g, 0.0, 1.0)
        room = np.sqrt(np.maximum(1.0 - used * used, 0.05))
        resist = v.drag * vx * np.abs(vx) + 0.012 * v.m * v.g
        force = feedback + v.m * self.ax_ff
        top = np.where(np.isfinite(self.grip_drive), self.grip_drive, 0.0) * v.m * mu_g * room + resist
        bottom = -np.where(np.isfinite(self.grip_brake), self.grip_brake, 0.0) * v.m * mu_g * room
        return np.clip(force, bottom, top)

    def _lock_relief(self, x: np.ndarray, acting: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(pedal, rear) shares (0..1, each (B,)) of its brake demand, and of the balance's rear
        brake torque, that a driver following ``path_speed`` keeps while a wheel starts to lock.

        The brakes have a fixed front/rear balance and the car no ABS or EBD. Braking out of a
        corner unloads the inner rear wheel (to 820 N of its 2,850 N static load at Montreal); the
        balance's rear share saturates it, its side force goes, the car oversteers and, under the
        driver's correction, spins. Braking into a tight corner locks the inner front wheel and
        the car runs straight on. So the driver (or an EBD/ABS modulating its pressure) lets off:

        * the rear brakes, as the more slipping rear wheel's braking slip rises from
          ``REAR_SLIP_RELIEF[0]`` (share 1) to ``REAR_SLIP_RELIEF[1]`` (share 0), linearly; the
          front brakes stay on, and with them most of the deceleration;
        * the whole pedal, as the more slipping front wheel's slip rises over ``FRONT_SLIP_RELIEF``.

        The braking slip is ``-kappa`` of the tyre model, ``kappa = (omega r - v) / |v|`` (the
        longitudinal slip state, which an ABS estimates from the wheel speeds). Acts only where
        ``acting`` (runs braking under :meth:`_graded_force`); elsewhere, and wherever the slip is
        under the first threshold, both shares are exactly 1.0: those runs are unchanged.
        """
        if not acting.any():
            ones = np.ones(self.v.B)
            return ones, ones
        slip = -x[:, IKA]
        return (_relief_share(slip[:, :2].max(axis=1), self.FRONT_SLIP_RELIEF, acting),
                _relief_share(slip[:, 2:].max(axis=1), self.REAR_SLIP_RELIEF, acting))

    def _spin_relief(self, x: np.ndarray, acting: np.ndarray) -> np.ndarray:
        """(B,) share (0..1) of its motor-torque demand that a driver following ``path_speed`` keeps while a
        driven front wheel starts to spin.

        The motor drives the front wheels through an open differential and the car has no traction control:
        accelerating out of a corner unloads the inner front wheel, the differential gives it the same torque as
        the outer one, it spins, its side force goes and the car runs wide (the README's "A driven wheel that
        spins" has the laps this put off the road). So the driver (or a traction control) feathers the throttle as
        the more spinning front wheel's drive slip ``kappa`` rises from ``FRONT_SPIN_RELIEF[0]`` (share 1) to
        ``FRONT_SPIN_RELIEF[1]`` (share 0), linearly. Acts only where ``acting`` (runs driving under
        :meth:`_graded_force`); elsewhere, and wherever the slip is under the first threshold, the share is exactly
        1.0: those runs are unchanged."""
        if not acting.any():
            return np.ones(self.v.B)
        return _relief_share(x[:, IKA][:, :2].max(axis=1), self.FRONT_SPIN_RELIEF, acting)

    def _brake_torques(self, x: np.ndarray, brake_dem: np.ndarray, graded: np.ndarray) -> np.ndarray:
        """(B, 4) brake torques (Nm) for a front brake demand ``brake_dem`` (Nm per wheel), the rear
        at the balance's share, through the hydraulics' lag; runs ``graded`` braking let off as a
        wheel starts to lock (:meth:`_lock_relief`; the rear's let-off through the same lag)."""
        v = self.v
        a_brake = CONTROL_DT / np.maximum(v.brake_tau, CONTROL_DT)
        pedal, rear = self._lock_relief(x, graded & (brake_dem > 0.0))
        self.rear_relief += (rear - self.rear_relief) * a_brake
        self.brake += (brake_dem * pedal - self.brake) * a_brake
        brake = np.empty((v.B, 4))
        brake[:, :2] = self.brake[:, None]
        brake[:, 2:] = (self.brake * (1.0 - v.brake_share) / v.brake_share * self.rear_relief)[:, None]
        return brake

    # ---- the control step -------------------------------------------------------------
    def update(self, k: int, x: np.ndarray) -> Inputs:
        """Actuator inputs for control step ``k`` (time ``k * CONTROL_DT``) at state ``x``."""
        v = self.v
        k = min(k, self.n - 1)
        mode = self.steer_mode[:, k]
        following = mode == STEER_PATH
        sw = self.steer_sw[:, k].copy()
        target = self.speed_target[:, k].copy()
        if following.any():
            sw_path, vt = self._follow(x)
            # a driver's (or robot's path loop's) bandwidth: first-order low-pass
            a = CONTROL_DT / np.maximum(self.cmd_tau, CONTROL_DT)
            self.follow_sw = np.where(following, self.follow_sw + a * (sw_path - self.follow_sw), self.cmd_sw)
            sw = np.where(following, self.follow_sw, sw)
            target = np.where(following & np.isfinite(vt), vt, target)
        hold = mode == STEER_HOLD
        # the hold angle is the command at the moment holding starts
        self.held_sw = np.where(hold, self.held_sw, self.cmd_sw)
        sw = np.where(hold, self.held_sw, sw)
        free = mode == STEER_FREE
        sw = np.where(free, x[:, ISW], sw)
        # no driver or robot turns the wheel past the rack's end stops or faster than it can
        sw = np.clip(sw, -self.sw_lock, self.sw_lock)
        step = self.max_rate * CONTROL_DT
        sw = np.where(free, sw, np.clip(sw, self.cmd_sw - step, self.cmd_sw + step))
        new_rate = (sw - self.cmd_sw) / CONTROL_DT
        self.cmd_rate = np.where(free, 0.0, new_rate)
        self.cmd_sw = sw

        # longitudinal
        smode = self.speed_mode[:, k]
        vx = x[:, IVX]
        v_esc = 0.5 * (x[:, IOM][:, 2] + x[:, IOM][:, 3]) * self.r_esc
        err = target - np.where(self.has_ff, v_esc, vx)
        self.v_int = np.where(smode == SPEED_TARGET, np.clip(self.v_int + err * CONTROL_DT, -5.0, 5.0), 0.0)
        resist = v.drag * vx * np.abs(vx) + 0.012 * v.m * v.g
        # with a motor-torque feedforward (a recorded run) the feedback adds only what
        # tracking still needs: the recorded torque already overcomes the resistances
        # (and at half the gain: it corrects what the recorded torque leaves, not noise)
        fb = np.where(self.has_ff, 0.5, 1.0) * (self.k_v * err + self.k_vi * self.v_int)
        force = np.where(self.has_ff, 0.0, resist) + fb
        graded = self.graded & following & (smode == SPEED_TARGET)
        if graded.any():
            force = np.where(graded, self._graded_force(x, force), force)
        r_wheel = v.R0 * 0.97
        motor_dem = np.where(force > 0, force * r_wheel / (v.gear * v.eta), 0.0) + self.motor_ff[:, k]
        brake_dem = np.where(force < 0, -force * r_wheel * 0.5 * v.brake_share, 0.0)
        motor_dem = np.where(smode == SPEED_OPEN, self.motor_cmd[:, k], motor_dem)
        brake_dem = np.where(smode == SPEED_OPEN, self.brake_cmd[:, k], brake_dem)
        motor_dem = np.where(smode == SPEED_COAST, 0.0, motor_dem)
        brake_dem = np.where(smode == SPEED_COAST, 0.0, brake_dem)
        # motor limits: torque, power, and no torque beyond the motor's top speed (the
        # motor turns with the mean of the driven wheels through the open differential)
        w_motor = np.maximum(0.5 * np.abs(x[:, IOM][:, 0] + x[:, IOM][:, 1]) * v.gear, 1.0)
        tmax = np.minimum(v.motor_tmax, v.motor_pmax / w_motor)
        tmax = tmax * np.clip((v.motor_wmax - w_motor) / (0.05 * v.motor_wmax), 0.0, 1.0)
        motor_dem = np.clip(motor_dem, -tmax, tmax)
        if graded.any():  # (the share of the torque the motor gives, as the pedal's share of the brakes)
            motor_dem = motor_dem * self._spin_relief(x, graded & (motor_dem > 0.0))
        brake_dem = np.clip(brake_dem, 0.0, v.brake_front_max)
        self.motor += (motor_dem - self.motor) * (CONTROL_DT / np.maximum(v.motor_tau, CONTROL_DT))
        brake = self._brake_torques(x, brake_dem, graded)

        drive = np.zeros((v.B, 4))
        drive[:, :2] = (0.5 * v.gear * v.eta * self.motor)[:, None]
        return Inputs(
            steer_cmd=self.cmd_sw.copy(),
            steer_cmd_rate=self.cmd_rate.copy(),
            hands_off=free,
            drive_torque=drive,
            brake_torque=brake,
            mu=self.road_mu(x[:, IS]),
        )
