"""Tests of sim.profiles: steering inputs and reference paths of the standard manoeuvres."""

from __future__ import annotations

import numpy as np
import pytest

from sim import profiles as pr

DEG = np.pi / 180.0


def grid(t_end: float, dt: float = 1e-3) -> np.ndarray:
    return np.arange(0.0, t_end + dt / 2, dt)


def durations_at(swa: np.ndarray, level: float, dt: float, tol: float = 1e-9) -> float:
    return float(np.count_nonzero(np.abs(swa - level) <= tol) * dt)


# ---------------------------------------------------------------------- sine with dwell
A = 120.0 * DEG
T0 = 1.0


def test_swd_timing_and_levels() -> None:
    dt = 1e-4
    t = grid(5.0, dt)
    swa = pr.sine_with_dwell(t, A, t0=T0)
    period = 1.0 / 0.7
    # 0.7 Hz: first peak +A at a quarter period, zero crossing at half, second peak at 3/4
    assert pr.sine_with_dwell(T0 + 0.25 * period, A) == pytest.approx(A)
    assert pr.sine_with_dwell(T0 + 0.5 * period, A) == pytest.approx(0.0, abs=1e-12)
    assert pr.sine_with_dwell(T0 + 0.75 * period, A) == pytest.approx(-A)
    # the dwell: 500 ms at -A starting at the second peak
    assert durations_at(swa, -A, dt, tol=1e-9 * A) == pytest.approx(0.5, abs=2 * dt)
    held = (t >= T0 + 0.75 * period) & (t <= T0 + 0.75 * period + 0.5)
    assert np.all(swa[held] == -A)
    assert swa.min() == -A and swa.max() == pytest.approx(A, rel=1e-6)
    # duration 1/0.7 + 0.5 s and zero outside
    end = T0 + period + 0.5
    assert pr.sine_with_dwell_duration() == pytest.approx(period + 0.5)
    assert np.all(swa[t < T0] == 0.0) and np.all(swa[t > end + 1e-9] == 0.0)
    nonzero = t[np.abs(swa) > 1e-6 * A]
    assert nonzero[0] == pytest.approx(T0, abs=2 * dt) and nonzero[-1] == pytest.approx(end, abs=2 * dt)
    # last quarter period returns from -A to 0 like a sine
    t_back = T0 + 0.75 * period + 0.5 + period / 8
    assert pr.sine_with_dwell(t_back, A) == pytest.approx(-A * np.sin(np.pi / 4))


def test_swd_continuous() -> None:
    dt = 1e-4
    swa = pr.sine_with_dwell(grid(4.0, dt), A)
    w = 2 * np.pi * 0.7
    assert np.max(np.abs(np.diff(swa))) <= A * w * dt * 1.001


def test_swd_direction_mirrors_exactly() -> None:
    t = grid(4.0)
    assert np.array_equal(pr.sine_with_dwell(t, A, direction=-1), -pr.sine_with_dwell(t, A, direction=1))
    with pytest.raises(ValueError):
        pr.sine_with_dwell(t, A, direction=0)


def test_swd_shape_follows_t() -> None:
    t = np.linspace(0.0, 4.0, 12).reshape(3, 4)
    assert pr.sine_with_dwell(t, A).shape == (3, 4)


# ---------------------------------------------------------------------- FMVSS 126 amplitude rule
def test_amplitude_rule_small_A_ends_at_270() -> None:
    a = 20.0 * DEG  # 6.5 A = 130 deg < 270 deg
    amps = pr.fmvss126_amplitudes(a)
    assert amps[0] == pytest.approx(1.5 * a)
    assert amps[-1] == pytest.approx(270.0 * DEG)
    steps = np.diff(amps)
    assert np.allclose(steps[:-1], 0.5 * a)
    assert 0.0 < steps[-1] <= 0.5 * a + 1e-12
    assert np.any(np.isclose(amps, 6.5 * a))  # passes through 6.5 A on the way


def test_amplitude_rule_mid_A_ends_at_6p5A() -> None:
    a = 45.0 * DEG  # 6.5 A = 292.5 deg: between 270 and 300
    amps = pr.fmvss126_amplitudes(a)
    assert amps[-1] == pytest.approx(6.5 * a)
    assert np.allclose(amps, a * np.arange(1.5, 6.51, 0.5))


def test_amplitude_rule_large_A_capped_at_300() -> None:
    a = 50.0 * DEG  # 6.5 A = 325 deg > 300 deg
    amps = pr.fmvss126_amplitudes(a)
    assert amps[-1] == pytest.approx(300.0 * DEG)
    assert np.all(amps <= 300.0 * DEG + 1e-12)
    assert amps[0] == pytest.approx(1.5 * a)
    assert np.allclose(np.diff(amps)[:-1], 0.5 * a)
    assert len(amps) == 10  # 75, 100, ..., 300 deg


