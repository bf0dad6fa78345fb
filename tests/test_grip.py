"""The grip margin (issue 19): the estimate's contract, VS_Grip on the matrix, and VS_Grip published by the daemon
on the virtual bus with SAT_FRONT's statuses under timeouts and E2E faults."""

from __future__ import annotations

import json
import math
import time
import uuid
from dataclasses import replace

import can
import cantools
import numpy as np
import pytest
from runtime_support import SYNC_ID, CaptureBus, with_sync

from virtsensor import signals as cat
from virtsensor.assets import dbc_path, model_path
from virtsensor.canbus.codec import CanMatrix
from virtsensor.canbus.e2e import USABLE
from virtsensor.daemon import DEGRADED, INIT, INVALID, VALID, VirtualSensor
from virtsensor.daemon.gripout import worse_status
from virtsensor.errors import UserError
from virtsensor.grip import PRESSURE_INPUTS, GripEstimator, GripParams, estimate_run, load_params
from virtsensor.learning import gripscore as gs
from virtsensor.model import OnnxModel
from virtsensor.recordings.canlog import iter_frames, simulated_recording

MATRIX = CanMatrix.load()
SAT_ID = MATRIX.messages["SAT_FRONT"].frame_id
GRIP_ID = MATRIX.messages["VS_Grip"].frame_id


# ------------------------------------------------------------------------------------------------ the estimate
def _steady(est: GripEstimator, n: int, ay: float, trail_m: float, vx: float = 20.0) -> None:
    """Feed a steady left turn: lateral acceleration ``ay``, axle SAT = -trail * front lateral force."""
    p = est.params
    fy = p.mass_kg * p.front_load_fraction * ay
    for _ in range(n):
        r = ay / vx
        est.step(-0.5 * trail_m * fy, -0.5 * trail_m * fy, 0.0, ay, vx, r, 0.05, 20.0, vx / 0.305, vx / 0.305)


def test_straight_driving_gives_utilisation_but_no_friction():
    est = GripEstimator()
    _steady(est, 40, 0.0, 0.03)
    s = est.state
    assert math.isfinite(s.util) and s.util < 0.2
    assert math.isnan(s.mu) and math.isnan(s.halfwidth) and not s.warning


def test_collapsed_trail_gives_friction_and_warning():
    """A turn at 0.4 g with the trail collapsed (the tyres at their limit): the friction follows from the force
    used and the calibrated force ratio at that trail, the utilisation is high and the warning is on."""
    p = load_params()
    est = GripEstimator(p)
    _steady(est, 40, 0.4 * 9.81, 0.0)
    s = est.state
    k = np.interp(0.0, p.trail_m, p.use_at_trail)
    assert s.mu == pytest.approx(0.4 / k, rel=0.05)
    assert 0 < s.halfwidth <= p.halfwidth_max
    assert s.util >= p.warn_on and s.warning
    # a gentle corner of the same road: the trail is long, the friction is unknown, the warning ends
    _steady(est, 60, 0.1 * 9.81, 0.03)
    assert math.isnan(est.state.mu) and not est.state.warning and est.state.util < 0.5


def test_force_floor_warns_in_combined_slip_where_the_trail_is_gated_off():
    """A hard corner under drive on a dry road: the drive force gates the trail off (no friction, no trail
    evidence), yet the axle already uses n = |F| / Fz of its load, at least n / mu_road_max of any rated road's
    grip: the warning comes from that floor, and not without it."""
    p = load_params()
    assert p.mu_road_max > 0 and p.demand_weight * 0.5 < p.warn_on

    def run(params: GripParams) -> tuple[bool, float, float]:
        est = GripEstimator(params)
        vx, ay, torque = 25.0, 0.6 * 9.81, 150.0  # 150 Nm: |Fx| ~ 0.6 Fz, beyond the trail's gate
        ax = torque * p.gear_ratio / p.rolling_radius_m / p.mass_kg
        for _ in range(40):
            est.step(-0.02 * 2000, -0.02 * 2000, ax, ay, vx, ay / vx, 0.0, torque, vx / 0.305, vx / 0.305)
        return est.state.warning, est.state.force_ratio, est.state.trail_m

    warned, n, trail = run(p)
    assert math.isnan(trail)
    assert n >= p.warn_on * p.mu_road_max and warned
    assert not run(replace(p, mu_road_max=0.0))[0]


def test_braking_into_a_corner_warns_by_the_more_used_tyre():
    """Braking into a dry corner (the trail gated off): the axle uses less than the threshold of a rated road,
    but the inner front tyre, unloaded by the lateral load transfer and braked as hard as the outer one, uses
    more: the force floor of the more used tyre warns; with no load transfer (the axle's floor) it does not."""
    p = replace(load_params(), demand_weight=0.0)
    assert p.load_transfer > 0

    def run(params: GripParams) -> tuple[bool, float]:
        est = GripEstimator(params)
        vx, ay, ax = 45.0, 5.5, -4.5  # (near a 229 km/h lap's corner entry of the held-out study: 5.9, -4.8)
        for _ in range(40):
            est.step(-40.0, -40.0, ax, ay, vx, ay / vx, 0.0, 0.0, vx / 0.305, vx / 0.305)
        return est.state.warning, est.state.force_ratio

    warned, n = run(p)
    assert n < p.warn_on * p.mu_road_max and warned
    assert not run(replace(p, load_transfer=0.0))[0]


def test_a_collapsed_trail_under_drive_or_braking_warns_within_the_evidence_gate_and_gives_no_friction():
    """A wet corner (0.45 g) under a drive force of about 0.2 Fz, beyond the friction's gate (``max_long_ratio``), its
    trail short (6 mm): neither the force floor nor the demand reaches the threshold. With the trail read as evidence
    up to 0.25 Fz the utilisation is the trail curve's value there and the warning comes; without (0, the older
    files' meaning) it does not; under braking the same; beyond the evidence gate (0.4 Fz), or with too little
    lateral force to divide by, the gate changes nothing. The friction and its trail stay unknown throughout."""
    p = replace(load_params(), demand_weight=0.0, max_long_ratio=0.15)
    trail = 0.006
    curve = float(np.interp(trail, p.trail_m, p.util_at_trail))
    assert curve >= p.warn_on and curve < max(p.util_at_trail)  # (on the curve's slope, not its flat top)

    def run(params: GripParams, torque: float, ax_brake: float = 0.0, g: float = 0.45) -> GripEstimator:
        est = GripEstimator(params)
        vx, ay = 20.0, g * 9.81
        fy = p.mass_kg * p.front_load_fraction * ay
        ax = torque * p.gear_ratio / p.rolling_radius_m / p.mass_kg + ax_brake
        for _ in range(40):
            est.step(-0.5 * trail * fy, -0.5 * trail * fy, ax, ay, vx, ay / vx, 0.05, torque, vx / 0.305,
                     vx / 0.305)
        return est

    gate, none = replace(p, evidence_long_ratio=0.25), replace(p, evidence_long_ratio=0.0)
    for kw in ({"torque": 57.0}, {"torque": 0.0, "ax_brake": -1.5}):  # drive; braking
        on = run(gate, **kw)
        s = on.state
        assert p.max_long_ratio < abs(on._fx) / on._fz <= 0.25
        assert s.util == pytest.approx(curve, abs=1e-6) and s.warning
        assert math.isnan(s.mu) and math.isnan(s.trail_m)
        assert on._tyre_ratio(on._fx, on._fy, on._fz) / p.mu_road_max < p.warn_on  # (not the force floor)
        assert not run(none, **kw).state.warning
    far = run(gate, 110.0)  # (beyond the gate the gate changes nothing)
    assert abs(far._fx) / far._fz > 0.25
    assert far.state.util == run(none, 110.0).state.util
    weak = run(gate, 15.0, g=0.05)  # (|Fy| below min_force_ratio Fz: no trail to read)
    assert abs(weak._fy) < p.min_force_ratio * weak._fz and abs(weak._fx) <= 0.25 * weak._fz
    assert weak.state.util == run(none, 15.0, g=0.05).state.util and not weak.state.warning


def test_torque_step_on_a_slippery_road_warns_on_the_tick_the_wheels_spin():
    """A drive-torque step on a slippery road saturates the driven front tyres within one 20 Hz tick (the truth goes
    from 0.05 to above 0.95 between two ticks): the force it asks for is one a dry road carries, so only the front
    wheels' slip tells the limit, and the warning comes on that very tick (a lead of 0, the best any causal
    estimate has there) once the slip exceeds what the driven wheels show below 0.7 utilisation (|kappa| < 0.03 in
    999 of 1000 samples of the fit seed); the same step with less slip than that does not warn."""
    p = load_params()

    def step(kappa: float, params: GripParams = p) -> bool:
        est = GripEstimator(params)
        vx = 18.5
        for _ in range(30):  # cruising: a little drive torque, the wheels rolling
            est.step(0.0, 0.0, 0.0, 0.0, vx, 0.0, 0.0, 7.0, vx / p.rolling_radius_m, vx / p.rolling_radius_m)
        w = (1.0 + kappa) * vx / p.rolling_radius_m  # the step: 170 Nm, the road gives 1.1 m/s^2 (mu 0.2)
        return est.step(0.0, 0.0, 1.1, 0.0, vx, 0.0, 0.0, 170.0, w, w).warning

    assert step(0.045)
    assert not step(0.025)
    assert not step(0.045, replace(p, kappa_limit=0.1))  # (the previous limit, 0.1, did not see it)


