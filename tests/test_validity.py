"""The daemon's input-validity contract as pure functions (:mod:`virtsensor.daemon.validity`) and the clock
mapping of drained frames (:class:`virtsensor.daemon.receive.ClockMap`): no threads, no bus, no model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from virtsensor.daemon.receive import CONFIRM_S, ClockMap
from virtsensor.daemon.validity import (
    DEGRADED,
    INVALID,
    VALID,
    FrameOrder,
    Plausibility,
    PlausibilityRule,
    ValidityRules,
    ValidityState,
    assess_inputs,
    wheel_status,
)

# three signals: 0 critical (message 0, history 2), 1 non-critical (message 1), 2 critical (message 1)
RULES = ValidityRules(sig_msg=(0, 1, 1), sig_timeout=(0.03, 0.06, 0.06), sig_hist=(2, 0, 0),
                      critical=(True, False, True), sig_bit=(1, 2, 2), msg_timeout=(0.03, 0.06),
                      bitmap_msgs=((0, 1), (1, 2)))
T = 100.0


def _assess(times, flags=(False,) * 3, last_ok=None, err=(False, False), in_order=(True, True), state=None,
            t=T):
    state = state or ValidityState(3)
    last_ok = list(last_ok) if last_ok is not None else [times[0], max(times[1], times[2])]
    return (*assess_inputs(t, list(times), list(flags), last_ok, list(err), list(in_order), RULES, state), state)


def test_fresh_inputs_are_valid_with_every_bit():
    status, bitmap, st = _assess([T - 0.01, T - 0.05, T])
    assert status == VALID and bitmap == 3 and not any(st.stale) and not any(st.bad)


@pytest.mark.parametrize("age", [0.0, 0.0299])
def test_ages_from_zero_to_the_timeout_are_fresh(age):
    assert _assess([T - age, T, T])[0] == VALID


@pytest.mark.parametrize("stamp", [T + 1e-6, T + 10.0, T - 0.0301, -math.inf, math.nan])
def test_future_stale_never_seen_or_nan_critical_input_is_invalid(stamp):
    """An age below 0 (stamped after the tick) is as unusable as one beyond the timeout."""
    status, bitmap, st = _assess([stamp, T, T], last_ok=[stamp, T])
    assert status == INVALID and st.stale[0] and not bitmap & 1 and bitmap & 2


def test_non_critical_bad_input_degrades_and_clears_its_message_bit():
    status, bitmap, st = _assess([T, T - 0.07, T], last_ok=[T, T])
    assert status == DEGRADED and st.bad == [False, True, False]
    assert bitmap == 1  # message 1 delivered, but one of its inputs is stale: its bit is cleared


def test_sna_flag_and_e2e_error_make_inputs_bad():
    assert _assess([T, T, T], flags=(False, True, False))[0] == DEGRADED
    assert _assess([T, T, T], flags=(True, False, False))[0] == INVALID
    status, bitmap, st = _assess([T, T, T], err=(False, True))
    assert status == INVALID and bitmap == 1 and st.bad == [False, True, True] and not any(st.stale)


def test_out_of_order_message_is_not_fresh():
    status, bitmap, st = _assess([T, T, T], in_order=(False, True))
    assert status == INVALID and st.stale[0] and bitmap == 2


def test_recovery_lasts_the_signals_history():
    st = ValidityState(3)
    assert _assess([T - 1.0, T, T], state=st)[0] == INVALID  # stale
    seen = [_assess([T + k * 0.05, T + k * 0.05, T + k * 0.05], state=st, t=T + k * 0.05)[0] for k in range(1, 5)]
    assert seen == [INVALID, INVALID, VALID, VALID]  # history 2: two fresh ticks still bad


def test_wheel_status():
    assert wheel_status(VALID, 10.0, -300, 300) == VALID
    assert wheel_status(DEGRADED, 10.0, -300, 300) == DEGRADED
    assert wheel_status(VALID, 301.0, -300, 300) == INVALID
    assert wheel_status(VALID, math.nan, -300, 300) == INVALID
    assert wheel_status(INVALID, 10.0, -300, 300) == INVALID


# ------------------------------------------------------------------------------------------------ frame order
def test_time_step_back_holds_the_message_out_of_order_for_the_window():
    fo = FrameOrder([0.01], timeout_cycles=3)
    for k in range(5):
        assert not fo.frame(0, 1.0 + 0.01 * k)
    assert fo.tick(1.05) == 0 and fo.in_order == [True]
    assert fo.frame(0, 1.035)  # behind the previous frame (1.04)
    fo.tick(1.05)
    assert fo.in_order == [False]
    for k, t in enumerate((1.045, 1.055, 1.065)):
        assert not fo.frame(0, t)
        fo.tick(t + 0.001)
        assert fo.in_order == [k == 2]  # in order again once frames ran 3 cycles (30 ms) past the step


def test_future_stamped_frame_is_counted_once_and_silence_keeps_it_out_of_order():
    fo = FrameOrder([0.01, 0.02], timeout_cycles=3)
    fo.frame(0, 1.0)
    fo.frame(1, 1.0)
    fo.frame(0, 11.0)  # 10 s ahead
    assert fo.tick(1.05) == 1 and fo.in_order == [False, True]
    assert fo.tick(1.10) == 0 and fo.in_order == [False, True]  # silence: still out of order, not recounted
    assert fo.tick(11.0) == 0 and fo.in_order == [False, True]  # the clock reaching it does not help
    assert fo.frame(0, 1.11)  # frames resume on the true time base: a step back
    for t in (1.12, 1.13, 1.14):
        fo.frame(0, t)
    fo.tick(1.15)
    assert fo.in_order == [True, True]


def test_slightly_ahead_frame_within_one_cycle_is_in_order():
    fo = FrameOrder([0.01], timeout_cycles=3)
    fo.frame(0, 1.0)
    fo.frame(0, 1.059)  # 9 ms after the tick at 1.05: within one cycle
    assert fo.tick(1.05) == 0 and fo.in_order == [True]


# ------------------------------------------------------------------------------------------------ clock map
def test_clock_map_takes_the_tightest_bound_and_ignores_a_backlog():
    cm = ClockMap(window=4)
    assert cm.offset == math.inf
    for d in (5.0002, 5.0001, 5.0003):
        cm.push(d)
    assert cm.offset == pytest.approx(5.0001)
    cm.push(5.3)  # a backlog: read 300 ms after its stamps; the offset keeps the earlier, tighter bound
    assert cm.offset == pytest.approx(5.0001)


def test_clock_map_follows_a_time_base_step_after_its_window():
    cm = ClockMap(window=3)
    cm.push(5.0)
    for _ in range(3):
        assert cm.offset == pytest.approx(5.0)
        cm.push(15.0)  # the interface's clock stepped back by 10 s
    assert cm.offset == pytest.approx(15.0)


def test_clock_map_is_confirmed_by_two_consecutive_drains_that_agree():
    cm = ClockMap(window=4)
    assert cm.confirmed  # (nothing mapped yet)
    cm.push(4.5)  # the first drain: a backlog or live frames, no telling
    assert not cm.confirmed
    cm.push(4.3)  # the next drain read 0.2 s of stamps in one tick: a backlog being read out
    assert not cm.confirmed
    cm.idle()  # a drain without frames breaks the streak
    cm.push(0.003)
    assert not cm.confirmed
    cm.push(0.004 + CONFIRM_S * 0.9)  # live frames at two drains in a row
    assert cm.confirmed
    cm.push(9.0)
    cm.idle()
    assert cm.confirmed  # (for good)


# ------------------------------------------------------------------------------------------------ plausibility
_VX_RULE = PlausibilityRule("vx_vs_wheels", subject=0, refs=(1, 2), scale=0.3, tol_abs=1.5, tol_rel=0.15, debounce=3)


def test_plausibility_fails_after_the_debounce_and_clears_after_it():
    p = Plausibility([_VX_RULE], 3)
    good, bad = [20.0, 66.0, 68.0], [89.0, 63.0, 64.0]  # 0.3 * mean(wheels) = 20.1 / 19.05 m/s
    assert p.update(good) == 0 and p.implausible == [False] * 3
    assert [p.update(bad) for _ in range(3)] == [0, 0, 1]  # fails on the third tick in a row, counted once
    assert p.failing == [True] and p.implausible == [True, False, False] and p.new == [True]
    assert p.update(bad) == 0 and p.new == [False]
    p.update(good)
    p.update(bad)  # one bad tick in between restarts the count
    p.update(good)
    p.update(good)
    assert p.implausible[0]
    p.update(good)
    assert p.implausible == [False] * 3 and p.failing == [False]


def test_plausibility_tolerance_and_unknown_values():
    p = Plausibility([_VX_RULE], 3)
    for _ in range(5):  # 15 % + 1.5 m/s of 30 m/s: 6 m/s allowed; never-received (NaN) inputs pass
        assert p.update([30.0, 80.0, 80.0]) == 0 and p.update([30.0, math.nan, 80.0]) == 0
    assert not p.failing[0]


def test_implausible_input_is_bad_not_stale():
    st = ValidityState(3)
    status, bitmap = assess_inputs(T, [T] * 3, [False] * 3, [T, T], [False, False], [True, True], RULES, st,
                                   implausible=[False, True, False])
    assert status == DEGRADED and st.bad == [False, True, False] and not any(st.stale) and bitmap == 1
    status, _ = assess_inputs(T, [T] * 3, [False] * 3, [T, T], [False, False], [True, True], RULES, st,
                              implausible=[True, False, False])
    assert status == INVALID
    assert assess_inputs(T, [T] * 3, [False] * 3, [T, T], [False, False], [True, True], RULES, st)[0] == VALID


# the catalogue's checks as the daemon builds them, on the 12 inputs in catalogue order
def _catalogue_rules():
    from virtsensor import signals as cat
    from virtsensor.daemon.layout import plausibility_rules

    return cat, {r.name: r for r in plausibility_rules(cat.INPUTS)}


def _row(cat, **values) -> list[float]:
    base = dict(ax_mps2=0.2, ay_mps2=0.0, vx_mps=20.0, yaw_rate_radps=0.0, steer_angle_rad=0.0, steer_torque_nm=0.0,
                assist_torque_nm=0.0, motor_torque_nm=15.0, susp_defl_fl_m=0.0, susp_defl_fr_m=0.0,
                wheel_speed_fl_radps=20.0 / cat.ROLLING_RADIUS_M, wheel_speed_fr_radps=20.0 / cat.ROLLING_RADIUS_M)
    base.update(values)
    return [base[n] for n in cat.INPUTS]


def _steady_turn(cat, ay: float, vx: float = 20.0, r: float = 0.2) -> list[float]:
    """A steady left turn with grip: yaw rate r at speed vx, the steering a little above the kinematic angle."""
    steer = 1.2 * r * cat.STEADY_TURN.steer_ratio * cat.STEADY_TURN.wheelbase_m / vx
    return _row(cat, ay_mps2=ay, vx_mps=vx, yaw_rate_radps=r, steer_angle_rad=steer)


def test_lateral_acceleration_against_yaw_rate_times_speed_in_a_steady_turn():
    cat, rules = _catalogue_rules()
    rule = rules["ay_vs_yaw_rate_times_speed"]
    p = Plausibility([rule], 12)
    i_ay = cat.INPUTS.index("ay_mps2")
    for _ in range(40):  # r vx = 4 m/s^2; body roll adds some 8 %: plausible
        assert p.update(_steady_turn(cat, ay=4.3)) == 0
    n = [p.update(_steady_turn(cat, ay=0.0)) for _ in range(rule.debounce)]  # ay stuck at 0 in the turn
    assert n == [0] * (rule.debounce - 1) + [1] and p.implausible[i_ay]
    for _ in range(rule.debounce):
        p.update(_steady_turn(cat, ay=4.0))
    assert not p.implausible[i_ay]


def _lifted(rule, gate: str):
    """``rule`` without one of its gates, so that a row it leaves unjudged is judged."""
    from dataclasses import replace

    if gate == "steady":
        return replace(rule, steady=())
    if gate == "within":
        return replace(rule, within=())
    if gate == "max_expected":
        return replace(rule, max_expected=math.inf)
    if gate == "min_expected":
        return replace(rule, min_expected=0.0)
    if gate == "turn_lo":
        return replace(rule, turn=(*rule.turn[:5], 0.0, rule.turn[6]))
    assert gate == "turn"
    return replace(rule, turn=None)


def _verdicts(rule, rows) -> tuple[bool, bool]:
    """Whether the rule, and the same rule without the gate the rows are for, end implausible on ``rows``."""
    out = []
    for r in rule:
        p = Plausibility([r], 12)
        for row in rows:
            p.update(row)
        out.append(any(p.implausible))
    return out[0], out[1]


@pytest.mark.parametrize("why", ["steering moves", "slide: yaw rate far below the steering's", "straight ahead",
                                 "spin: r vx beyond any road's grip"])
def test_lateral_acceleration_check_is_not_judged_outside_steady_turns_with_grip(why):
    """Each row disagrees beyond the tolerance, so only its gate keeps the check from failing: without that gate
    the same rows fail it."""
    cat, rules = _catalogue_rules()
    rule = rules["ay_vs_yaw_rate_times_speed"]
    rows = []
    for k in range(100):
        row = _steady_turn(cat, ay=0.0)
        if why == "steering moves":
            row[cat.INPUTS.index("steer_angle_rad")] += 0.05 * (k % 2)  # 1 rad/s back and forth
            gate = "steady"
        elif why.startswith("slide"):
            row[cat.INPUTS.index("yaw_rate_radps")] = 0.07  # 0.42 of the steering's kinematic yaw rate; r vx = 1.4
            gate = "turn_lo"
        elif why.startswith("spin"):  # r vx = 12 m/s^2 (and the steering's kinematic yaw rate) with ay at 6
            row = _steady_turn(cat, ay=6.0, r=0.6)
            gate = "max_expected"
        else:
            row = _row(cat, ay_mps2=-2.6, yaw_rate_radps=0.0)  # sliding sideways with the wheels straight
            gate = "turn"
        rows.append(row)
    assert _verdicts((rule, _lifted(rule, gate)), rows) == (False, True)


@pytest.mark.parametrize("name", ["assist_vs_boosted_steer_torque", "assist_vs_boost_above_3nm"])
def test_assist_torque_against_the_boost_curve(name):
    cat, rules = _catalogue_rules()
    rule = rules[name]
    p = Plausibility([rule], 12)
    i_as = cat.INPUTS.index("assist_torque_nm")
    gain_at_15 = cat.EPAS_BOOST.gains[cat.EPAS_BOOST.speeds_mps.index(15.0)]
    boosted = gain_at_15 * 3.0 * 3.0 / (3.0 + cat.EPAS_BOOST.knee_nm)  # 3 Nm on the torsion bar at 15 m/s: 9 Nm
    for _ in range(30):
        assert p.update(_row(cat, vx_mps=15.0, steer_torque_nm=3.0, assist_torque_nm=boosted + 1.5)) == 0
        assert p.update(_row(cat, vx_mps=15.0, steer_torque_nm=-30.0, assist_torque_nm=-60.0)) == 0  # the limit
    for _ in range(rule.debounce):  # the assist pushes the wrong way
        p.update(_row(cat, vx_mps=15.0, steer_torque_nm=3.0, assist_torque_nm=-boosted))
    assert p.implausible[i_as] and p.failing == [True]
    # the same wrong torques where the check is not judged, each for longer than its debounce; without the
    # gate each is for, the same rows fail it
    moving = [_row(cat, vx_mps=15.0, steer_torque_nm=3.0, assist_torque_nm=-boosted, steer_angle_rad=0.05 * (k % 2))
              for k in range(60)]  # the wheel turning fast (EPAS damping, back-EMF): 1 rad/s back and forth
    assert _verdicts((rule, _lifted(rule, "steady")), moving) == (False, True)
    locked = [_row(cat, vx_mps=15.0, steer_torque_nm=3.0, assist_torque_nm=-boosted, ax_mps2=-7.0)] * 30
    assert _verdicts((rule, _lifted(rule, "within")), locked) == (False, True)  # locked wheels: vx reads low
    if rule.min_expected > 0:  # below 3 Nm of boost a gain is invisible: that variant does not judge it
        small = [_row(cat, vx_mps=15.0, steer_torque_nm=0.3, assist_torque_nm=5.0)] * 30
        assert _verdicts((rule, _lifted(rule, "min_expected")), small) == (False, True)


def test_vehicle_speed_check_is_not_judged_while_a_wheel_can_spin_or_lock():
    """Driven wheels spinning (motor torque above 30 Nm) and wheels locked (braking harder than 1 m/s^2), each
    steady for longer than the debounce, disagree with vx beyond the tolerance: not judged, but the same rows
    fail the check without its ``within`` gate."""
    cat, rules = _catalogue_rules()
    rule = rules["vx_vs_front_wheel_speed"]
    spin = 52.0 / cat.ROLLING_RADIUS_M  # the driven wheels spinning on ice, no traction control
    spinning = [_row(cat, vx_mps=11.6, motor_torque_nm=57.0, ax_mps2=1.0, wheel_speed_fl_radps=spin,
                     wheel_speed_fr_radps=spin)] * 50
    locked = [_row(cat, vx_mps=11.6, ax_mps2=-2.0, wheel_speed_fl_radps=0.0, wheel_speed_fr_radps=0.0)] * 50
    for rows in (spinning, locked):
        assert _verdicts((rule, _lifted(rule, "within")), rows) == (False, True)
    p = Plausibility([rule], 12)
    for row in spinning:
        assert p.update(row) == 0
    for _ in range(4):  # cruising with the same disagreement: judged (once the wheel speeds are steady again)
        p.update(_row(cat, vx_mps=11.6, wheel_speed_fl_radps=spin, wheel_speed_fr_radps=spin))
    assert p.implausible[cat.INPUTS.index("vx_mps")]


def test_the_catalogue_car_facts_are_the_simulated_car_s():
    """The boost curve, steering ratio and wheelbase the checks assume are those the simulator drives with."""
    from pathlib import Path

    import tomllib

    from virtsensor import signals as cat

    car = tomllib.loads((Path(__file__).resolve().parents[1] / "sim/data/car_c_segment.toml").read_text())
    st = car["steering"]
    assert cat.EPAS_BOOST.speeds_mps == tuple(st["assist_speeds_mps"])
    assert cat.EPAS_BOOST.gains == tuple(st["assist_gains"])
    assert (cat.EPAS_BOOST.knee_nm, cat.EPAS_BOOST.max_nm) == (st["assist_knee_nm"], st["assist_max_nm"])
    assert (cat.STEADY_TURN.steer_ratio, cat.STEADY_TURN.wheelbase_m) == (st["ratio"], car["vehicle"]["wheelbase_m"])


def _reference_update(rules, state, values, stale, prev):
    """The checks' semantics as written in PlausibilityRule's docstring, interpreted rule by rule (an oracle for
    the generated code; ``judge`` interprets one tick). ``state`` = (failing, run, window rings); returns (newly
    failed, new, implausible)."""
    from virtsensor.daemon.validity import judge

    failing, run, rings = state
    new, n_new = [False] * len(rules), 0
    for k, r in enumerate(rules):
        judged, residual, tolerance = judge(r, values, prev, stale)
        if r.window:
            if not judged:
                continue
            rings[k].append(residual > tolerance)  # (a NaN residual passes)
            del rings[k][:-r.window]
            run[k] = sum(rings[k])
            if failing[k] and len(rings[k]) - run[k] + (r.window - len(rings[k])) >= r.debounce:
                failing[k] = False
            elif not failing[k] and run[k] >= r.debounce:
                failing[k] = new[k] = True
                n_new += 1
            continue
        if not judged:
            run[k] = 0
            continue
        ok = not residual > tolerance
        if ok == failing[k]:
            run[k] += 1
            if run[k] >= r.debounce:
                failing[k], new[k], run[k] = not ok, not ok, 0
                n_new += not ok
        else:
            run[k] = 0
    imp = [any(failing[k] for k, r in enumerate(rules) if i in (r.subject, r.minus)) for i in range(len(values))]
    return n_new, new, imp


def test_generated_checks_match_the_rules_semantics_on_random_sequences():
    from virtsensor.daemon.validity import _boost

    cat, names, by_name = _check_rows()
    rules = list(by_name.values())
    assert {r.relation for r in rules} == {"mean", "product", "ratio", "boost", "difference"}
    assert any(r.turn for r in rules)
    assert any(r.above for r in rules) and any(r.window for r in rules) and any(r.minus >= 0 for r in rules)
    assert any(r.tol_per for r in rules) and any(r.min_expected > 0 for r in rules)
    rng = np.random.default_rng(15)
    p = Plausibility(rules, len(names))
    state = ([False] * len(rules), [0] * len(rules), [[] for _ in rules])
    prev = [math.nan] * len(names)
    turn = by_name["ay_vs_yaw_rate_times_speed"].turn
    yaw = turn[3] * 20.0 * 0.2  # a steady turn at the kinematic yaw rate
    boost = _boost(by_name["assist_vs_boosted_steer_torque"].boost, 2.0, 20.0)
    base = np.array(_full_row(cat, names, yaw=yaw, vx=20.0, steer_angle_rad=0.2, steer_torque_nm=2.0,
                              assist_torque_nm=boost))
    straight = np.array(_full_row(cat, names, yaw=0.0, vx=20.0, steer_torque_nm=2.0, assist_torque_nm=boost))
    broken_by_stretch = (("vx_mps", 8.0), ("ay_mps2", 4.0), ("assist_torque_nm", 10.0), ("steer_angle_rad", 0.6),
                         ("yaw_rate_radps", 0.5), ("susp_defl_fl_m", 0.05))
    failed = [0] * len(rules)
    for tick in range(400 * len(broken_by_stretch) * 2):
        # steady driving with small noise (turning, or straight in one stretch in six); stretches where one
        # redundancy breaks, some unsteady ticks, NaNs, stale signals
        phase, stretch = tick % 400, (tick // 400) % len(broken_by_stretch)
        row = (straight if stretch == 3 else base) * (1.0 + rng.normal(0.0, 0.005, len(base)))
        if 100 <= phase < 200:
            broken, by = broken_by_stretch[stretch]
            row[names.index(broken)] += by
        if rng.random() < 0.02:
            row[rng.integers(len(row))] *= 3.0
        if rng.random() < 0.01:
            row[rng.integers(len(row))] = math.nan
        values = [float(x) for x in row]
        stale = [bool(s) for s in rng.random(len(values)) < 0.01]
        got = p.update(values, stale)
        want, new, imp = _reference_update(rules, state, values, stale, prev)
        prev = values
        assert (got, p.new, p.implausible, p.failing, p._run) == (want, new, imp, state[0], state[1]), tick
        failed = [a + b for a, b in zip(failed, p.new, strict=True)]
    assert all(failed), failed  # the sequence made every check fail


# ------------------------------------------------------------------------------ windowed debounce, check references
def test_windowed_debounce_counts_failures_over_judged_ticks_and_ignores_unjudged_ones():
    """8 of the last 10 judged ticks: an unjudged tick (the steadiness gate) neither counts nor restarts, so
    failures scattered through transient driving reach the verdict; a consecutive count never would."""
    windowed = PlausibilityRule("w", subject=0, refs=(1,), scale=1.0, tol_abs=1.0, tol_rel=0.0, debounce=8,
                                window=10, steady=((2, 0.1),))
    consecutive = PlausibilityRule("c", subject=0, refs=(1,), scale=1.0, tol_abs=1.0, tol_rel=0.0, debounce=8,
                                   steady=((2, 0.1),))
    p, q = Plausibility([windowed], 3), Plausibility([consecutive], 3)
    seen = []
    for k in range(15):  # the gate signal steps every second tick: failing ticks judged and unjudged in turn
        row = [5.0, 0.0, float((k // 2) % 2)]
        q.update(row)
        seen.append(p.update(row))
    assert seen.count(1) == 0 and not p.failing[0]  # 7 judged failures (ticks 1, 3, ..., 13)
    q.update([5.0, 0.0, 1.0])
    assert p.update([5.0, 0.0, 1.0]) == 1 and p.failing == [True] and p.implausible == [True, False, False]
    assert not q.failing[0]  # the consecutive count restarted at every unjudged tick
    for _ in range(5):  # passing judged ticks: cleared once 8 of the last 10 passed
        p.update([0.5, 0.0, 1.0])
    assert p.failing == [True]
    for _ in range(3):
        p.update([0.5, 0.0, 1.0])
    assert p.failing == [False]


def _check_rows():
    """The catalogue's checks on the 12 inputs and the check references (the daemon's decoded signals)."""
    from virtsensor import signals as cat
    from virtsensor.canbus.codec import CanMatrix
    from virtsensor.daemon.layout import check_references, plausibility_rules

    names = cat.INPUTS + check_references(cat.INPUTS, CanMatrix.load())
    return cat, names, {r.name: r for r in plausibility_rules(names)}


def _full_row(cat, names, yaw=0.1, vx=15.0, ax=0.2, roll=0.0, **values) -> list[float]:
    """A steady turn at yaw rate ``yaw`` (rad/s) and ``vx`` (m/s), the rear wheels rolling apart by the yaw rate
    and the body rolled by ``roll`` (rad), every catalogue check holding."""
    w = vx / cat.ROLLING_RADIUS_M
    half = yaw * cat.TRACK_REAR_M / 2.0 / cat.ROLLING_RADIUS_M
    base = dict(ax_mps2=ax, ay_mps2=yaw * vx, vx_mps=vx, yaw_rate_radps=yaw, steer_angle_rad=0.0,
                steer_torque_nm=0.0, assist_torque_nm=0.0, motor_torque_nm=15.0,
                susp_defl_fl_m=-roll * cat.TRACK_FRONT_M / 2, susp_defl_fr_m=roll * cat.TRACK_FRONT_M / 2,
                wheel_speed_fl_radps=w, wheel_speed_fr_radps=w, wheel_speed_rl_radps=w - half,
                wheel_speed_rr_radps=w + half, susp_defl_rl_m=-roll * cat.TRACK_REAR_M / 2,
                susp_defl_rr_m=roll * cat.TRACK_REAR_M / 2)
    base.update(values)
    return [base[n] for n in names]


def test_yaw_rate_against_the_rear_wheel_speeds():
    cat, names, rules = _check_rows()
    rule = rules["yaw_rate_vs_rear_wheel_speeds"]
    i_yaw = names.index("yaw_rate_radps")
    p = Plausibility([rule], len(names))
    fast = Plausibility([rule], len(names))
    for _ in range(40):  # the rear wheels and the IMU agree; a rear tyre 1 % smaller still agrees at 30 m/s
        assert p.update(_full_row(cat, names, yaw=0.12)) == 0
        assert fast.update(_full_row(cat, names, yaw=0.12, vx=30.0,
                                     wheel_speed_rl_radps=30.0 / cat.ROLLING_RADIUS_M * 1.0099)) == 0
    for _ in range(rule.debounce + 1):  # the IMU's yaw rate 0.3 rad/s off at 15 m/s (its step is not judged)
        p.update(_full_row(cat, names, yaw=0.12, yaw_rate_radps=0.42))
    assert p.implausible[i_yaw] and p.failing == [True]
    q = Plausibility([rule], len(names))
    stale = [n in ("wheel_speed_rl_radps", "wheel_speed_rr_radps") for n in names]
    for _ in range(50):  # the same 0.3 rad/s while braking hard (rear wheels slip apart), cornering at 6 m/s^2, or
        # with the rear wheel speeds stale: not judged
        q.update(_full_row(cat, names, yaw=0.12, yaw_rate_radps=0.42, ax=-3.0))
        q.update(_full_row(cat, names, yaw=0.4, yaw_rate_radps=0.7))
        q.update(_full_row(cat, names, yaw=0.12, yaw_rate_radps=0.42), stale)
    assert not any(q.implausible)


def test_front_roll_against_rear_roll_marks_both_front_deflections():
    cat, names, rules = _check_rows()
    rule = rules["front_roll_vs_rear_roll"]
    p = Plausibility([rule], len(names))
    i_fl, i_fr = names.index("susp_defl_fl_m"), names.index("susp_defl_fr_m")
    for k in range(40):  # a rigid body rolling up to 0.05 rad
        assert p.update(_full_row(cat, names, roll=0.05 * math.sin(k / 5))) == 0
    for _ in range(rule.debounce):  # the front-left sensor 20 mm off
        p.update(_full_row(cat, names, roll=0.01, susp_defl_fl_m=-0.01 * cat.TRACK_FRONT_M / 2 + 0.02))
    assert p.implausible[i_fl] and p.implausible[i_fr] and p.failing == [True]
    q = Plausibility([rule], len(names))
    for _ in range(50):  # a car at walking pace with a wheel on a kerb: not judged
        q.update(_full_row(cat, names, vx=3.0, susp_defl_fl_m=0.05))
    assert not any(q.implausible)


def test_a_stale_check_reference_never_changes_the_status_and_clears_only_its_own_message_bit():
    """Signals 0-2 are the model's (as RULES); 3 is a check reference in message 1 (which carries model inputs),
    4 one in message 2 (its own message, health bit 4)."""
    rules = ValidityRules(sig_msg=(0, 1, 1, 1, 2), sig_timeout=(0.03, 0.06, 0.06, 0.06, 0.06), sig_hist=(2, 0, 0),
                          critical=(True, False, True), sig_bit=(1, 2, 2, 0, 4), msg_timeout=(0.03, 0.06, 0.06),
                          bitmap_msgs=((0, 1), (1, 2), (2, 4)))
    st = ValidityState(5)
    status, bitmap = assess_inputs(T, [T] * 5, [False] * 5, [T, T, T], [False] * 3, [True] * 3, rules, st)
    assert status == VALID and bitmap == 7 and not any(st.bad)
    status, bitmap = assess_inputs(T, [T, T, T, T, -math.inf], [False, False, False, True, False],
                                   [T, T, -math.inf], [False] * 3, [True] * 3, rules, st)
    assert status == VALID and st.stale == [False, False, False, True, True] and bitmap == 3
    status, _ = assess_inputs(T, [T] * 5, [False] * 5, [T, T, T], [False, False, True], [True] * 3, rules, st)
    assert status == VALID and st.bad[4] and not st.stale[4]  # an E2E error: bad, not stale


def test_the_catalogue_tracks_are_the_simulated_car_s():
    from pathlib import Path

    import tomllib

    from virtsensor import signals as cat

    car = tomllib.loads((Path(__file__).resolve().parents[1] / "sim/data/car_c_segment.toml").read_text())
    assert (cat.TRACK_FRONT_M, cat.TRACK_REAR_M) == (car["vehicle"]["track_front_m"], car["vehicle"]["track_rear_m"])


def test_a_check_is_not_judged_while_a_signal_of_its_conditions_is_stale():
    """A steering angle held while its sensor reports out of range reads as a wheel at rest: the assist checks,
    whose condition it is, wait for it (seen in the fault soak: a held angle tripped the assist check)."""
    cat, rules = _catalogue_rules()
    rule = rules["assist_vs_boost_above_3nm"]
    p = Plausibility([rule], 12)
    stale = [n == "steer_angle_rad" for n in cat.INPUTS]
    for _ in range(30):  # the assist far off the boost curve, the steering angle stale
        assert p.update(_row(cat, vx_mps=15.0, steer_torque_nm=3.0, assist_torque_nm=-9.0), stale) == 0
    assert not p.failing[0]
    assert sum(p.update(_row(cat, vx_mps=15.0, steer_torque_nm=3.0, assist_torque_nm=-9.0))
               for _ in range(rule.debounce)) == 1  # the same, the angle fresh: judged