def test_amplitude_rule_boundary() -> None:
    a = 300.0 / 6.5 * DEG  # 6.5 A exactly 300 deg
    assert pr.fmvss126_amplitudes(a)[-1] == pytest.approx(300.0 * DEG)
    with pytest.raises(ValueError):
        pr.fmvss126_amplitudes(0.0)


# ---------------------------------------------------------------------- SIS
def test_slowly_increasing_steer() -> None:
    t = grid(20.0, 0.01)
    swa = pr.slowly_increasing_steer(t, t0=T0)
    assert np.all(swa[t <= T0] == 0.0)
    rate = np.diff(swa[t > T0 + 0.1]) / 0.01
    assert np.allclose(rate, 13.5 * DEG)
    assert np.array_equal(pr.slowly_increasing_steer(t, direction=-1), -swa)
    capped = pr.slowly_increasing_steer(t, max_angle=90.0 * DEG)
    assert capped.max() == pytest.approx(90.0 * DEG) and capped[-1] == pytest.approx(90.0 * DEG)


def test_sis_amplitude_regression() -> None:
    g = pr.G_MPS2
    swa = np.deg2rad(np.linspace(0.0, 200.0, 2001))
    gain = 0.3 * g / (35.0 * DEG)  # 0.3 g at 35 deg in the linear range
    ay = gain * swa - 0.02 * g * np.clip(swa / DEG - 60.0, 0.0, None) ** 1.5 / 10.0  # saturates late
    ay = np.minimum(ay, 0.9 * g)
    a_fit = pr.sis_amplitude_from_ay(swa, ay)
    assert a_fit == pytest.approx(35.0 * DEG, rel=1e-6)
    # clockwise run: both signals negative, same A
    assert pr.sis_amplitude_from_ay(-swa, -ay) == pytest.approx(a_fit)
    # with sensor noise and an offset the regression still lands close
    rng = np.random.default_rng(1)
    noisy = ay + 0.01 * g * rng.standard_normal(ay.size) + 0.005 * g
    assert pr.sis_amplitude_from_ay(swa, noisy) == pytest.approx(35.0 * DEG, rel=0.03)
    with pytest.raises(ValueError):
        pr.sis_amplitude_from_ay(swa[:10], ay[:10])  # never reaches the window


# ---------------------------------------------------------------------- fishhook
def test_fishhook_ramps_levels_and_hold() -> None:
    dt = 1e-4
    amp = pr.fishhook_amplitude(30.0 * DEG)
    assert amp == pytest.approx(6.5 * 30.0 * DEG)
    t = grid(8.0, dt)
    swa = pr.fishhook(t, amp, t0=T0)
    rate = np.diff(swa) / dt
    ramp = np.abs(rate) > 1e-6
    assert np.allclose(np.abs(rate[ramp][np.abs(rate[ramp]) > 0.99 * 720 * DEG]), 720.0 * DEG)
    # every moving sample moves at 720 deg/s, except the ones straddling a corner
    assert np.count_nonzero(ramp & (np.abs(np.abs(rate) - 720 * DEG) > 1e-6)) <= 8
    assert swa.max() == pytest.approx(amp) and swa.min() == pytest.approx(-amp)
    assert durations_at(swa, amp, dt) == pytest.approx(0.25, abs=2 * dt)
    assert durations_at(swa, -amp, dt) == pytest.approx(3.0, abs=2 * dt)
    end = T0 + pr.fishhook_duration(amp)
    assert end == pytest.approx(T0 + 4 * amp / (720 * DEG) + 0.25 + 3.0)
    assert np.all(swa[t > end + 1e-9] == 0.0) and np.all(swa[t < T0] == 0.0)
    assert np.array_equal(pr.fishhook(t, amp, direction=-1), -pr.fishhook(t, amp))


# ---------------------------------------------------------------------- ISO 7401 inputs
def test_steering_pulse() -> None:
    t = grid(3.0)
    for shape in ("triangle", "half_sine"):
        swa = pr.steering_pulse(t, 40 * DEG, t0=T0, width=0.4, shape=shape)
        assert pr.steering_pulse(T0 + 0.2, 40 * DEG, width=0.4, shape=shape) == pytest.approx(40 * DEG)
        assert np.all(swa[(t < T0) | (t > T0 + 0.4)] == 0.0)
        assert np.max(np.abs(np.diff(swa))) < 40 * DEG * 8 * 1e-3  # continuous
    tri = pr.steering_pulse(t, 40 * DEG, width=0.4)
    assert np.trapezoid(tri, t) == pytest.approx(0.5 * 0.4 * 40 * DEG, rel=1e-3)