def _slip_warns(vx: float, road_wheel: float, slip: float, torque: float, ax: float) -> bool:
    """Warning after 30 ticks of a steady left turn at ``vx`` (the ESC's rear-axle speed) with road-wheel angle
    ``road_wheel`` (kinematic yaw rate), a healthy trail, the front wheels ``slip`` beyond the front axle's own speed
    along them."""
    p = load_params()
    est = GripEstimator(p)
    r = vx * math.tan(road_wheel) / p.wheelbase_m
    w = (1.0 + slip) * vx / math.cos(road_wheel) / p.rolling_radius_m
    sat = -0.5 * 0.035 * p.mass_kg * p.front_load_fraction * vx * r  # (a healthy 35 mm trail: far from the limit)
    warned = False
    for _ in range(30):
        s = est.step(sat, sat, ax, vx * r, vx, r, road_wheel * p.steer_ratio, torque, w, w)
        warned = warned or s.warning
    return warned


def test_tight_low_speed_turn_is_no_wheel_slip():
    """In a tight turn the front axle runs on a wider circle than the rear axle, whose wheels give the ESC's speed:
    at 0.28 rad of road-wheel angle the front wheels roll 4 % faster than ``vx`` with no slip at all (the seed 1901
    false warnings at 5-6 m/s in a free-steer run read |kappa| = 0.04 against ``vx`` with a true slip of 0.001).
    Against the front axle's own speed that is no slip; a real spin in the same turn still warns."""
    assert not _slip_warns(5.5, 0.28, 0.0, 10.0, -0.3)
    assert _slip_warns(5.5, 0.28, 0.06, 170.0, 1.1)


def test_wheel_running_ahead_without_drive_is_no_limit():
    """When the brakes release, the front wheels spin up and overshoot the car's speed for a tick or two (seed 1901:
    +0.04 at 6.2 m/s, true slip -0.0005): a slip against the longitudinal force is no tyre at its limit. The same
    slip under a drive torque step (a spin) warns; a lock under braking does too."""
    assert not _slip_warns(6.2, 0.0, 0.045, 0.0, -1.3)
    assert _slip_warns(6.2, 0.0, 0.045, 170.0, 1.1)
    assert _slip_warns(6.2, 0.0, -0.06, 0.0, -6.0)


def test_wheel_spin_below_3_mps_warns_down_to_the_signals_resolution():
    """A launch on ice spins the driven wheels at 2 m/s: no fixed speed gate hides it (the slip is read wherever the
    CAN resolutions' floor ``(r q_w + q_v) / (2 v)`` is below the limit: 0.13 m/s), and the floor is taken off
    (so at walking pace a slip within one resolution step does not warn)."""
    assert _slip_warns(2.0, 0.0, 0.1, 170.0, 1.0)
    assert not _slip_warns(0.2, 0.0, 0.02, 170.0, 0.5)
    assert not _slip_warns(0.1, 0.0, 0.3, 170.0, 0.5)  # (below the floor's speed: not read at all)


def test_wet_corner_under_drive_warns_by_the_held_friction():
    """A wet road measured in a corner (the trail collapsed: friction about 0.5 given and held), then a corner
    exit under drive on it (the trail gated off): the more used tyre uses most of that road's grip but little of a
    rated dry road's, so only the held friction's upper end (``evidence_mu_held``) sees the limit; without it the
    same exit is silent."""
    p = replace(load_params(), demand_weight=0.0)

    def exit_warns(params: GripParams) -> tuple[bool, float]:
        est = GripEstimator(params)
        _steady(est, 60, 0.45 * 9.81, 0.0)  # the friction given and held
        mu = est._mu_held
        _steady(est, 40, 0.0, 0.03)  # 40 m straight: the warning ends, the friction stays held
        assert not est.state.warning
        vx, ay, torque = 20.0, 0.4 * 9.81, 60.0  # |Fx| ~ 0.2 Fz: beyond the trail's gate
        ax = torque * p.gear_ratio / p.rolling_radius_m / p.mass_kg
        for _ in range(10):
            est.step(-0.02 * 2000, -0.02 * 2000, ax, ay, vx, ay / vx, 0.0, torque, vx / 0.305, vx / 0.305)
        assert math.isnan(est.state.trail_m)
        return est.state.warning, mu

    warned, mu = exit_warns(replace(p, evidence_mu_held=1.0))
    assert 0.4 < mu < 0.7 and warned
    assert not exit_warns(replace(p, evidence_mu_held=0.0))[0]


def test_steering_demand_warns_before_the_force_builds():
    """A sharp steering input at speed on a straight: the linear car asks for far more lateral acceleration than
    any rated road gives before the axle force has built up: the demand term (weighted as the fit may choose it;
    the shipped calibration may leave it off) warns on the first tick, and without it the same tick is silent."""
    p = replace(load_params(), demand_weight=0.6)

    def first_tick(params: GripParams) -> bool:
        est = GripEstimator(params)
        _steady(est, 20, 0.0, 0.03, vx=25.0)
        v2 = 25.0 ** 2  # the steering-wheel angle whose linear-car demand is twice what warns (p's numbers)
        wheel = 2.0 * p.warn_on / p.demand_weight * 9.81 * p.steer_ratio * p.wheelbase_m * (
            1.0 + p.understeer_s2pm2 * v2) / v2
        est.step(0.0, 0.0, 0.0, 0.3, 25.0, 0.0, wheel, 20.0, 25.0 / 0.305, 25.0 / 0.305)
        return est.state.warning

    assert first_tick(p)
    assert not first_tick(replace(p, demand_weight=0.0))


def test_friction_is_held_while_excited_and_only_so_far():
    """After a turn with the trail collapsed (friction given), the same road under hard drive (the trail gated
    off) keeps the held friction with a wider interval; a gentle stretch gives none (never a guess); beyond
    ``hold_m`` of driving without a new estimate it is unknown again."""
    p = load_params()
    assert p.hold_m > 0 and p.hold_count >= 1
    est = GripEstimator(p)
    _steady(est, 60, 0.4 * 9.81, 0.0)
    mu, hw = est.state.mu, est.state.halfwidth
    assert math.isfinite(mu)

    def drive(ticks: int, torque: float, vx: float = 20.0) -> None:
        ax = torque * p.gear_ratio / p.rolling_radius_m / p.mass_kg  # (the car accelerates as the drive says)
        for _ in range(ticks):
            est.step(-0.03 * 1000, -0.03 * 1000, ax, 1.0, vx, 1.0 / vx, 0.0, torque, vx / 0.305, vx / 0.305)

    drive(5, 150.0)  # |Fx| ~ 0.6 Fz: the trail is not read
    s = est.state
    assert math.isnan(s.trail_m) and s.force_ratio >= p.hold_min_use * mu
    assert s.mu == pytest.approx(mu, rel=0.1) and hw < s.halfwidth <= hw + p.hold_widen_per_m * p.hold_m
    drive(5, 5.0)  # gentle: the axle uses little of the road
    assert math.isnan(est.state.mu)
    drive(int(p.hold_m / (20.0 * 0.05)) + 1, 5.0)
    drive(2, 150.0)
    assert math.isnan(est.state.mu)
    unheld = GripEstimator(replace(p, hold_m=0.0))
    _steady(unheld, 60, 0.4 * 9.81, 0.0)
    for _ in range(5):
        unheld.step(-30.0, -30.0, 3.0, 1.0, 20.0, 0.05, 0.0, 150.0, 20.0 / 0.305, 20.0 / 0.305)
    assert math.isfinite(unheld.state.force_ratio) and math.isnan(unheld.state.mu)


def test_reversing_drives_the_held_friction_s_metres_too():
    """The held friction is given on for ``hold_m`` metres driven after the latest, its half-width growing with
    them. Reversing drives metres too: it counted them negative, so that the half-width shrank below the one
    measured and the hold outlasted its distance for as long as the car had reversed."""
    p = load_params()
    est = GripEstimator(p)
    _steady(est, 60, 0.4 * 9.81, 0.0)
    mu, hw = est.state.mu, est.state.halfwidth
    assert math.isfinite(mu)
    ay, vx = 0.4 * 9.81, -5.0  # reversing round a bend, the axle as used as in the turn; the trail not read
    fy = p.mass_kg * p.front_load_fraction * ay
    metres = 0.0
    while metres < 100.0:
        s = est.step(-0.02 * fy, -0.02 * fy, 0.0, ay, vx, ay / vx, 0.0, 0.0, vx / 0.305, vx / 0.305)
        metres -= vx * est.dt
    assert s.mu == mu and s.halfwidth == pytest.approx(hw + p.hold_widen_per_m * metres, abs=2e-4)  # (+0.01)
    while metres <= p.hold_m + 1.0:
        s = est.step(-0.02 * fy, -0.02 * fy, 0.0, ay, vx, ay / vx, 0.0, 0.0, vx / 0.305, vx / 0.305)
        metres -= vx * est.dt
    assert math.isnan(s.mu) and math.isnan(s.halfwidth)


