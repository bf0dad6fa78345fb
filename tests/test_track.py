"""Tests of sim.track: the bundled Magny-Cours centreline and the lap speed profile."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim import track as track_mod
from sim.track import Track, lap_time, load_magny_cours, speed_profile

STATED_LENGTH_M = 4412.0
G = 9.81


@pytest.fixture(scope="module")
def trk() -> Track:
    return load_magny_cours()


# ---------------------------------------------------------------------- the bundled file
def test_csv_is_bundled_in_the_package_with_provenance() -> None:
    csv = Path(track_mod.__file__).parent / "data" / track_mod.MAGNY_COURS_CSV
    text = csv.read_text(encoding="utf-8")
    assert "bacinger/f1-circuits" in text and "MIT" in text and "tools/derive_track.py" in text
    first_data_line = next(ln for ln in text.splitlines() if not ln.startswith("#"))
    assert first_data_line == "s_m,x_m,y_m,heading_rad,curvature_1pm"


def test_length_close_to_stated(trk: Track) -> None:
    assert abs(trk.length / STATED_LENGTH_M - 1.0) < 0.015
    assert trk.s[0] == 0.0 and trk.s[-1] == pytest.approx(trk.length)


def test_sampled_every_2_m(trk: Track) -> None:
    ds = np.diff(trk.s)
    assert np.allclose(ds, ds[0], atol=2e-4)
    assert ds[0] == pytest.approx(2.0, abs=0.01)


def test_closed_in_position_and_heading(trk: Track) -> None:
    assert np.hypot(trk.x[-1] - trk.x[0], trk.y[-1] - trk.y[0]) < 1e-3
    turn = trk.heading[-1] - trk.heading[0]
    assert turn == pytest.approx(-2.0 * np.pi, abs=1e-6)
    # the join is smooth: the last step and the first step look like any other step
    step_in = np.hypot(trk.x[-1] - trk.x[-2], trk.y[-1] - trk.y[-2])
    step_out = np.hypot(trk.x[1] - trk.x[0], trk.y[1] - trk.y[0])
    assert step_in == pytest.approx(step_out, rel=1e-3)
    assert trk.curvature[-1] == pytest.approx(trk.curvature[0], abs=1e-6)


def test_runs_clockwise(trk: Track) -> None:
    area = 0.5 * np.sum(trk.x[:-1] * trk.y[1:] - trk.x[1:] * trk.y[:-1])
    assert area < -1e5  # clockwise seen from above (z up)
    assert trk.turn_per_lap == pytest.approx(-2 * np.pi, abs=1e-6)
    assert np.trapezoid(trk.curvature, trk.s) == pytest.approx(-2 * np.pi, abs=1e-3)


def test_starts_on_the_start_finish_straight(trk: Track) -> None:
    near = trk.s < 150.0
    assert np.all(np.abs(trk.curvature[near]) < 0.002)  # R > 500 m
    near_end = trk.s > trk.length - 100.0
    assert np.all(np.abs(trk.curvature[near_end]) < 0.002)


def test_heading_continuous_and_consistent_with_curvature(trk: Track) -> None:
    dh = np.diff(trk.heading)
    assert np.max(np.abs(dh)) < 0.25
    ds = np.diff(trk.s)
    k_mid = 0.5 * (trk.curvature[1:] + trk.curvature[:-1])
    assert np.max(np.abs(dh / ds - k_mid)) < 2e-3
    # heading is the direction of travel
    chord = np.arctan2(np.diff(trk.y), np.diff(trk.x))
    mid_heading = 0.5 * (trk.heading[1:] + trk.heading[:-1])
    assert np.max(np.abs(np.angle(np.exp(1j * (chord - mid_heading))))) < 5e-3


def test_curvature_extremes_plausible(trk: Track) -> None:
    """The tightest corner is the Adelaide hairpin, a right-hander turning ~155 deg.

    The GeoJSON draws it with vertices whose circumradii are 12-15 m and legs ~26 m
    apart; the smoothed centreline's minimum radius is ~10 m (not the 15-30 m one
    might expect from the real circuit: the trace itself is that tight).
    """
    i = int(np.argmin(trk.curvature))
    r_min = 1.0 / abs(trk.curvature[i])
    assert 8.0 < r_min < 30.0
    assert np.max(np.abs(trk.curvature)) == pytest.approx(abs(trk.curvature[i]))  # a right-hander
    window = np.abs(trk.s - trk.s[i]) <= 40.0
    turn = trk.heading[window][-1] - trk.heading[window][0]
    assert np.deg2rad(-175.0) < turn < np.deg2rad(-135.0)  # hairpin
    # every other corner is gentler than 8 m and left turns stay above 12 m
    assert np.all(np.abs(trk.curvature) < 1.0 / 8.0)
    assert 1.0 / trk.curvature.max() > 12.0
    # most of the lap is straight-ish
    assert np.mean(np.abs(trk.curvature) < 1.0 / 200.0) > 0.5


# ---------------------------------------------------------------------- Track methods
def test_at_reproduces_samples_and_wraps(trk: Track) -> None:
    p = trk.at(trk.s)
    assert np.allclose(p.x, trk.x) and np.allclose(p.y, trk.y)
    assert np.allclose(p.heading, trk.heading) and np.allclose(p.curvature, trk.curvature)
    s = np.array([[0.0, 123.4], [2000.0, 4000.5]])
    q0, q1 = trk.at(s), trk.at(s + 2 * trk.length)
    assert q1.x.shape == s.shape
    assert np.allclose(q0.x, q1.x) and np.allclose(q0.y, q1.y)
    assert np.allclose(q1.heading - q0.heading, 2 * trk.turn_per_lap)
    qn = trk.at(-1.0)  # just before the start: end of the previous lap
    assert float(qn.x) == pytest.approx(float(trk.at(trk.length - 1.0).x))


def test_at_midpoints_lie_on_the_arc(trk: Track) -> None:
    mid = 0.5 * (trk.s[1:] + trk.s[:-1])
    q = trk.at(mid)
    # distance from each chord end equals half the step, within the chord/arc difference
    d0 = np.hypot(q.x - trk.x[:-1], q.y - trk.y[:-1])
    assert np.allclose(d0, 0.5 * np.diff(trk.s), atol=2e-3)


def test_laps(trk: Track) -> None:
    t3 = trk.laps(3)
    assert t3.length == pytest.approx(3 * trk.length)
    assert len(t3.s) == 3 * (len(trk.s) - 1) + 1
    assert np.all(np.diff(t3.s) > 0)
    assert np.max(np.abs(np.diff(t3.heading))) < 0.25
    assert t3.heading[-1] - t3.heading[0] == pytest.approx(3 * trk.turn_per_lap)
    s = np.linspace(0.0, trk.length, 777)
    a, b = trk.at(s), t3.at(s + trk.length)
    assert np.allclose(a.x, b.x) and np.allclose(a.curvature, b.curvature)
    assert np.allclose(b.heading - a.heading, trk.turn_per_lap)
    with pytest.raises(ValueError):
        trk.laps(0)


def test_aligned_to_start(trk: Track) -> None:
    a = trk.aligned_to_start()
    assert a.x[0] == pytest.approx(0.0) and a.y[0] == pytest.approx(0.0) and a.heading[0] == 0.0
    assert np.allclose(np.hypot(np.diff(a.x), np.diff(a.y)), np.hypot(np.diff(trk.x), np.diff(trk.y)))
    assert np.allclose(a.curvature, trk.curvature)


def test_track_is_immutable(trk: Track) -> None:
    with pytest.raises(ValueError):
        trk.x[0] = 1.0
    with pytest.raises(AttributeError):
        trk.length = 1.0  # type: ignore[misc]


def test_track_validation() -> None:
    s = np.array([0.0, 1.0, 2.0])
    with pytest.raises(ValueError):
        Track(s, s, s, s, s, 3.0)  # length does not match the closing sample
    with pytest.raises(ValueError):
        Track(s[::-1], s, s, s, s, 2.0)


# ---------------------------------------------------------------------- speed profile
V_MAX = 50.0


@pytest.fixture(scope="module")
def profiles(trk: Track) -> dict[float, np.ndarray]:
    return {mu: speed_profile(trk, trk.s, mu, v_max_mps=V_MAX) for mu in (1.0, 0.7)}


@pytest.mark.parametrize("mu", [1.0, 0.7])
def test_speed_never_exceeds_cornering_limit(trk: Track, profiles, mu: float) -> None:
    v = profiles[mu]
    with np.errstate(divide="ignore"):
        v_corner = np.sqrt(0.85 * mu * G / np.abs(trk.curvature))
    assert np.all(v <= np.minimum(v_corner, V_MAX) * (1 + 1e-12))
    assert np.all(v > 0)
    if mu == 1.0:
        assert np.any(v >= V_MAX - 1e-9)  # the longest straights reach the cap
    assert np.any(v <= v_corner * (1 + 1e-9))  # and the limit binds in corners
    assert v.min() == pytest.approx(np.sqrt(0.85 * mu * G / np.abs(trk.curvature).max()), rel=0.02)


@pytest.mark.parametrize("mu", [1.0, 0.7])
def test_speed_respects_accel_and_brake_limits(trk: Track, profiles, mu: float) -> None:
    v = profiles[mu]
    ax = np.diff(v**2) / (2 * np.diff(trk.s))  # dv/ds * v
    assert ax.max() <= 3.0 + 1e-9
    assert ax.min() >= -0.8 * mu * G - 1e-9
    assert ax.max() > 2.5 and ax.min() < -0.7 * 0.8 * mu * G  # both limits are used
    # friction ellipse: where accelerating, the lateral use leaves room for it
    ay = v[:-1] ** 2 * np.abs(trk.curvature[:-1])
    room = np.sqrt(np.clip(1 - (ay / (0.85 * mu * G)) ** 2, 0, None))
    assert np.all(ax <= 3.0 * room + 1e-9)


def test_lower_friction_is_slower_where_the_limit_binds(profiles) -> None:
    v10, v07 = profiles[1.0], profiles[0.7]
    assert np.all(v07 <= v10 + 1e-9)
    binding = v10 < V_MAX - 1e-6
    assert binding.mean() > 0.3
    assert np.all(v07[binding] < v10[binding])


def test_lap_times(trk: Track, profiles) -> None:
    t10, t07 = lap_time(trk.s, profiles[1.0]), lap_time(trk.s, profiles[0.7])
    assert 120.0 < t10 < 200.0
    assert t07 > t10 * 1.08


def test_friction_array_dry_then_wet(trk: Track) -> None:
    two = trk.laps(2)
    mu = np.where(two.s < trk.length, 1.0, 0.7)
    v = speed_profile(two, two.s, mu, v_max_mps=V_MAX)
    dry = speed_profile(two, two.s, 1.0, v_max_mps=V_MAX)
    wet = speed_profile(two, two.s, 0.7, v_max_mps=V_MAX)
    lap1, lap2 = two.s < trk.length - 300.0, two.s > trk.length
    assert np.allclose(v[lap1], dry[lap1])  # far from the change it is the dry profile
    with np.errstate(divide="ignore"):
        v_corner_wet = np.sqrt(0.85 * 0.7 * G / np.abs(two.curvature))
    assert np.all(v[lap2] <= v_corner_wet[lap2] * (1 + 1e-12))  # wet limits from the change on
    late = two.s > trk.length + 1000.0  # past the first wet corner it is the wet profile
    assert np.allclose(v[late], wet[late])
    assert np.all(v <= dry + 1e-9)
    assert lap_time(two.s[lap2], v[lap2]) > lap_time(two.s[lap1], v[lap1])
    ax = np.diff(v**2) / (2 * np.diff(two.s))
    mu_seg = np.minimum(mu[1:], mu[:-1])
    assert np.all(ax >= -0.8 * mu_seg * G - 1e-9)


def test_curvature_input_and_boundary_speeds(trk: Track) -> None:
    v_a = speed_profile(trk, trk.s, 1.0, v_max_mps=V_MAX)
    v_b = speed_profile(trk.curvature, trk.s, 1.0, v_max_mps=V_MAX)
    assert np.allclose(v_a, v_b)
    v = speed_profile(trk, trk.s, 1.0, v_max_mps=V_MAX, v_start_mps=0.0, v_end_mps=0.0)
    assert v[0] == 0.0 and v[-1] == 0.0
    assert np.diff(v**2)[0] / (2 * (trk.s[1] - trk.s[0])) <= 3.0 + 1e-9
    with pytest.raises(ValueError):
        speed_profile(trk.curvature[:-1], trk.s, 1.0, v_max_mps=V_MAX)
    with pytest.raises(ValueError):
        speed_profile(trk, trk.s[::-1], 1.0, v_max_mps=V_MAX)


def test_braking_across_a_friction_change() -> None:
    """Braking for a corner that starts on a wet patch: each step obeys the lower friction."""
    s = np.arange(0.0, 400.0, 2.0)
    kappa = np.where(s >= 300.0, 1.0 / 30.0, 0.0)
    mu = np.where(s < 251.0, 1.0, 0.5)  # changes between s = 250 and 252, inside the braking zone
    v = speed_profile(kappa, s, mu, v_max_mps=45.0, v_start_mps=45.0)
    ax = np.diff(v**2) / (2 * np.diff(s))
    mu_seg = np.minimum(mu[1:], mu[:-1])
    assert np.all(ax >= -0.8 * mu_seg * G - 1e-9)
    assert ax[s[:-1] < 250.0].min() < -0.8 * 0.5 * G * 1.5  # braking harder on the dry part
    assert v[s >= 300.0].max() <= np.sqrt(0.85 * 0.5 * G * 30.0) + 1e-9