def test_single_sine() -> None:
    t = grid(4.0)
    swa = pr.single_sine(t, 30 * DEG, freq=0.5, t0=T0)
    assert pr.single_sine(T0 + 0.5, 30 * DEG) == pytest.approx(30 * DEG)
    assert pr.single_sine(T0 + 1.5, 30 * DEG) == pytest.approx(-30 * DEG)
    assert np.all(swa[(t < T0) | (t > T0 + 2.0)] == 0.0)
    assert np.trapezoid(swa, t) == pytest.approx(0.0, abs=1e-6)


def test_random_steer_reproducible_rms_and_band() -> None:
    fs = 100.0
    t = np.arange(0.0, 62.0, 1 / fs)
    kw = dict(amplitude_rms=20 * DEG, f_max=2.0, t0=1.0, duration=60.0)
    a = pr.random_steer(t, seed=7, **kw)
    b = pr.random_steer(t, seed=7, **kw)
    c = pr.random_steer(t, seed=8, **kw)
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)
    window = (t >= 1.0) & (t <= 61.0)
    assert np.sqrt(np.mean(a[window] ** 2)) == pytest.approx(20 * DEG, rel=0.01)
    assert np.all(a[~window] == 0.0)
    # with the fades, energy outside the band only within ~1/fade Hz of its edges
    spec = np.abs(np.fft.rfft(a)) ** 2
    f = np.fft.rfftfreq(a.size, 1 / fs)
    assert spec[f > 2.0 * 1.1].sum() < 1e-3 * spec.sum()
    assert spec[f > 2.0 * 1.25].sum() < 1e-5 * spec.sum()
    assert spec[(f > 1.5) & (f <= 2.0)].sum() > 0.05 * spec.sum()  # the band is used up to f_max
    assert spec[f < 0.08].sum() < 1e-2 * spec.sum()  # and starts near 0.1 Hz
    # a pure function of t: any sampling gives the same values; any shape
    sub = t[::37]
    assert np.allclose(pr.random_steer(sub, seed=7, **kw), a[::37])
    assert pr.random_steer(sub[:60].reshape(6, 10), seed=7, **kw).shape == (6, 10)
    # fades to zero at both ends, continuously
    assert abs(pr.random_steer(1.0 + 1e-3, seed=7, **kw)) < 1e-3 * 20 * DEG
    # continuous; Bernstein's bound |da/dt| <= 2 pi f_max max|a| for a band-limited signal
    assert np.max(np.abs(np.diff(a))) <= 1.2 * 2 * np.pi * 2.0 * np.max(np.abs(a)) / fs


def test_random_steer_has_no_energy_above_f_max() -> None:
    """Without fades the signal is periodic over ``duration``: one period's FFT is exactly band-limited."""
    fs, duration = 50.0, 40.0
    t = 3.0 + np.arange(0.0, duration, 1 / fs)  # exactly one period from t0 = 3 s
    a = pr.random_steer(t, 0.2, seed=3, f_max=1.5, t0=3.0, duration=duration, fade=0.0)
    spec = np.abs(np.fft.rfft(a)) ** 2
    f = np.fft.rfftfreq(a.size, 1 / fs)
    assert spec[f > 1.5 + 1e-9].sum() < 1e-20 * spec.sum()
    assert spec[f < 0.1 - 1e-9].sum() < 1e-20 * spec.sum()
    assert np.sqrt(np.mean(a**2)) == pytest.approx(0.2, rel=1e-6)


def test_swept_sine() -> None:
    dt = 1e-3
    t = grid(35.0, dt)
    swa = pr.swept_sine(t, 10 * DEG, f0=0.2, f1=2.0, duration=30.0, t0=T0)
    end = T0 + pr.swept_sine_end(0.2, 2.0, 30.0)
    assert end <= T0 + 30.0 + 1e-9
    assert np.all(swa[(t < T0) | (t > end + 1e-9)] == 0.0)
    assert abs(pr.swept_sine(end - 1e-6, 10 * DEG, duration=30.0, t0=T0)) < 1e-4 * 10 * DEG  # ends at zero
    assert np.max(np.abs(np.diff(swa))) <= 10 * DEG * 2 * np.pi * 2.0 * dt * 1.01  # continuous
    # frequency rises: zero crossings get closer, from ~1/(2 f0) to ~1/(2 f1)
    zc = t[1:][np.sign(swa[1:]) != np.sign(swa[:-1])]
    zc = zc[(zc > T0 + 0.01) & (zc < end - 0.01)]
    gaps = np.diff(zc)
    assert np.all(np.diff(gaps) < 1e-3)
    f_measured = 1.0 / (2.0 * gaps)
    f_expected = 0.2 + (2.0 - 0.2) * (0.5 * (zc[1:] + zc[:-1]) - T0) / 30.0
    assert np.allclose(f_measured, f_expected, rtol=0.02)
    assert f_measured[0] < 0.4 and f_measured[-1] > 1.9