def test_no_friction_is_read_from_sats_outside_the_model_s_envelope():
    """A SAT of inputs outside the model's validity envelope is an extrapolation: the trail read from it gives no
    friction, neither given nor held (a friction held from before still is), while it still counts as the
    limit's evidence for the utilisation and the warning. Back inside, no friction is read while the SAT filter
    still weighs the extrapolated SATs (``settle_ticks``, 3 time constants), and the filter runs on (no tick reads one
    raw SAT)."""
    p = load_params()
    inside, outside = GripEstimator(p), GripEstimator(p)
    fy = p.mass_kg * p.front_load_fraction * 0.4 * 9.81
    for _ in range(60):
        a = inside.step(0.0, 0.0, 0.0, 0.4 * 9.81, 20.0, 0.4 * 9.81 / 20.0, 0.0, 0.0, 20 / 0.305, 20 / 0.305)
        b = outside.step(0.0, 0.0, 0.0, 0.4 * 9.81, 20.0, 0.4 * 9.81 / 20.0, 0.0, 0.0, 20 / 0.305, 20 / 0.305,
                         outside=True)
        assert math.isnan(b.mu) and math.isnan(b.halfwidth) and b.util == a.util and b.warning == a.warning
    assert math.isfinite(a.mu) and a.util > 0.8 and a.warning  # (the trail collapsed: the limit's evidence)
    # back inside with a trail far from the extrapolated one: no friction until the filter has forgotten those
    assert outside.settle_ticks == 6  # (filter 0.1 s at 20 Hz)
    trails = []
    for k in range(outside.settle_ticks + 30):
        c = outside.step(-0.0075 * fy / 2, -0.0075 * fy / 2, 0.0, 0.4 * 9.81, 20.0, 0.4 * 9.81 / 20.0, 0.0, 0.0,
                         20 / 0.305, 20 / 0.305)
        trails.append(c.trail_m)
        if k < outside.settle_ticks:
            assert math.isnan(c.mu) and math.isnan(c.trail_m), k
    assert trails[outside.settle_ticks] == pytest.approx(0.0075, abs=0.0075 * 0.06)  # (< 5 % of the old trail left)
    # the filter ran on: the extrapolated SATs (a trail of 0) still weigh a few % (exp(-3.5)); a filter restarted back
    # inside would read 0.0075 exactly there
    assert trails[outside.settle_ticks] <= 0.0075 * 0.99
    assert trails[-1] == pytest.approx(0.0075, rel=1e-3)
    # a friction given inside is held through an excursion (nothing new is read there)
    mu = a.mu
    for _ in range(10):
        a = inside.step(-0.02 * fy, -0.02 * fy, 0.0, 0.4 * 9.81, 20.0, 0.4 * 9.81 / 20.0, 0.0, 0.0, 20 / 0.305,
                        20 / 0.305, outside=True)
    assert a.mu == mu


def test_the_published_interval_is_its_own_curve_and_the_gate_the_pooled_one():
    """With ``interval_at_trail`` the published half-width is read from it (given and held, widened as held), while
    the gate, the held friction and the utilisation still read the pooled error (``abs_err90_at_trail``); without it
    (older files) the two are the same curve. ``interval_max`` withholds a friction whose published half-width, or a
    held one's widened, exceeds it. An unlimited ``interval_max`` stays out of strict JSON; bad values are refused."""
    p = replace(load_params(), interval_at_trail=(), interval_max=0.5)
    wide = replace(p, interval_at_trail=tuple((0.5,) * len(p.trail_m) for _ in p.mu_bands))
    a, b = GripEstimator(p), GripEstimator(wide)
    for est in (a, b):
        _steady(est, 60, 0.4 * 9.81, 0.0)
    assert math.isfinite(a.state.mu) and a.state.mu == b.state.mu and a.state.util == b.state.util
    assert 0 < a.state.halfwidth <= p.halfwidth_max and b.state.halfwidth == 0.5
    ax = 150.0 * p.gear_ratio / p.rolling_radius_m / p.mass_kg
    for est in (a, b):  # hard drive: the trail is gated off, the friction held
        for _ in range(5):
            est.step(-30.0, -30.0, ax, 1.0, 20.0, 0.05, 0.0, 150.0, 20.0 / 0.305, 20.0 / 0.305)
    assert math.isnan(b.state.trail_m)
    assert math.isnan(b.state.mu)  # (held, its interval widened past interval_max: withheld, not published wider)
    assert math.isfinite(a.state.mu) and a.state.halfwidth > a._hw_held  # (the pooled one, widened as held)
    loose = GripEstimator(replace(wide, interval_max=0.6))
    _steady(loose, 60, 0.4 * 9.81, 0.0)
    for _ in range(5):
        loose.step(-30.0, -30.0, ax, 1.0, 20.0, 0.05, 0.0, 150.0, 20.0 / 0.305, 20.0 / 0.305)
    widen = loose.state.halfwidth - 0.5
    assert loose.state.mu == a.state.mu and 0 < widen <= p.hold_widen_per_m * p.hold_m
    assert a.state.halfwidth - widen == pytest.approx(a._hw_held)
    tight = GripEstimator(replace(wide, interval_max=0.49))  # (the interval wider than the limit: never given)
    _steady(tight, 60, 0.4 * 9.81, 0.0)
    assert math.isnan(tight.state.mu) and math.isnan(tight.state.halfwidth)
    doc = wide.to_json()
    assert GripParams.from_json(doc) == wide
    unlimited = replace(wide, interval_max=math.inf)
    assert "interval_max" not in unlimited.to_json() and GripParams.from_json(unlimited.to_json()) == unlimited
    json.dumps(unlimited.to_json(), allow_nan=False)
    with pytest.raises(UserError, match="interval_at_trail"):
        GripParams.from_json({**doc, "interval_at_trail": doc["interval_at_trail"][:-1]})
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(UserError, match="interval_max"):
            GripParams.from_json({**doc, "interval_max": bad})


def test_non_finite_input_gives_nan_and_restarts():
    est = GripEstimator()
    _steady(est, 20, 4.0, 0.0)
    s = est.step(math.nan, 1.0, 0.0, 4.0, 20.0, 0.2, 0.05, 20.0, 65.0, 65.0)
    assert math.isnan(s.util) and math.isnan(s.mu) and not s.warning


def _without_curves(p: GripParams) -> GripParams:
    return replace(p, pressure_grid_pa=(), trail_at_pressure=(), peak_at_pressure=())


def _pressure_state(params: GripParams, trail_m: float, pressure: float, ay: float = 0.45 * 9.81,
                    reads: bool = False) -> tuple[float, float, float]:
    est = GripEstimator(params, sat_reads_pressure=reads)
    est.set_front_pressure(pressure)
    _steady(est, 40, ay, trail_m)
    return est.state.util, est.state.mu, est.state.trail_m


def test_the_trail_is_read_on_the_tyres_own_curve_at_its_pressure():
    """A harder tyre has a shorter trail in the same slip state (MF 6.1: ``Dt`` scales with ``1 - PPZ1 dpi``, and the
    cornering stiffness with ``1 + PPY1 dpi`` moves how far it has collapsed) and another peak force (``PPY3``,
    ``PPY4``). For the SATs of a model that reads the TPMS pressures, the estimate locates the trail on that
    pressure's knots and scales the curves by its peak: a hard tyre in the same slip state on the same road gives the
    nominal tyre's friction."""
    p = load_params()
    assert p.pressure_nominal_pa == 220_000.0 and len(p.pressure_grid_pa) >= 2
    row = p.pressure_grid_pa.index(290_000.0)
    j = p.trail_m.index(0.0125)
    t_hard, r = p.trail_at_pressure[row][j], p.peak_at_pressure[row]
    assert t_hard < 0.0125 * (1.0 - p.trail_pressure_coeff * 70 / 220) - 0.001  # (shorter than the PPZ1 scale says)
    nominal = _pressure_state(p, 0.0125, 220_000.0, 0.3 * 9.81, reads=True)
    hard = _pressure_state(p, t_hard, 290_000.0, 0.3 * 9.81 * r, reads=True)  # (the same slip state: r times the force)
    assert math.isfinite(nominal[1])
    # the same friction (to the small drive force _steady adds, not scaled), the trail as the nominal tyre has it
    assert hard[1:] == pytest.approx(nominal[1:], rel=1e-3)
    assert _pressure_state(p, 0.0125, math.nan, 0.3 * 9.81, reads=True) == pytest.approx(nominal, rel=1e-12)  # unknown
    as_is = _pressure_state(p, t_hard, math.nan, 0.3 * 9.81 * r, reads=True)
    assert as_is[2] == pytest.approx(t_hard) and as_is[1] < nominal[1] - 0.05  # a hard tyre read as a wet road
    # between grid pressures: the knots linear in the pressure
    mid = _pressure_state(p, 0.5 * (t_hard + p.trail_at_pressure[row + 1][j]), 295_000.0, reads=True)
    assert mid[2] == pytest.approx(0.0125, abs=1e-9)
    est = GripEstimator(p, sat_reads_pressure=True)
    est.set_front_pressure(290_000.0)
    first = (est._trail, est._util, est._use, est.peak_ratio)
    est.set_front_pressure(220_000.0)
    est.set_front_pressure(290_000.0)  # (seen before: the same knots and curves, kept)
    assert (est._trail, est._util, est._use, est.peak_ratio) == first and est._trail[j] == t_hard
    est.set_front_pressure(math.nan)  # (the pressure lost again: the calibration's curves)
    _steady(est, 40, 0.3 * 9.81, 0.0125)
    assert (est.state.util, est.state.mu, est.state.trail_m) == pytest.approx(nominal, rel=1e-12)


