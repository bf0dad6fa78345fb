"""The kinematic check of a named motion-sensor gain (virtsensor.diagnose.kinematics), on synthetic drives whose
physics is known: ay = dvy/dt + r vx + g sin(roll)."""

from __future__ import annotations

import numpy as np
import pytest

from virtsensor.diagnose import kinematics as kin

G = 9.80665


def _drive(yaw_scale: float = 1.0, speed_scale: float = 1.0, corners: int = 6, seed: int = 0
           ) -> dict[str, np.ndarray]:
    """True signals of a drive at 20 Hz: corners (half-sine yaw-rate pulses of alternating sign) between
    straights, a lateral velocity that swells in each corner and is 0 on the straights, roll from ay. The same
    steering at ``speed_scale`` times the speed follows the same path: the yaw rate scales with the speed."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, corners * 8.0, 0.05)
    vx = speed_scale * (20.0 + 2.0 * np.sin(2 * np.pi * t / 37.0))
    r = np.zeros_like(t)
    vy = np.zeros_like(t)
    for k in range(corners):
        t0, dur = 8.0 * k + 2.0, rng.uniform(3.0, 5.0)
        inside = (t >= t0) & (t <= t0 + dur)
        shape = np.sin(np.pi * (t[inside] - t0) / dur)
        amp = (-1) ** k * rng.uniform(0.15, 0.35) * yaw_scale * speed_scale
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


def _resimulated(true: dict[str, np.ndarray], signal: str, named: float, gain: float) -> dict[str, np.ndarray]:
    """The re-simulation of a car whose ``signal`` sensor reads ``gain`` times true, with the gain ``named``. The
    speed drives it: the re-simulated car runs at the measured speed over the named gain (another speed, so its own
    yaw rate), and reads it back times ``named``."""
    if signal != "vx_mps":
        return _with(true, **{signal: named})
    return _with(_drive(speed_scale=gain / named), vx_mps=named)


@pytest.mark.parametrize("signal,gain", [("yaw_rate_radps", 1.05), ("yaw_rate_radps", 0.93), ("ay_mps2", 0.9),
                                         ("vx_mps", 1.08), ("vx_mps", 0.92)])
@pytest.mark.parametrize("named_as", [1.0, 1.2, "truth"])
def test_a_sensor_gain_is_measured_by_the_kinematics(signal: str, gain: float, named_as) -> None:
    named = gain if named_as == "truth" else named_as
    true = _drive()
    k = kin.measure([_segment(_with(true, **{signal: gain}), _resimulated(true, signal, named, gain))], signal,
                    named)
    assert k is not None and k.stretches >= kin.MIN_STRETCHES and k.half_width < 0.015
    if signal != "vx_mps" or named == gain:
        assert abs(k.gain - gain) < 0.002, (k.gain, gain)  # whatever gain the re-simulation holds
        # named at the truth with an interval around it, it holds; named at nominal with a tight interval, not
        assert not kin.contradicts((gain - 0.01, gain + 0.02), k)
        assert kin.contradicts((0.99, 1.01), k)
    else:  # the speed drives the re-simulation: off the truth by a share of the simulated gain's own error
        assert 0.002 < abs(k.gain - gain) < 0.35 * abs(named - gain), (k.gain, gain, named)


def test_a_change_of_the_car_is_not_a_sensor_gain() -> None:
    # the measured car yaws 8 % more than the re-simulated one (a load, a rear toe): r and ay move together;
    # a yaw-rate gain named for it (the re-simulation then holds the gain) is contradicted
    meas, pred = _drive(yaw_scale=1.08), _drive()
    k = kin.measure([_segment(meas, _with(pred, yaw_rate_radps=1.08))], "yaw_rate_radps", 1.08)
    assert abs(k.gain - 1.0) < 0.005, k
    assert kin.contradicts((1.06, 1.10), k)
    assert kin.measure([_segment(meas, pred)], "yaw_rate_radps", 1.0).gain == pytest.approx(1.0, abs=0.005)


def test_no_verdict_without_enough_stretches_or_a_finite_interval() -> None:
    true = _drive(corners=2)
    assert kin.measure([_segment(true, true)], "yaw_rate_radps", 1.0) is None
    # a stretch with a row not compared is not a stretch: every corner broken, none left
    many = _drive()
    valid = np.ones(len(many["t"]), bool)
    for k in range(6):
        valid[int((8.0 * k + 4.0) / 0.05)] = False
    assert kin.measure([_segment(many, many, valid)], "yaw_rate_radps", 1.0) is None
    k = kin.measure([_segment(many, many)], "yaw_rate_radps", 1.0)
    assert k is not None and k.stretches == 6
    # a named gain without a finite interval gets no verdict, nor does a gain simulated as nan
    assert not kin.contradicts((float("nan"), 1.01), kin.Kinematic(1.2, 0.01, 5))
    assert kin.measure([_segment(many, many)], "yaw_rate_radps", float("nan")) is None


def _data(table: dict[str, np.ndarray]):
    from pathlib import Path

    from virtsensor.diagnose.identify import Data
    from virtsensor.recordings.measured import MeasuredRun, Segment

    run = MeasuredRun("r0", Path("r0.csv"), table, [Segment(0, len(table["time_s"]))])
    return Data([run], tuple(kin.TERMS))


def _fit(signal: str, estimate: float, ci95: tuple[float, float], sim_value: float | None = None):
    from virtsensor.diagnose.identify import Fit, candidates

    cand = next(c for c in candidates() if c.cause == "sensor_gain" and c.signal == signal)
    return Fit(cand, estimate, 0.0, 0.0, {}, ci95=ci95, significant=True, sim_value=sim_value)


def test_a_named_gain_the_kinematics_contradict_leaves_the_day_unexplained() -> None:
    from virtsensor.diagnose import _cause_entry
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
    assert not named.consistent and not k["agrees"] and abs(k["estimate"] - 1.0) < 0.002
    names = tuple(kin.TERMS)
    verdict = idn.Identification([named], named, {n: 1.0 for n in names}, dict(data.n), 1.0, sims, sims, 0, names,
                                 causes=[named], excess={n: 1.0 for n in names}, rss_best={n: 0.5 for n in names})
    why = idn._unexplained(data, verdict)
    assert why is not None and why["kinematics"] is k and not why["disagreeing_groups"], why
    line = _cause_lines({"cause": "unexplained", "unexplained": why})[0]
    assert "kinematics" in line and f"over {k['stretches']} straight-to-straight stretches" in line, line
    # the sensor does read 4 % high: the same named gain holds, and the report gives the kinematic value
    right = _fit("yaw_rate_radps", 1.04, (1.02, 1.06))
    gained = dict(measured, yaw_rate_radps=true["yaw_rate_radps"] * 1.04)
    idn._kinematic_check(_data(gained), right, sims)
    assert right.consistent and right.groups["kinematics"]["agrees"]
    entry = _cause_entry(right)
    assert entry["kinematics"] is right.groups["kinematics"]
    text = "\n".join(_cause_lines({"cause": "sensor_gain", "causes": [entry], "signature": {}}))
    assert "they agree" in text and f"{entry['kinematics']['stretches']} straight-to-straight" in text, text
    # a gain of another signal is not checked
    other = _fit("steer_angle_rad", 1.04, (1.02, 1.06))
    idn._kinematic_check(data, other, [[{"pred": true}]])
    assert other.consistent and "kinematics" not in other.groups


def test_the_check_reads_the_gain_the_re_simulation_holds_and_skips_rows_not_finite() -> None:
    from virtsensor.diagnose import identify as idn

    # a speed gain of 1.10, searched by re-simulation: the re-simulation stands at 1.20, the estimate 1.19
    true = _drive()
    measured = {"time_s": true["t"], **_with({k: true[k] for k in kin.TERMS}, vx_mps=1.10)}
    pred = _resimulated(true, "vx_mps", 1.20, 1.10)
    pred["ay_mps2"] = pred["ay_mps2"].copy()
    pred["ay_mps2"][int(4.0 / 0.05)] = np.nan  # (a row the re-simulation left undefined, in the first corner)
    f = _fit("vx_mps", 1.19, (1.15, 1.23), sim_value=1.20)
    idn._kinematic_check(_data(measured), f, [[{"pred": pred}]])
    k = f.groups["kinematics"]
    # read at the simulated 1.20 (not at the estimate), one corner fewer; the check at 1.19 would differ
    valid = np.isfinite(pred["ay_mps2"])
    at = {g: kin.measure([_segment({"t": true["t"], **{n: measured[n] for n in kin.TERMS}}, pred, valid)],
                         "vx_mps", g) for g in (1.20, 1.19)}
    assert k["estimate"] == at[1.20].gain != at[1.19].gain and k["stretches"] == 5, (k, at)
    assert abs(k["estimate"] - 1.10) < 0.35 * 0.10 and f.consistent == k["agrees"]
