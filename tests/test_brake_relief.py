"""The track driver lets the brakes off while a wheel starts to lock (``Driver._lock_relief``), and the motor
torque while a driven front wheel starts to spin (``Driver._spin_relief``).

Braking out of a corner unloads the inner rear wheel; the fixed brake balance (no ABS or EBD in the
car) then saturates it, the rear loses its side force and the car spins: the dry Montreal lap did
so before. Only the driver that follows a speed profile (``Plan.path_grip``) lets off; open-loop
brake commands (the paper's manoeuvres) keep the balance, and so does the track driver as long as
no wheel slips past the thresholds.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim.driver import SPEED_OPEN, STEER_PATH, STEER_TABLE, Driver, Plan
from sim.manoeuvres import TRACK_GRIP
from sim.params import car_parameters
from sim.vehicle import IKA, Vehicle

SPEED = 30.0  # m/s, the car's speed in every run
FRONT_NM = 900.0  # open-loop front brake torque (Nm per wheel)
MOTOR_NM = 150.0  # open-loop motor torque (Nm)
SHARE = car_parameters()["brakes"]["front_share"]


def _plan(open_loop: bool, target_mps: float = 20.0) -> Plan:
    """A straight road; the track driver asked for ``target_mps`` (20 m/s: it brakes), or open-loop commands
    (a brake torque when braking, a motor torque when the target is above the car's speed)."""
    n = len(Plan.grid(2.0))
    xs = np.arange(0.0, 200.0, 1.0)
    drive = target_mps > SPEED
    return Plan(name="brake", duration_s=2.0, speed0_mps=SPEED,
                steer_mode=np.full(n, STEER_TABLE if open_loop else STEER_PATH, np.int8), steer_sw=np.zeros(n),
                speed_mode=np.full(n, SPEED_OPEN if open_loop else 0, np.int8), speed_target=np.full(n, SPEED),
                motor_cmd=np.full(n, MOTOR_NM if open_loop and drive else 0.0),
                brake_cmd=np.full(n, FRONT_NM if open_loop and not drive else 0.0), mu_values=(1.0,),
                path=np.stack([xs, np.zeros_like(xs)], axis=1), path_ds=1.0,
                path_speed=None if open_loop else np.full(len(xs), target_mps),
                path_grip=None if open_loop else TRACK_GRIP)


def _inputs(kappa: np.ndarray, open_loop: np.ndarray, steps: int = 30, target_mps: float = 20.0):
    """The driver's inputs after ``steps`` updates, the state held with the wheels' longitudinal slips ``kappa``
    ((B, 4), -; negative braking)."""
    car = car_parameters()
    veh = Vehicle([car] * len(open_loop))
    drv = Driver(veh, [_plan(bool(o), target_mps) for o in open_loop], [car] * len(open_loop))
    x = veh.initial_state(np.full(len(open_loop), SPEED))
    x[:, IKA] = np.asarray(kappa)
    drv.reset(x)
    for k in range(steps):
        u = drv.update(k, x)
    return u


def _brake_torques(slip: np.ndarray, open_loop: np.ndarray, steps: int = 30) -> np.ndarray:
    """(B, 4) brake torques (Nm) after ``steps`` driver updates, the state held with the wheels'
    braking slips ``slip`` ((B, 4), -)."""
    return _inputs(-np.asarray(slip), open_loop, steps).brake_torque


def _drive_torques(spin: np.ndarray, open_loop: np.ndarray, steps: int = 300) -> np.ndarray:
    """(B,) left front drive torques (Nm) after ``steps`` updates of a driver asked to accelerate from 30 to
    40 m/s, the state held with the wheels' drive slips ``spin`` ((B, 4), -)."""
    return _inputs(np.asarray(spin), open_loop, steps, target_mps=40.0).drive_torque[:, 0]


def test_a_wheel_starting_to_lock_lets_the_track_drivers_brakes_off():
    rear_left = [0.0, 0.0, 1.0, 0.0]
    slip = np.array([np.zeros(4), [0.06, 0.01, 0.02, 0.02], np.multiply(rear_left, 0.08), np.multiply(rear_left, 0.08),
                     [0.30, 0.0, 0.0, 0.0]])
    open_loop = np.array([False, False, False, True, False])
    tq = _brake_torques(slip, open_loop)
    balance = tq[:, 0] * (1.0 - SHARE) / SHARE
    assert (tq[:4, 0] > 500.0).all()  # every run but the last brakes hard at the front
    # rolling, or slipping as a wheel does braking hard: the balance, bit for bit
    assert np.array_equal(tq[1, :2], tq[0, :2])
    assert np.array_equal(tq[:2, 2:], np.stack([balance[:2]] * 2, axis=1))
    # a rear wheel locking under the track driver: its rear brakes are off, the front unchanged
    assert tq[2, 0] == tq[0, 0]
    assert (tq[2, 2:] < 0.01 * balance[2]).all()
    # the same wheel under an open-loop brake command (the paper's manoeuvres): the balance
    assert tq[3, 0] == pytest.approx(FRONT_NM, rel=0.01)  # the pressure builds up with its time constant
    assert np.array_equal(tq[3, 2:], [balance[3]] * 2)
    # a front wheel locking: the whole pedal is off
    assert (tq[4] < 0.01 * tq[0]).all()


@pytest.mark.parametrize("axle, relief", [(2, Driver.REAR_SLIP_RELIEF), (0, Driver.FRONT_SLIP_RELIEF)])
def test_the_let_off_grows_linearly_with_the_slip_between_its_two_thresholds(axle: int, relief: tuple) -> None:
    on, off = relief
    slip = np.zeros((4, 4))
    slip[1:, axle] = [on, 0.5 * (on + off), off]
    tq = _brake_torques(slip, np.zeros(4, dtype=bool), steps=300)
    assert np.array_equal(tq[1], tq[0])  # at the first threshold, nothing yet
    assert tq[2, 2] / tq[0, 2] == pytest.approx(0.5, abs=1e-6)  # halfway: half the rear brakes' torque
    assert tq[3, 2] == pytest.approx(0.0, abs=1e-6)
    # the rear let-off leaves the front brakes alone; the front's lets the pedal off
    assert (tq[2, 0] == tq[0, 0]) == (axle == 2)


def test_a_driven_wheel_starting_to_spin_lets_the_track_drivers_motor_torque_off():
    on, off = Driver.FRONT_SPIN_RELIEF
    spin = np.zeros((6, 4))
    spin[1] = [0.02, 0.02, 0.0, 0.0]  # accelerating hard on a dry road: about 2 % (no let-off)
    spin[2:5, 1] = [on, 0.5 * (on + off), off]  # the right front wheel spinning
    spin[5, 1] = off  # the same under an open-loop motor command (the paper's manoeuvres)
    open_loop = np.array([False] * 5 + [True])
    tq = _drive_torques(spin, open_loop)
    assert tq[0] > 100.0  # the track driver drives hard towards 40 m/s
    assert tq[1] == tq[0] and tq[2] == tq[0]  # up to the first threshold, bit for bit
    assert tq[3] / tq[0] == pytest.approx(0.5, abs=1e-6)  # halfway: half the torque
    assert tq[4] == pytest.approx(0.0, abs=1e-6)  # spinning past the second: off
    assert tq[5] == pytest.approx(_drive_torques(np.zeros((1, 4)), np.array([True]))[0])  # open loop: untouched