def test_a_model_blind_to_the_pressure_reads_the_trail_at_the_calibrations_pressure_by_ppz1():
    """For the SATs of a model that does not read the TPMS (its trail carries only part of the pressure's effect), or
    without the tyre's curves (an older file), the trail is scaled to the calibration's pressure by ``PPZ1`` alone,
    ``t / (1 - PPZ1 dpi)``; without the coefficient either, it is read as measured."""
    for reads in (False, True):
        a = _pressure_state(load_params(), 0.009, 290_000.0)
        assert a == pytest.approx(_pressure_state(_without_curves(load_params()), 0.009, 290_000.0, reads=reads))
    p = _without_curves(load_params())
    c, p0 = p.trail_pressure_coeff, p.pressure_nominal_pa
    assert p0 == 220_000.0 and 0.5 < c < 1.2  # (the car's own pressure; its tyre file's PPZ1)
    hard = 290_000.0
    shorter = 1.0 - c * (hard - p0) / p0
    nominal = _pressure_state(p, 0.012, p0)
    assert math.isfinite(nominal[1])
    assert _pressure_state(p, 0.012 * shorter, hard) == pytest.approx(nominal, rel=1e-9)
    assert _pressure_state(p, 0.012, math.nan) == pytest.approx(nominal, rel=1e-12)  # unknown: as measured
    as_is = _pressure_state(p, 0.012 * shorter, math.nan)
    assert as_is[2] == pytest.approx(0.012 * shorter) and as_is[1] < nominal[1] - 0.05
    assert _pressure_state(replace(p, trail_pressure_coeff=0.0), 0.012 * shorter, hard) == pytest.approx(
        as_is, rel=1e-12)
    est = GripEstimator(p)
    est.set_front_pressure(5.1e5)  # far above any rating: the factor is held at 0.25
    assert est._trail_gain == pytest.approx(4.0)


def test_params_are_checked():
    doc = load_params().to_json()
    with pytest.raises(UserError, match="grip params"):
        GripParams.from_json({**doc, "util_at_trail": doc["util_at_trail"][::-1] + [0.0]})
    with pytest.raises(UserError):
        GripParams.from_json({k: v for k, v in doc.items() if k != "mass_kg"})
    for bad in (-0.1, "nan", 1e999):
        with pytest.raises(UserError, match="evidence_long_ratio"):
            GripParams.from_json({**doc, "evidence_long_ratio": float(bad)})
    assert GripParams.from_json({k: v for k, v in doc.items() if k != "evidence_long_ratio"}).evidence_long_ratio == 0
    for bad in ({"trail_pressure_coeff": -0.1}, {"trail_pressure_coeff": float("nan")}, {"trail_pressure_coeff": 2.5},
                {"pressure_nominal_pa": 0.0}, {"pressure_nominal_pa": float("inf")}):
        with pytest.raises(UserError, match="trail_pressure_coeff"):
            GripParams.from_json({**doc, **bad})
    older = GripParams.from_json({k: v for k, v in doc.items() if k not in (
        "trail_pressure_coeff", "pressure_nominal_pa", "pressure_grid_pa", "trail_at_pressure", "peak_at_pressure")})
    assert older.trail_pressure_coeff == 0.0  # (an older file: the trail as measured)
    rows = doc["trail_at_pressure"]
    for bad in ({"pressure_grid_pa": doc["pressure_grid_pa"][:-1]}, {"peak_at_pressure": [0.0] * len(rows)},
                {"trail_at_pressure": [r[::-1] for r in rows]}, {"trail_at_pressure": [r[:-1] for r in rows]},
                {"pressure_grid_pa": doc["pressure_grid_pa"][::-1]},
                {"pressure_nominal_pa": 3.0e5},  # (the grid holds it, but its curves are not the calibration's)
                {"pressure_nominal_pa": 2.25e5},  # (not on the grid)
                {"pressure_grid_pa": [True, *doc["pressure_grid_pa"][1:]]}):
        with pytest.raises(UserError, match="pressure"):
            GripParams.from_json({**doc, **bad})
    assert not GripParams.from_json({k: v for k, v in doc.items() if k not in (
        "pressure_grid_pa", "trail_at_pressure", "peak_at_pressure")}).pressure_grid_pa  # (older: the PPZ1 scale)
    assert GripParams.from_json(doc) == load_params()


def test_metrics_lead_and_false_warnings():
    t = np.arange(200) * 0.05
    u = np.where(t < 5.0, 0.3, 0.97)
    warn = (t >= 4.5) | ((t >= 1.0) & (t < 1.3))
    m = gs.grip_metrics(t, u, np.full(200, 0.5), np.where(t > 5, 0.52, np.nan), warn)
    assert m["warning_lead_s"] == pytest.approx(0.5)
    assert m["false_warnings"] == 1 and m["calm_s"] == pytest.approx(5.0)
    assert m["mu_within_0_1_share"] == 1.0 and m["mu_given_share_above_0_6"] == pytest.approx(99 / 100)
    late = gs.grip_metrics(t, u, np.full(200, 0.5), np.full(200, np.nan), t >= 6.0)
    assert late["warning_lead_s"] == pytest.approx(-1.0) and late["mu_within_0_1_share"] is None
    none = gs.grip_metrics(t, np.full(200, 0.3), np.full(200, 0.5), np.full(200, np.nan), np.zeros(200, bool))
    assert none["warning_lead_s"] is None and gs.pool([none])["warning_lead_s_median"] is None
    assert m["mu_interval_cover_share"] is None  # (no half-widths given: not scored)


def test_samples_without_the_true_friction_are_not_scored():
    """A row whose true mu is unknown (nan) is neither within nor outside +-0.1: the figures are those of the rows
    with the truth, and none at all where no row has it."""
    t = np.arange(100) * 0.05
    u = np.full(100, 0.5)
    est = np.where(t >= 1.0, 0.52, np.nan)  # 80 given, each within 0.1 of the truth 0.5
    truth = np.full(100, 0.5)
    truth[40:80] = np.nan
    m = gs.grip_metrics(t, u, truth, est, np.zeros(100, bool), np.full(100, 0.05))
    assert m["mu_given"] == 80 and m["mu_scored"] == 40
    assert m["mu_within_0_1_share"] == 1.0 and m["mu_abs_err_p90"] == pytest.approx(0.02)
    assert m["mu_interval_cover_share"] == 1.0
    unknown = gs.grip_metrics(t, u, np.full(100, np.nan), est, np.zeros(100, bool), np.full(100, 0.05))
    assert unknown["mu_scored"] == 0 and unknown["mu_within_0_1_share"] is None
    assert unknown["mu_abs_err_p90"] is None and unknown["mu_interval_cover_share"] is None
    pooled = gs.pool([m, unknown])
    assert pooled["mu_given"] == 160 and pooled["mu_scored"] == 40 and pooled["mu_within_0_1_share"] == 1.0
    assert "40 samples given" in gs.grip_markdown({"overall": pooled})