# ---------------------------------------------------------------------- ISO 3888-1
def test_dlc_gates_dimensions() -> None:
    w = 1.8
    entry, side, exit_ = pr.double_lane_change_gates(w)
    edges = (entry.x_start, entry.x_end, side.x_start, side.x_end, exit_.x_start, exit_.x_end)
    assert edges == (0.0, 15.0, 45.0, 70.0, 95.0, 110.0)
    assert entry.y_left - entry.y_right == pytest.approx(1.1 * w + 0.25)
    assert side.y_left - side.y_right == pytest.approx(1.2 * w + 0.25)
    assert exit_.y_left - exit_.y_right == pytest.approx(1.3 * w + 0.25)
    centre = [0.5 * (g.y_left + g.y_right) for g in (entry, side, exit_)]
    assert centre[1] - centre[0] == pytest.approx(3.5)
    assert exit_.y_right == pytest.approx(entry.y_right)  # outer cone line shared


@pytest.mark.parametrize("direction", [1, -1])
def test_dlc_path_stays_inside_the_gates(direction: int) -> None:
    w, length = 1.8, 4.5  # car width and length (m)
    x = np.arange(-20.0, 140.0, 0.01)
    y = pr.double_lane_change_path(x, w, direction=direction)
    psi = np.arctan(np.gradient(y, x))
    half_extent = 0.5 * w * np.cos(psi) + 0.5 * length * np.abs(np.sin(psi))
    for gate in pr.double_lane_change_gates(w, direction=direction):
        inside = (x >= gate.x_start) & (x <= gate.x_end)
        clearance_left = gate.y_left - (y[inside] + half_extent[inside])
        clearance_right = (y[inside] - half_extent[inside]) - gate.y_right
        assert min(clearance_left.min(), clearance_right.min()) >= 0.2  # margin for a 1.8 m car
        centre = 0.5 * (gate.y_left + gate.y_right)
        assert np.allclose(y[inside], centre)  # through the middle of every gate


def test_dlc_path_smooth() -> None:
    dx = 1e-3
    x = np.arange(-10.0, 130.0, dx)
    y = pr.double_lane_change_path(x)
    slope = np.diff(y) / dx
    assert np.max(np.abs(np.diff(slope))) < 1e-4  # C1: no slope jumps
    curv = np.diff(slope) / dx
    assert np.max(np.abs(np.diff(curv))) < 1e-4  # C2: no curvature jumps
    # peak curvature of the quintic blend: 5.77 * offset / length^2 (back: 3.5 - 0.1 w over 25 m)
    assert np.max(np.abs(curv)) == pytest.approx(5.7735 * (3.5 - 0.18) / 25.0**2, rel=0.01)
    assert y[0] == 0.0 and y[-1] == pytest.approx(0.1 * 1.8)


def test_dlc_direction_mirrors_exactly() -> None:
    x = np.linspace(-5.0, 130.0, 1000)
    assert np.array_equal(
        pr.double_lane_change_path(x, direction=-1), -pr.double_lane_change_path(x, direction=1)
    )


# ---------------------------------------------------------------------- ISO 4138
@pytest.mark.parametrize("direction", [1, -1])
def test_circle_path(direction: int) -> None:
    r, lead = 40.0, 30.0
    p = pr.circle_path(r, 2.0, ds=0.5, direction=direction, lead_in=lead)
    assert p.x[0] == 0.0 and p.y[0] == 0.0 and p.heading[0] == 0.0
    assert p.s[-1] == pytest.approx(lead + 2 * 2 * np.pi * r)
    assert np.allclose(np.diff(p.s), np.diff(p.s)[0])
    circle = p.s > lead
    dist = np.hypot(p.x[circle] - lead, p.y[circle] - direction * r)
    assert np.allclose(dist, r)
    assert np.all(p.y[~circle] == 0.0)
    # heading matches the direction of travel and turns counter-clockwise for +1
    chord = np.arctan2(np.diff(p.y), np.diff(p.x))
    mid = 0.5 * (p.heading[1:] + p.heading[:-1])
    assert np.max(np.abs(np.angle(np.exp(1j * (chord - mid))))) < 1e-3
    assert p.heading[-1] == pytest.approx(direction * 4 * np.pi)
    assert np.all(direction * np.diff(p.heading) >= 0)
    assert np.allclose(p.curvature[circle], direction / r) and np.all(p.curvature[~circle] == 0.0)
    # joins tangentially: position and heading continuous at the lead-in end
    assert np.max(np.hypot(np.diff(p.x), np.diff(p.y))) <= 0.5 + 1e-9


def test_circle_direction_mirrors_exactly() -> None:
    a, b = pr.circle_path(50.0, 1.0, direction=1), pr.circle_path(50.0, 1.0, direction=-1)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.y, -b.y) and np.array_equal(a.heading, -b.heading)
