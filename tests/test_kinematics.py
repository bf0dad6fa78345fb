"""The kinematic check of a named motion-sensor gain (virtsensor.diagnose.kinematics), on synthetic drives whose
physics is known: ay = dvy/dt + r vx + g sin(roll)."""

from __future__ import annotations

import numpy as np
import pytest

from virtsensor.diagnose import kinematics as kin

G = 9.80665


def _drive(yaw_scale: float = 1.0, corners: int = 6, seed: int = 0) -> dict[str, np.ndarray]:
    """True signals of a drive at 20 Hz: corners (half-sine yaw-rate pulses of alternating sign) between
    straights, a lateral velocity that swells in each corner and is 0 on the straights, roll from ay."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, corners * 8.0, 0.05)
    vx = 20.0 + 2.0 * np.sin(2 * np.pi * t / 37.0)
    r = np.zeros_like(t)
    vy = np.zeros_like(t)
    for k in range(corners):
        t0, dur = 8.0 * k + 2.0, rng.uniform(3.0, 5.0)
        inside = (t >= t0) & (t <= t0 + dur)
        shape = np.sin(np.pi * (t[inside] - t0) / dur)
        amp = (-1) ** k * rng.uniform(0.15, 0.35) * yaw_scale
        r[inside] = amp * shape
        vy[inside] = -0.08 * amp * vx[inside] * shape ** 2  # the car swings out, and back in
    ay_kin = np.gradient(vy, t) + r * vx
    roll = -0.006 * ay_kin  # rad: ~0.35 deg per m/s^2
    return {"t": t, "ay_mps2": ay_kin + G * np.sin(roll), "yaw_rate_radps": r, "vx_mps": vx}


def _segment(meas: dict[str, np.ndarray], pred: dict[str, np.ndarray], valid=None) -> kin.Segment:
    n = len(meas["t"])
    return kin.Segment(meas["t"], {k: meas[k] for k in kin.TERMS}, {k: pred[k] for k in kin.TERMS},
                       np.ones(n, bool) if valid is None else valid)


def _with(sig: dict[str, np.ndarray], **gains: float) -> dict[str, np.ndarray]:
    out = dict(sig)
    for k, g in gains.items():
        out[k] = sig[k] * g
    return out


@pytest.mark.parametrize("signal,gain", [("yaw_rate_radps", 1.05), ("yaw_rate_radps", 0.93), ("ay_mps2", 0.9),
                                         ("vx_mps", 1.08)])
def test_a_sensor_gain_is_measured_by_the_kinematics(signal: str, gain: float) -> None:
    true = _drive()
    s = kin.gain_shift([_segment(_with(true, **{signal: gain}), true)], signal)
    assert s is not None and s.stretches >= kin.MIN_STRETCHES
    g, h = kin.kinematic_gain(1.0, s)
    assert abs(g - gain) < 0.005 and h < 0.01
    # named at its value it holds; named at nominal with a tight interval it is contradicted
    assert not kin.contradicts(gain, (gain - 0.01, gain + 0.01),
                               kin.gain_shift([_segment(_with(true, **{signal: gain}),
                                                        _with(true, **{signal: gain}))], signal))
    assert kin.contradicts(1.0, (0.99, 1.01), s)


def test_a_change_of_the_car_is_not_a_sensor_gain() -> None:
    # the measured car yaws 8 % more than the re-simulated one (a load, a rear toe): r and ay move together
    meas, pred = _drive(yaw_scale=1.08), _drive()
    s = kin.gain_shift([_segment(meas, pred)], "yaw_rate_radps")
    g, h = kin.kinematic_gain(1.0, s)
    assert abs(g - 1.0) < 0.005
    # a yaw-rate gain named for it (the re-simulation then holds the gain) is contradicted
    named = _with(pred, yaw_rate_radps=1.08)
    s = kin.gain_shift([_segment(meas, named)], "yaw_rate_radps")
    assert kin.contradicts(1.08, (1.06, 1.10), s)
    assert kin.kinematic_gain(1.08, s)[0] == pytest.approx(1.0, abs=0.01)


def test_too_few_straight_to_straight_stretches_give_no_verdict() -> None:
    true = _drive(corners=2)
    assert kin.gain_shift([_segment(true, true)], "yaw_rate_radps") is None
    # a stretch with a row not compared is not a stretch: every corner broken, none left
    many = _drive()
    valid = np.ones(len(many["t"]), bool)
    for k in range(6):
        valid[int((8.0 * k + 4.0) / 0.05)] = False
    assert kin.gain_shift([_segment(many, many, valid)], "yaw_rate_radps") is None
    assert kin.gain_shift([_segment(many, many)], "yaw_rate_radps") is not None


def _data(table: dict[str, np.ndarray]):
    from pathlib import Path

    from virtsensor.diagnose.identify import Data
    from virtsensor.recordings.measured import MeasuredRun, Segment

    run = MeasuredRun("r0", Path("r0.csv"), table, [Segment(0, len(table["time_s"]))])
    return Data([run], tuple(kin.TERMS))


def _fit(signal: str, estimate: float, ci95: tuple[float, float]):
    from virtsensor.diagnose.identify import Fit, candidates

    cand = next(c for c in candidates() if c.cause == "sensor_gain" and c.signal == signal)
    return Fit(cand, estimate, 0.0, 0.0, {}, ci95=ci95, significant=True)


def test_a_named_gain_the_kinematics_contradict_leaves_the_day_unexplained() -> None:
    from virtsensor.diagnose import identify as idn
    from virtsensor.diagnose.report import _cause_lines

    true = _drive()
    measured = {"time_s": true["t"], **{k: true[k] for k in kin.TERMS}}
    # the re-simulation of a yaw-rate gain of 1.04 named for a car that yaws more: the sensor reads true
    named = _fit("yaw_rate_radps", 1.04, (1.02, 1.06))
    data = _data(measured)
    sims = [[{"pred": _with(true, yaw_rate_radps=1.04)}]]
    idn._kinematic_check(data, named, sims)
    k = named.groups["kinematics"]
    assert not named.consistent and not k["agrees"] and abs(k["estimate"] - 1.0) < 0.005
    names = tuple(kin.TERMS)
    verdict = idn.Identification([named], named, {n: 1.0 for n in names}, dict(data.n), 1.0, sims, sims, 0, names,
                                 causes=[named], excess={n: 1.0 for n in names}, rss_best={n: 0.5 for n in names})
    why = idn._unexplained(data, verdict)
    assert why is not None and why["kinematics"] is k and not why["disagreeing_groups"], why
    line = _cause_lines({"cause": "unexplained", "unexplained": why})[0]
    assert "kinematics" in line and f"over {k['stretches']} straight-to-straight stretches" in line, line
    # the sensor does read 4 % high: the same named gain holds
    right = _fit("yaw_rate_radps", 1.04, (1.02, 1.06))
    gained = dict(measured, yaw_rate_radps=true["yaw_rate_radps"] * 1.04)
    idn._kinematic_check(_data(gained), right, sims)
    assert right.consistent and right.groups["kinematics"]["agrees"]
    from virtsensor.diagnose import _cause_entry

    entry = _cause_entry(right)
    assert entry["kinematics"] is right.groups["kinematics"]
    text = "\n".join(_cause_lines({"cause": "sensor_gain", "causes": [entry], "signature": {}}))
    assert "they agree" in text and f"{entry['kinematics']['stretches']} straight-to-straight" in text, text
    # a gain of another signal is not checked
    other = _fit("steer_angle_rad", 1.04, (1.02, 1.06))
    idn._kinematic_check(data, other, [[{"pred": true}]])
    assert other.consistent and "kinematics" not in other.groups