def test_the_interval_coverage_counts_the_given_samples_whose_interval_holds_the_truth():
    """``mu_interval_cover_share``: of the given samples, those with ``|mu - truth| <= halfwidth``; pooled over the
    samples (not the runs); null where no run gave half-widths."""
    t = np.arange(100) * 0.05
    u = np.full(100, 0.5)
    mu = np.where(t >= 2.0, 0.6, np.nan)  # 60 given, 0.1 above the truth 0.5
    hw = np.where(t >= 3.0, 0.15, 0.05)  # the first 20 given too narrow, the last 40 wide enough
    m = gs.grip_metrics(t, u, np.full(100, 0.5), mu, np.zeros(100, bool), hw)
    assert m["mu_interval_cover_share"] == pytest.approx(40 / 60)
    tight = gs.grip_metrics(t, u, np.full(100, 0.5), mu, np.zeros(100, bool), np.full(100, 0.01))
    assert tight["mu_interval_cover_share"] == 0.0
    assert gs.pool([m, tight])["mu_interval_cover_share"] == pytest.approx(40 / 120)
    assert gs.pool([m, gs.grip_metrics(t, u, np.full(100, 0.5), mu, np.zeros(100, bool))])[
        "mu_interval_cover_share"] is None


def test_pool_counts_the_limits_warned_by_the_time_they_are_reached():
    """``limit_warned_share``: of the runs that reach the limit, those warned by then (a lead >= 0); runs that never
    reach it do not count."""
    t = np.arange(200) * 0.05
    u = np.where(t < 5.0, 0.3, 0.97)
    early, late = (gs.grip_metrics(t, u, np.full(200, 0.5), np.full(200, np.nan), t >= t0) for t0 in (4.5, 6.0))
    calm = gs.grip_metrics(t, np.full(200, 0.3), np.full(200, 0.5), np.full(200, np.nan), np.zeros(200, bool))
    assert gs.pool([early, late, calm])["limit_warned_share"] == pytest.approx(0.5)
    assert gs.pool([early, early])["limit_warned_share"] == 1.0 and gs.pool([calm])["limit_warned_share"] is None


def test_lead_metric_cannot_be_gamed_by_a_held_warning_and_always_on_is_false():
    """A warning kept on through calm driving earns no lead for it (counted from the end of the latest calm second
    within the episode); an always-on warning is a false warning in every calm run; a limit the run starts in is
    not one to anticipate (only a rise through 0.95 after the start-up counts)."""
    t = np.arange(200) * 0.05
    u = np.where(t < 5.0, 0.3, 0.97)
    held = gs.grip_metrics(t, u, np.full(200, 0.5), np.full(200, np.nan), t >= 1.5)  # on 3.5 s before, calm
    assert held["warning_lead_s"] == pytest.approx(0.0)
    ramp = np.clip(0.3 + 0.4 * (t - 3.0), 0.3, 0.97)  # calm to 4 s, the limit at 4.625 s (tick 4.65)
    early = gs.grip_metrics(t, ramp, np.full(200, 0.5), np.full(200, np.nan), t >= 3.2)
    assert early["warning_lead_s"] == pytest.approx(4.65 - 3.2)  # (warned 0.8 s while still below 0.7: counted)
    calm = gs.grip_metrics(t, np.full(200, 0.3), np.full(200, 0.5), np.full(200, np.nan), np.ones(200, bool))
    assert calm["false_warnings"] == 1 and calm["false_warnings_per_10min"] > 1.0
    start = gs.grip_metrics(t, np.where(t < 2.0, 0.97, 0.3), np.full(200, 0.5), np.full(200, np.nan),
                            np.zeros(200, bool))
    assert start["warning_lead_s"] is None


def test_the_lead_is_scored_at_the_first_limit_only_and_an_unwarned_last_row_is_not_warned():
    """The lead is before the axle FIRST reaches 0.95: a run that first reaches it in its start-up second is not
    scored, not re-scored on a later corner (it was: a later corner's +0.35 to +1.8 s counted for 4 laps of a
    study); and a limit reached unwarned on the run's last row scored 0.0, counted as warned."""
    t = np.arange(200) * 0.05
    twice = np.where((t >= 0.5) & (t < 0.8) | (t >= 6.0), 0.97, 0.3)  # (a limit in the start-up, one at 6 s)
    m = gs.grip_metrics(t, twice, np.full(200, 0.5), np.full(200, np.nan), t >= 5.0)
    assert m["warning_lead_s"] is None and m["reaches_limit"] and m["limit_in_startup"]
    pooled = gs.pool([m])
    assert pooled["runs_reaching_limit"] == 0 and pooled["runs_limit_in_startup"] == 1
    assert "over 0 runs reaching 0.95 after their start-up (1 more first at it in their first 1 s, not scored)" in \
        gs.grip_markdown({"overall": pooled})
    last = gs.grip_metrics(t, np.where(t >= t[-1], 0.97, 0.3), np.full(200, 0.5), np.full(200, np.nan),
                           np.zeros(200, bool))
    assert last["warning_lead_s"] == pytest.approx(-0.05) and gs.pool([last])["limit_warned_share"] == 0.0
    lateish = gs.grip_metrics(t, np.where(t >= 9.0, 0.97, 0.3), np.full(200, 0.5), np.full(200, np.nan),
                              np.zeros(200, bool))
    assert lateish["warning_lead_s"] == pytest.approx(9.0 - 9.95 - 0.05)


@pytest.fixture(scope="module")
def step_runs(model):
    """Seeded runs, offline with the daemon's code (``estimate_run``, tick for tick the daemon's VS_Grip, see
    test_offline_estimate_is_the_daemons): a dry fishhook that reaches the limit and two calm random-steer runs."""
    from sim.api import Request, simulate_many
    from sim.sensors import truth_at

    reqs = [Request("fishhook", 80.0, 1.0, 8), Request("random-steer", 60.0, 0.3, 7),
            Request("random-steer", 80.0, 1.0, 11)]
    out = []
    for run in simulate_many(reqs):
        ts = run.streams["time_s"]
        rec = simulated_recording(ts, {k: v for k, v in run.streams.items() if k != "time_s"})
        t = np.asarray(rec.table["time_s"], float)
        tr = truth_at(run.truth, t)
        out.append((rec.table, t, np.maximum(tr["util_fl_1"], tr["util_fr_1"]), gs.model_sats(model, rec.table)))
    return out


def test_step_steer_warns_before_the_limit_and_the_demand_leads(step_runs):
    """The fishhook's steering ramp takes the front axle to 95 % utilisation within a second: the warning (the
    driver's demand against the rated road, with the trail and the force) is on before it, and earlier than the
    same warning without the demand term."""
    table, t, u, (fl, fr) = step_runs[0]
    p = load_params()
    assert p.demand_weight > 0
    lead = gs.grip_metrics(t, u, np.ones(len(t)), np.full(len(t), np.nan), estimate_run(table, fl, fr, p)["warning"])
    without = gs.grip_metrics(t, u, np.ones(len(t)), np.full(len(t), np.nan),
                              estimate_run(table, fl, fr, replace(p, demand_weight=0.0))["warning"])
    assert lead["reaches_limit"] and lead["warning_lead_s"] > 0.0
    assert lead["warning_lead_s"] > without["warning_lead_s"]


def test_calm_driving_raises_no_warning(step_runs):
    """Random steering that stays below 70 % utilisation (a wet road near it, a dry one far from it): no warning."""
    for table, _, u, (fl, fr) in step_runs[1:]:
        assert u.max() < 0.7
        assert not estimate_run(table, fl, fr)["warning"].any()


# ------------------------------------------------------------------------------------------------ the matrix
def test_vs_grip_decodes_with_cantools():
    db = cantools.database.load_file(str(dbc_path()))
    m = db.get_message_by_name("VS_Grip")
    assert m.frame_id == 0x202 and m.senders == ["VSENS"] and m.cycle_time == 50
    assert cat.MESSAGES["VS_Grip"].data_id == 0x2021
    data = MATRIX.encode("VS_Grip", {"VS_GripUtil": 0.8, "VS_GripMu": 0.45, "VS_GripMuHalfWidth": 0.05,
                                     "VS_GripWarning": 1, "VS_GripUtil_Status": VALID, "VS_GripMu_Status": VALID,
                                     "VS_GripMuHalfWidth_Status": VALID, "VS_GripWarning_Status": VALID}, 0)
    d = db.decode_message(0x202, data, decode_choices=False)
    assert d["VS_GripUtil"] == pytest.approx(0.8) and d["VS_GripMu"] == pytest.approx(0.45)
    assert d["VS_GripMuHalfWidth"] == pytest.approx(0.05) and d["VS_GripWarning"] == 1
    assert MATRIX.fresh().decode(0x202, data, 0.0).status in USABLE


