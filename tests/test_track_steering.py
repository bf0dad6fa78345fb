"""The track driver steers a corner with its car's understeer (``Driver._follow``).

Pure pursuit asks for the curvature of the arc to its preview point and turns it into a road-wheel angle with
the kinematic (Ackermann) gain ``atan(L kappa)``. At speed a car needs more: its steady-state steering is
``L kappa + K_us v^2 kappa`` (``K_us`` the understeer gradient, rad per m/s^2), so a kinematic driver holds a
corner only once its lateral error has grown enough to ask for the rest, on the outside of the line (a random
circuit's lap at 170 km/h left the road that way; README, "A driver that knows its car's understeer"). The driver that
follows a speed profile adds its car's ``K_us v^2 kappa`` of the path ahead; the open-loop and ISO path
manoeuvres (the paper's campaign) keep the kinematic gain, bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim.driver import STEER_PATH, Driver, Plan
from sim.linear import linear_model
from sim.manoeuvres import TRACK_GRIP
from sim.params import car_parameters
from sim.vehicle import Vehicle

RADIUS_M = 210.0


def _circle_plan(graded: bool, speed_mps: float) -> Plan:
    """A left-hand circle of :data:`RADIUS_M` starting at the origin heading +x, points 1 m apart; the track
    driver's speed profile (``graded``) or a path without one."""
    n = len(Plan.grid(2.0))
    theta = np.arange(0.0, 600.0) / RADIUS_M
    path = np.stack([RADIUS_M * np.sin(theta), RADIUS_M * (1.0 - np.cos(theta))], axis=1)
    return Plan(name="circle", duration_s=2.0, speed0_mps=speed_mps,
                steer_mode=np.full(n, STEER_PATH, np.int8), steer_sw=np.zeros(n), speed_mode=np.zeros(n, np.int8),
                speed_target=np.full(n, speed_mps), motor_cmd=np.zeros(n), brake_cmd=np.zeros(n), mu_values=(1.0,),
                path=path, path_ds=1.0, path_speed=np.full(len(path), speed_mps) if graded else None,
                path_grip=TRACK_GRIP if graded else None)


@pytest.mark.parametrize("speed_mps", [15.0, 35.7, 47.0])
def test_the_track_driver_adds_its_cars_understeer_to_the_kinematic_steering(speed_mps: float) -> None:
    car = car_parameters()
    veh = Vehicle([car, car])
    drv = Driver(veh, [_circle_plan(True, speed_mps), _circle_plan(False, speed_mps)], [car, car])
    x = veh.initial_state(np.full(2, speed_mps))  # on the path, along it (origin, heading +x)
    drv.reset(x)
    sw, _ = drv._follow(x)
    delta = sw / veh.ratio
    kin = np.arctan(veh.L / RADIUS_M)  # pure pursuit on a circle it sits on asks for the circle's curvature
    k_us = linear_model(car).understeer_gradient
    assert delta[1] == pytest.approx(kin, rel=2e-3)  # no speed profile: the kinematic gain
    assert delta[0] == pytest.approx(kin + k_us * speed_mps**2 / RADIUS_M, rel=2e-3)