def test_every_vs_grip_status_is_the_worse_of_the_two_wheels_as_cantools_reads_it():
    """Over all 16 pairs of the two SAT_FRONT statuses (the order INVALID, INIT, DEGRADED, VALID written out here,
    not taken from the code), decoded from the frame by cantools; INVALID or INIT: every value SNA, no warning."""
    from virtsensor.daemon.gripout import GripOutput

    order = [INVALID, INIT, DEGRADED, VALID]  # worst first
    db = cantools.database.load_file(str(dbc_path()))
    signals = list(cat.SIGNALS)
    out = GripOutput(MATRIX, signals)
    inputs = [0.0] * len(signals)
    for name, v in {"vx_mps": 20.0, "ay_mps2": 3.0, "wheel_speed_fl_radps": 65.6,
                    "wheel_speed_fr_radps": 65.6}.items():
        inputs[signals.index(name)] = v
    seen = set()
    for a in order:
        for b in order:
            want = order[min(order.index(a), order.index(b))]
            msg = out.fill(20.0, 22.0, a, b, inputs)
            d = db.decode_message(GRIP_ID, bytes(msg.data), decode_choices=False)
            got = {d[f"{n}_Status"] for n in ("VS_GripUtil", "VS_GripMu", "VS_GripMuHalfWidth", "VS_GripWarning")}
            assert got == {want}, (a, b, d)
            named = db.decode_message(GRIP_ID, bytes(msg.data))  # (the DBC's value names: "SNA")
            sna = {n: str(named[n]) == "SNA" for n in ("VS_GripUtil", "VS_GripMu", "VS_GripMuHalfWidth")}
            if want in (INVALID, INIT):
                assert all(sna.values()) and d["VS_GripWarning"] == 0, (a, b, named)
            else:
                assert not sna["VS_GripUtil"] and 0.0 <= d["VS_GripUtil"] <= 1.0, (a, b, named)
            seen.add(want)
    assert seen == set(order)


# ------------------------------------------------------------------------------------------------ the daemon
@pytest.fixture(scope="module")
def model() -> OnnxModel:
    return OnnxModel.load(str(model_path()))


@pytest.fixture(scope="module")
def run_frames():
    """A wet fishhook (reaches the limit), its frames as a CAN receiver sees them and its truth."""
    from sim.api import Request, simulate_many

    (run,) = simulate_many([Request("fishhook", 60.0, 0.5, 19)])
    ts = run.streams["time_s"]
    sig = {k: v for k, v in run.streams.items() if k != "time_s"}
    return list(iter_frames(ts, sig)), run, simulated_recording(ts, sig)


def _drive(model, frames: list[can.Message]):
    """A sync-mode daemon on a virtual bus: (SAT_FRONT frames, VS_Grip frames, ticks, stats)."""
    ch = f"grip-{uuid.uuid4().hex[:10]}"
    dbus, col = can.Bus(interface="virtual", channel=ch), can.Bus(interface="virtual", channel=ch)
    tx = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
    merged, ticks = with_sync(frames, frames[0].timestamp, frames[-1].timestamp)
    vs = VirtualSensor(dbus, model, MATRIX, sync_id=SYNC_ID, freeze_gc=False)
    assert vs._out.grip.enabled
    vs.start()
    sat: list[can.Message] = []
    grip: list[can.Message] = []
    try:
        for f in merged:
            tx.send(f)
        end = time.monotonic() + 30
        while (len(sat) < len(ticks) or len(grip) < len(ticks)) and time.monotonic() < end:
            m = col.recv(0.5)
            if m is None or m.timestamp < 1e6:
                continue
            if m.arbitration_id == SAT_ID:
                sat.append(m)
            elif m.arbitration_id == GRIP_ID:
                grip.append(m)
    finally:
        stats = vs.stop()
        tx.shutdown()
        col.shutdown()
    assert stats["tick_errors"] == 0 and len(sat) == len(grip) == len(ticks)
    return sat, grip, ticks


def _decode(sat: list[can.Message], grip: list[can.Message]):
    ms, mg = MATRIX.fresh(), MATRIX.fresh()
    sat_st, vals, gst = [], [], []
    for i, (a, b) in enumerate(zip(sat, grip, strict=True)):
        da, db = ms.decode(a.arbitration_id, a.data, 0.05 * i), mg.decode(b.arbitration_id, b.data, 0.05 * i)
        assert db.status in USABLE  # VS_Grip's own E2E: CRC and counter right, one frame per tick
        o = db.other
        sat_st.append((int(da.other["SAT_FL_Status"]), int(da.other["SAT_FR_Status"])))
        gst.append([int(o[f"{n}_Status"]) for n in ("VS_GripUtil", "VS_GripMu", "VS_GripMuHalfWidth",
                                                    "VS_GripWarning")])
        vals.append((o["VS_GripUtil"], o["VS_GripMu"], o["VS_GripMuHalfWidth"], int(o["VS_GripWarning"])))
    return np.array(sat_st), np.array(vals, dtype=float), np.array(gst)


def _statuses_follow_sat(sat_st: np.ndarray, vals: np.ndarray, gst: np.ndarray) -> None:
    want = np.array([worse_status(a, b) for a, b in sat_st])
    assert (gst == want[:, None]).all()
    bad = (want == INVALID) | (want == INIT)
    assert np.isnan(vals[bad, :3]).all() and (vals[bad, 3] == 0).all()  # SNA, never a number, no warning
    assert np.isfinite(vals[~bad, 0]).all()  # the utilisation is always given while VALID/DEGRADED
    assert (np.isnan(vals[:, 1]) == np.isnan(vals[:, 2])).all()


def test_daemon_publishes_vs_grip_tracking_truth(model, run_frames):
    frames, run, _ = run_frames
    sat, grip, ticks = _drive(model, frames)
    sat_st, vals, gst = _decode(sat, grip)
    _statuses_follow_sat(sat_st, vals, gst)
    assert np.isin(gst[5:], (VALID, DEGRADED)).all()  # (DEGRADED: outside the model's envelope at the limit)
    db = cantools.database.load_file(str(dbc_path()))  # the frames the daemon sent, as a third party reads them
    for m, v in zip(grip, vals, strict=True):
        d = db.decode_message(m.arbitration_id, bytes(m.data), decode_choices=False)
        for k, name in enumerate(("VS_GripUtil", "VS_GripMu", "VS_GripMuHalfWidth")):
            assert math.isnan(v[k]) or d[name] == pytest.approx(v[k], abs=1e-9), (name, d, v)
        assert d["VS_GripWarning"] == v[3]
    from sim.sensors import truth_at

    truth = truth_at(run.truth, np.asarray(ticks) - frames[0].timestamp)
    u_true = np.maximum(truth["util_fl_1"], truth["util_fr_1"])
    assert vals[:, 3].any() and u_true.max() > 0.8  # the limit is reached and warned of
    given = np.isfinite(vals[:, 1])
    assert given.any() and np.all(np.abs(vals[given, 1] - 0.5) <= 0.15)


@pytest.mark.parametrize(("message", "expected"), [("ESC_VehicleSpeed", INVALID), ("PT_Torque", DEGRADED)])
def test_vs_grip_statuses_under_timeout(model, run_frames, message, expected):
    frames = run_frames[0]
    fid, t0 = MATRIX.messages[message].frame_id, frames[0].timestamp
    kept = [f for f in frames if not (f.arbitration_id == fid and t0 + 2.0 <= f.timestamp < t0 + 3.0)]
    sat, grip, _ = _drive(model, kept)
    sat_st, vals, gst = _decode(sat, grip)
    _statuses_follow_sat(sat_st, vals, gst)
    assert (gst[:, 0] == expected).sum() >= 10  # the timeout reaches VS_Grip as it reaches SAT_FRONT
    assert np.isin(gst[-10:], (VALID, DEGRADED)).all()  # and it recovers with it


def test_vs_grip_statuses_under_e2e_fault(model, run_frames):
    frames = run_frames[0]
    fid, t0 = MATRIX.messages["EPAS_Steering"].frame_id, frames[0].timestamp
    out, done = [], False
    for f in frames:
        if not done and f.arbitration_id == fid and f.timestamp >= t0 + 2.001:  # a wrong CRC on a critical input
            done = True
            f = can.Message(timestamp=f.timestamp, arbitration_id=fid, is_extended_id=False,
                            data=bytes([f.data[0] ^ 0x5A]) + bytes(f.data[1:]))
        out.append(f)
    sat, grip, _ = _drive(model, out)
    sat_st, vals, gst = _decode(sat, grip)
    _statuses_follow_sat(sat_st, vals, gst)
    assert (gst[:, 0] == INVALID).sum() >= 1 and np.isin(gst[-10:], (VALID, DEGRADED)).all()


def test_offline_estimate_is_the_daemons(model, run_frames):
    """``estimate_run`` (scoring) and the daemon's VS_Grip agree tick for tick on the same run."""
    frames, _, rec = run_frames
    sat, grip, ticks = _drive(model, frames)
    _, vals, _ = _decode(sat, grip)
    fl, fr = gs.model_sats(model, rec.table)
    est = estimate_run(rec.table, fl, fr, outside=gs.model_outside(model, rec.table))
    off = rec.dropped_ticks  # online tick k <-> offline table row k - off
    assert len(ticks) == off + len(fl)
    on = vals[off:]
    ok = np.isfinite(est["util"])
    assert ok.sum() > 0.8 * len(fl) and (np.isfinite(on[:, 0]) == ok).all()
    assert np.abs(on[ok, 0] - est["util"][ok]).max() <= 0.0025 + 1e-9  # (VS_GripUtil resolution 0.005)
    assert (on[:, 3] == est["warning"]).all()
    assert (np.isfinite(on[:, 1]) == np.isfinite(est["mu"])).all()


def _curve_streams(t: np.ndarray, vx: np.ndarray, steer: np.ndarray) -> dict[str, np.ndarray]:
    """A car turning kinematically (yaw rate vx * delta / L, ay = r vx) with plausible EPAS, wheels and body."""
    L = cat.STEADY_TURN.steer_ratio * cat.STEADY_TURN.wheelbase_m
    r = vx * steer / L
    sig = {"vx_mps": vx, "yaw_rate_radps": r, "ay_mps2": r * vx, "steer_angle_rad": steer,
           "ax_mps2": 0.1 * np.sin(t), "motor_torque_nm": 25.0 + 2.0 * np.sin(t),
           "steer_torque_nm": 1.0 + 0.1 * np.sin(t), "susp_defl_fl_m": -0.002 * r * vx,
           "susp_defl_fr_m": 0.002 * r * vx}
    b = cat.EPAS_BOOST
    tb = sig["steer_torque_nm"]
    sig["assist_torque_nm"] = np.interp(vx, b.speeds_mps, b.gains) * tb * np.abs(tb) / (np.abs(tb) + b.knee_nm)
    d = steer / cat.STEADY_TURN.steer_ratio
    for w in ("fl", "fr"):
        sig[f"wheel_speed_{w}_radps"] = vx / np.cos(d) / cat.ROLLING_RADIUS_M
    half = r * cat.TRACK_REAR_M / 2.0
    sig["wheel_speed_rl_radps"], sig["wheel_speed_rr_radps"] = (vx - half) / 0.305, (vx + half) / 0.305
    k = cat.TRACK_REAR_M / cat.TRACK_FRONT_M
    sig["susp_defl_rl_m"], sig["susp_defl_rr_m"] = k * sig["susp_defl_fl_m"], k * sig["susp_defl_fr_m"]
    return sig


def test_a_friction_read_from_extrapolated_sats_is_never_given_nor_held(model):
    """6 s at 56 m/s in a gentle left curve (the shipped model trained up to some 50 m/s: outside its envelope,
    DEGRADED), then 45 m/s in a gentler one (inside: VALID). The extrapolated SATs point the wrong way, as a trail
    collapsed at 1.6 m/s^2: the daemon gave a friction of 0.2 from them, DEGRADED, and held it on into the VALID
    stretch, where VS_Grip published it VALID. Now no friction is read outside: unknown throughout."""
    t = np.arange(0.0, 9.0, 0.01)
    sig = _curve_streams(t, np.where(t < 6.0, 56.0, 45.0), np.where(t < 6.0, 0.02, 0.012))
    frames = list(iter_frames(t, sig))
    merged, _ = with_sync(frames, frames[0].timestamp, frames[-1].timestamp)
    vs = VirtualSensor(CaptureBus(), model, MATRIX, sync_id=SYNC_ID, freeze_gc=False)
    outside = []
    for m in merged:
        n = vs.counters["ticks"]
        vs.process(m)
        if vs.counters["ticks"] > n:
            outside.append(vs.outside_envelope)
    assert vs.counters["tick_errors"] == 0 and vs.counters["implausible_checks"] == 0
    sent = vs.bus.sent
    sat = [MATRIX.db.decode_message(SAT_ID, f.data, decode_choices=False) for f in sent if f.arbitration_id == SAT_ID]
    grip = [MATRIX.fresh().decode(GRIP_ID, f.data, 0.0).other for f in sent if f.arbitration_id == GRIP_ID]
    st = [(s["SAT_FL_Status"], s["SAT_FR_Status"]) for s in sat]
    out = [i for i, o in enumerate(outside) if o]
    assert len(out) >= 100 and all(st[i] == (DEGRADED, DEGRADED) for i in out)
    back = [i for i in range(out[-1] + 1, len(st))]
    assert len(back) >= 50 and all(st[i] == (VALID, VALID) for i in back)
    assert all(math.isnan(g["VS_GripMu"]) and math.isnan(g["VS_GripMuHalfWidth"]) for g in grip[5:])
    assert all(math.isfinite(g["VS_GripUtil"]) for g in grip[5:])


@pytest.fixture(scope="module")
def hard_tyre_run():
    """A double lane change on a wet road with the front tyres at 2.9 bar (the car's own: 2.2): its frames and its
    offline table (with the TPMS pressures)."""
    from sim.api import Request, simulate_many

    (run,) = simulate_many([Request("double-lane-change", 80.0, 0.5, 3, pressures_bar=(2.9, 2.9, 2.2, 2.2))])
    ts = run.streams["time_s"]
    sig = {k: v for k, v in run.streams.items() if k != "time_s"}
    return list(iter_frames(ts, sig)), simulated_recording(ts, sig)


def test_the_tpms_pressure_corrects_the_friction_of_a_hard_tyre(model, hard_tyre_run):
    _, rec = hard_tyre_run
    fl, fr = gs.model_sats(model, rec.table)
    with_p = estimate_run(rec.table, fl, fr)
    without = estimate_run({k: v for k, v in rec.table.items() if k not in PRESSURE_INPUTS}, fl, fr)
    share = {}
    for name, e in (("with", with_p), ("without", without)):
        given = np.isfinite(e["mu"])
        assert given.sum() >= 50
        share[name] = float(np.mean(np.abs(e["mu"][given] - 0.5) <= 0.1))
    assert share["with"] >= 0.85 and share["with"] >= share["without"] + 0.15, share


def test_the_daemon_reads_the_front_pressures_as_offline(model, hard_tyre_run):
    """The daemon decodes the TPMS for its grip estimate (the model does not read it) and publishes, tick for tick,
    what ``estimate_run`` gives with the table's pressures; with the TPMS off the bus, what it gives without them."""
    from virtsensor.daemon.layout import InputLayout

    lay = InputLayout.from_model(model, MATRIX)
    assert "tyre_pressure_fl_pa" not in lay.signals and lay.grip_signals == PRESSURE_INPUTS
    tpms = OnnxModel.load(str(model_path("tpms")))
    assert InputLayout.from_model(tpms, MATRIX).grip_signals == ()  # (its model reads them)
    older = CanMatrix(MATRIX.db, {k: v for k, v in MATRIX.messages.items() if k != "VS_Grip"}, MATRIX.source)
    assert InputLayout.from_model(model, older).grip_signals == ()  # (no VS_Grip: nothing reads them)
    frames, rec = hard_tyre_run
    fl, fr = gs.model_sats(model, rec.table)
    off = rec.dropped_ticks
    tpms_id = MATRIX.messages["TPMS_Pressures"].frame_id
    for kept, table in ((frames, rec.table),
                        ([f for f in frames if f.arbitration_id != tpms_id],
                         {k: v for k, v in rec.table.items() if k not in PRESSURE_INPUTS})):
        sat, grip, ticks = _drive(model, kept)
        _, vals, _ = _decode(sat, grip)
        est = estimate_run(table, fl, fr)
        on = vals[off:]
        assert len(ticks) == off + len(fl)
        given = np.isfinite(est["mu"])
        assert given.sum() >= 50 and (np.isfinite(on[:, 1]) == given).all()
        assert np.abs(on[given, 1] - est["mu"][given]).max() <= 0.0025 + 1e-9  # (VS_GripMu resolution 0.005)


def test_replace_keeps_params_valid():
    """A replaced field is checked as the file's are: warning thresholds in order are taken, any other refused."""
    p = replace(load_params(), warn_on=0.9, warn_off=0.6)
    assert (p.warn_on, p.warn_off) == (0.9, 0.6)
    for on, off in ((0.5, 0.6), (1.1, 0.6), (0.7, 0.0), (0.7, -0.1)):
        with pytest.raises(ValueError, match="warn_off <= warn_on"):
            replace(p, warn_on=on, warn_off=off)


def test_no_vs_grip_in_the_dbc_publishes_none():
    from types import SimpleNamespace

    from virtsensor.daemon.gripout import NoGrip, grip_output

    older = SimpleNamespace(messages={k: v for k, v in MATRIX.messages.items() if k != "VS_Grip"})
    wheels = (SimpleNamespace(estimate="SAT_FL", status="SAT_FL_Status"),
              SimpleNamespace(estimate="SAT_FR", status="SAT_FR_Status"))
    assert isinstance(grip_output(older, cat.INPUTS, wheels), NoGrip)
    assert isinstance(grip_output(MATRIX, cat.INPUTS[:5], wheels), NoGrip)  # an input the estimate reads missing
    assert grip_output(MATRIX, cat.INPUTS, wheels).enabled


def test_the_daemon_reads_the_pressure_on_the_tyres_curves_only_for_a_model_that_reads_it():
    from types import SimpleNamespace

    from virtsensor.daemon.gripout import grip_output
    from virtsensor.grip import reads_pressure

    wheels = (SimpleNamespace(estimate="SAT_FL", status="SAT_FL_Status"),
              SimpleNamespace(estimate="SAT_FR", status="SAT_FR_Status"))
    decoded = (*cat.INPUTS, *PRESSURE_INPUTS)
    blind = grip_output(MATRIX, decoded, wheels, model_signals=cat.INPUTS)
    tpms = grip_output(MATRIX, decoded, wheels, model_signals=decoded)
    assert not blind.estimator.sat_reads_pressure and tpms.estimator.sat_reads_pressure
    assert not grip_output(MATRIX, decoded, wheels).estimator.sat_reads_pressure  # (model's inputs not said: PPZ1)
    assert reads_pressure(decoded) and not reads_pressure((*cat.INPUTS, PRESSURE_INPUTS[0]))


def test_score_reports_grip_per_run_and_overall(model, run_frames, tmp_path):
    from virtsensor.learning.dataset import load_runs
    from virtsensor.learning.scoring import markdown, score_runs
    from virtsensor.recordings.simulated import write_run_file

    _, run, _ = run_frames
    write_run_file(run, tmp_path / "fh.csv")
    write_run_file(run, tmp_path / "fh.blf")  # a CAN log carries no grip truth
    # (loaded apart: given together, the same run as a table and as a log is refused as one run given twice)
    res = score_runs(model, load_runs([tmp_path / "fh.csv"]) + load_runs([tmp_path / "fh.blf"]))
    keys = {"mu_within_0_1_share", "mu_abs_err_p90", "mu_given_share_above_0_6", "warning_lead_s_median",
            "false_warnings_per_10min", "mu_interval_cover_share"}
    g = res["overall"]["grip"]
    assert keys <= set(g) and g["runs"] == 1 and g["mu_given"] > 0
    assert keys <= set(res["runs"][0]["grip"]) and res["runs"][1]["grip"] is None
    assert 0.9 <= g["mu_within_0_1_share"] <= 1.0
    assert "Grip (1 runs with the truth)" in markdown(res)


def test_a_tpms_model_reads_the_hard_tyre_on_its_own_curves(hard_tyre_run):
    """With a SAT model that reads the TPMS (its trail carries the pressure's whole effect) the estimate reads the
    trail on the tyre's own curves at that pressure: the hard tyre's friction is right more often than by the
    ``PPZ1`` scale, and the daemon publishes, tick for tick, what ``estimate_run`` gives."""
    tpms = OnnxModel.load(str(model_path("tpms")))
    assert gs.model_reads_pressure(tpms)
    frames, rec = hard_tyre_run
    fl, fr = gs.model_sats(tpms, rec.table)
    share = {}
    for name, reads in (("curves", True), ("ppz1", False)):
        e = estimate_run(rec.table, fl, fr, sat_reads_pressure=reads)
        given = np.isfinite(e["mu"])
        assert given.sum() >= 50
        err = np.abs(e["mu"][given] - 0.5)
        share[name] = (float(np.mean(err <= 0.1)), float(np.quantile(err, 0.9)))
    print(share)
    assert share["curves"][0] >= 0.95 and share["curves"][1] <= 0.8 * share["ppz1"][1], share
    est = estimate_run(rec.table, fl, fr, sat_reads_pressure=True)
    sat, grip, ticks = _drive(tpms, frames)
    _, vals, _ = _decode(sat, grip)
    on = vals[rec.dropped_ticks:]
    given = np.isfinite(est["mu"])
    assert (np.isfinite(on[:, 1]) == given).all()
    assert np.abs(on[given, 1] - est["mu"][given]).max() <= 0.0025 + 1e-9  # (VS_GripMu resolution 0.005)


def test_a_friction_read_from_degraded_sats_stays_degraded_while_held():
    """A friction read on DEGRADED ticks (a non-critical input held or substituted, the SATs outside the envelope) is
    published DEGRADED; held on into VALID ticks it must not turn VALID: the friction and its half-width keep the
    worst status of the ticks its held median rests on (the latest ``hold_count`` that gave one), while the
    utilisation and the warning follow the tick. Once VALID ticks have given as many, the held friction is VALID."""
    from virtsensor.daemon.gripout import GripOutput

    signals = list(cat.SIGNALS)
    out = GripOutput(MATRIX, signals)
    p = out.estimator.params

    def tick(ay: float, trail: float, status: int) -> tuple[float, bool, int, int]:
        x = [0.0] * len(signals)
        for k, v in {"vx_mps": 20.0, "ay_mps2": ay, "yaw_rate_radps": ay / 20.0, "steer_angle_rad": 0.05,
                     "motor_torque_nm": 20.0, "wheel_speed_fl_radps": 20 / 0.305,
                     "wheel_speed_fr_radps": 20 / 0.305}.items():
            x[signals.index(k)] = v
        fy = p.mass_kg * p.front_load_fraction * ay
        out.fill(-0.5 * trail * fy, -0.5 * trail * fy, status, status, x)
        s = out.estimator.state
        return s.mu, s.held, out.values["VS_GripMu_Status"], out.values["VS_GripUtil_Status"]

    for _ in range(60):  # a collapsed trail at 0.4 g on DEGRADED ticks: a friction given, DEGRADED
        mu, held, st_mu, st_util = tick(0.4 * 9.81, 0.0, DEGRADED)
    assert math.isfinite(mu) and not held and st_mu == DEGRADED
    n_held = 0
    for _ in range(20):  # gentle driving on VALID ticks: once the friction is the held one, still DEGRADED
        mu, held, st_mu, st_util = tick(0.25 * 9.81, 0.03, VALID)
        assert st_util == VALID and (not held or (math.isfinite(mu) and st_mu == DEGRADED))
        n_held += held
    assert held and n_held >= 15
    for _ in range(int(p.hold_count) + 5):  # VALID ticks give the friction again, then it is held VALID
        tick(0.4 * 9.81, 0.0, VALID)
    mu, held, st_mu, _ = tick(0.25 * 9.81, 0.03, VALID)
    assert held and math.isfinite(mu) and st_mu == VALID
    db = cantools.database.load_file(str(dbc_path()))
    d = db.decode_message(GRIP_ID, bytes(out.msg.data), decode_choices=False)
    assert d["VS_GripMu_Status"] == VALID and d["VS_GripUtil_Status"] == VALID


def test_the_hold_reads_the_held_median_s_own_error():
    """The held friction is the median of ``hold_count`` readings, and the hold's gate reads that median's calibrated
    error (``hold_err90`` of its band, widened as held), not the latest single reading's pooled error: gated by a
    reading's error near ``halfwidth_max``, the hold ended within metres, so on dry circuits the friction went unknown
    under every braking and drive although the median held the road within +-0.1 (README, "How long to hold the
    road").
    A median whose own error leaves no room is withheld; without ``hold_err90`` (older files) the gate reads the
    latest reading's error, as before."""
    p = load_params()
    assert len(p.hold_err90) == len(p.mu_bands)  # (the shipped calibration has it)
    probe = GripEstimator(p)
    _steady(probe, 60, 0.4 * 9.81, 0.0)
    hw = probe._hw_held  # (the latest reading's pooled error)
    assert math.isfinite(probe.state.mu) and 0.0 < hw <= p.halfwidth_max
    tight = replace(p, halfwidth_max=hw + 0.005)  # (room for 50 m of widening after the latest reading)

    def held_after(q: GripParams, metres: float) -> float:
        est = GripEstimator(q)
        _steady(est, 60, 0.4 * 9.81, 0.0)
        ax = 150.0 * q.gear_ratio / q.rolling_radius_m / q.mass_kg
        for _ in range(round(metres / (20.0 * 0.05))):  # hard drive at 20 m/s: the trail is not read
            s = est.step(-30.0, -30.0, ax, 1.0, 20.0, 0.05, 0.0, 150.0, 20.0 / 0.305, 20.0 / 0.305)
        assert math.isnan(s.trail_m)
        return s.mu if s.held or math.isnan(s.mu) else -1.0

    bands = len(p.mu_bands)
    assert math.isfinite(held_after(replace(tight, hold_err90=()), 30.0))  # (the old gate: 30 m fits)
    assert math.isnan(held_after(replace(tight, hold_err90=()), 100.0))  # (100 m does not: refused)
    assert held_after(replace(tight, hold_err90=(0.01,) * bands), 100.0) == pytest.approx(probe.state.mu, rel=0.1)
    assert math.isnan(held_after(replace(tight, hold_err90=(tight.halfwidth_max,) * bands), 30.0))
    doc = replace(p, hold_err90=()).to_json()
    assert GripParams.from_json(doc).hold_err90 == () and GripParams.from_json(p.to_json()) == p
    for bad in ((0.01,) * (bands - 1), (math.nan,) * bands, (-0.01,) * bands, (True,) * bands):
        with pytest.raises(ValueError, match="hold_err90"):
            replace(p, hold_err90=bad)
