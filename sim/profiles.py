"""Steering-wheel-angle (SWA) profiles and reference paths of standard manoeuvres.

Every profile is a pure, vectorised function of a time array ``t`` (s, any
shape) and plain parameters; it returns the SWA in rad with the shape of
``t`` (ISO 8855: positive = counter-clockwise = steering to the left), zero
before the manoeuvre starts at ``t0`` and after it ends. Paths are arrays in
m in an earth-fixed frame (x forward at the start, y to the left). Angles are
rad in code; constants named ``*_DEG`` hold degrees, as the standards state
them.

What was checked against the standards' text, and what was not (the ISO
documents themselves were not available):

* FMVSS 126 (49 CFR 571.126) sine with dwell and slowly increasing steer: the
  0.7 Hz sine, the 500 ms dwell beginning at the second peak, the two series
  (counter-clockwise and clockwise first half cycle), the 13.5 deg/s SIS rate
  at 80 km/h up to about 0.5 g, "A" from linear regression at 0.3 g, and the
  amplitude rule (1.5A first run, +0.5A per run, final run the greater of 6.5A
  or 270 deg provided 6.5A <= 300 deg, else 300 deg) were read in the ACEA
  English translation of China's GB/T ESC standard, sections 7.6-7.7, whose
  wording reproduces FMVSS 126 S7.6 and S7.9. The CFR text itself (S7.9.3 /
  S7.9.4) was not reachable, so the section numbers are from memory.
* NHTSA fishhook (NCAP Fishhook Maneuver Test Procedure): the amplitude is the
  SIS angle at 0.3 g times a "steering scalar" whose default is 6.5 (read in
  the procedure's text). The 720 deg/s handwheel rate, the 3 s hold and the
  roll-rate-triggered dwell are as commonly described; not re-read here.
* ISO 3888-1 double lane change: the section lengths (15, 30, 25, 25, 15 m),
  lane widths (1.1w + 0.25, 1.2w + 0.25, 1.3w + 0.25 m) and the 3.5 m offset
  agree in several independent public implementations; how the 3.5 m is
  measured differs between them (see :func:`double_lane_change_gates`).
* ISO 7401 (open-loop lateral transient response): its inputs (step, one
  period of sine, random, pulse, continuous sine) were confirmed from its table
  of contents only; widths and frequency ranges are the values used in
  practice, given as parameters.
* ISO 4138 (steady-state circular driving): constant-radius method; the radius
  is a parameter.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "steering_pulse",
    "single_sine",
    "random_steer",
    "swept_sine",
    "swept_sine_end",
    "slowly_increasing_steer",
    "sis_amplitude_from_ay",
    "sine_with_dwell",
    "sine_with_dwell_duration",
    "fmvss126_amplitudes",
    "fishhook",
    "fishhook_amplitude",
    "fishhook_duration",
    "double_lane_change_path",
    "double_lane_change_gates",
    "Gate",
    "circle_path",
    "PathArrays",
]

G_MPS2 = 9.80665  # standard gravity used to express "g" levels

# FMVSS 126
SWD_FREQ_HZ = 0.7
SWD_DWELL_S = 0.5
SIS_RATE_DEG_S = 13.5
SIS_SPEED_KPH = 80.0
SWD_FIRST_FACTOR = 1.5
SWD_STEP_FACTOR = 0.5
SWD_FINAL_FACTOR = 6.5
SWD_FINAL_MIN_DEG = 270.0
SWD_CAP_DEG = 300.0

# NHTSA fishhook
FISHHOOK_RATE_DEG_S = 720.0
FISHHOOK_SCALAR = 6.5

# ISO 3888-1
DLC_SECTION_LENGTHS_M = (15.0, 30.0, 25.0, 25.0, 15.0)
DLC_OFFSET_M = 3.5


def _as_t(t: ArrayLike) -> np.ndarray:
    return np.asarray(t, dtype=float)


def _direction(direction: int) -> float:
    if direction not in (1, -1):
        raise ValueError("direction must be +1 (left first) or -1 (right first)")
    return float(direction)


def _smoothstep5(u: np.ndarray) -> np.ndarray:
    """Quintic 0 -> 1 blend on [0, 1] with zero 1st and 2nd derivatives at both ends (C2)."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


# ---------------------------------------------------------------------- ISO 7401
def steering_pulse(
    t: ArrayLike,
    amplitude: float,
    t0: float = 1.0,
    width: float = 0.4,
    shape: Literal["triangle", "half_sine"] = "triangle",
) -> np.ndarray:
    """ISO 7401 pulse input: a single short steering pulse, returned to zero.

    Args:
        t: time (s).
        amplitude: peak SWA (rad); negative for a pulse to the right.
        t0: start of the pulse (s).
        width: total duration of the pulse (s); ISO 7401 practice is 0.3-0.5 s.
        shape: ``"triangle"`` (default: linear rise to the peak at ``t0 + width/2`` and
            linear return, the shape a steering robot produces) or ``"half_sine"``.

    Returns:
        SWA (rad), shape of ``t``; zero outside ``[t0, t0 + width]``.
    """
    if width <= 0.0:
        raise ValueError("width must be positive")
    u = (_as_t(t) - t0) / width
    inside = (u >= 0.0) & (u <= 1.0)
    if shape == "triangle":
        form = 1.0 - np.abs(2.0 * u - 1.0)
    elif shape == "half_sine":
        form = np.sin(np.pi * u)
    else:
        raise ValueError("shape must be 'triangle' or 'half_sine'")
    return np.where(inside, amplitude * form, 0.0)


def single_sine(t: ArrayLike, amplitude: float, freq: float = 0.5, t0: float = 1.0) -> np.ndarray:
    """ISO 7401 "sinusoidal input - one period" (ISO/TR 8725): one full sine period.

    ``SWA = amplitude * sin(2 pi freq (t - t0))`` for ``t0 <= t <= t0 + 1/freq``, else 0.
    A positive amplitude steers left first.

    Args:
        t: time (s).
        amplitude: SWA amplitude (rad).
        freq: frequency (Hz); 0.5 Hz is the usual choice.
        t0: start (s).
    """
    if freq <= 0.0:
        raise ValueError("freq must be positive")
    tau = _as_t(t) - t0
    inside = (tau >= 0.0) & (tau <= 1.0 / freq)
    return np.where(inside, amplitude * np.sin(2.0 * np.pi * freq * tau), 0.0)


def random_steer(
    t: ArrayLike,
    amplitude_rms: float,
    seed: int,
    f_max: float = 2.0,
    t0: float = 1.0,
    *,
    duration: float = 60.0,
    f_min: float = 0.1,
    fade: float = 2.0,
) -> np.ndarray:
    """ISO 7401 random steering input, band-limited and reproducible.

    The signal is a realisation of band-limited Gaussian noise: a sum of sines at
    the frequencies ``f_k = k / duration`` inside ``[f_min, f_max]`` (Hz) with
    complex-Gaussian (Rayleigh amplitude, uniform phase) coefficients drawn from
    ``numpy.random.default_rng(seed)``; it is periodic with period ``duration``, so
    it is a pure function of ``t`` for any sampling. It is faded in over ``fade``
    seconds after ``t0`` and out over the last ``fade`` seconds before
    ``t0 + duration`` (raised-cosine ramps) and is zero outside that window. The
    fades add spectral content only within ~1/fade Hz of the band.

    Args:
        t: time (s).
        amplitude_rms: RMS of the SWA over the whole window ``[t0, t0 + duration]``,
            fades included (rad).
        seed: random seed; the same seed gives the same signal.
        f_max: upper band limit (Hz); ISO 7401 asks for content up to at least 2 Hz.
        t0: start (s).
        duration: length of the manoeuvre (s).
        f_min: lower band limit (Hz).
        fade: length of each fade ramp (s).

    Returns:
        SWA (rad), shape of ``t``.
    """
    if not 0.0 < f_min < f_max or duration <= 0.0 or not 0.0 <= 2.0 * fade <= duration:
        raise ValueError("need 0 < f_min < f_max, duration > 0 and 0 <= 2*fade <= duration")
    rng = np.random.default_rng(seed)
    k = np.arange(int(np.ceil(f_min * duration)), int(np.floor(f_max * duration)) + 1)
    if k.size == 0:
        raise ValueError("no frequency of the grid k/duration lies in [f_min, f_max]")
    freqs = k / duration
    coef = rng.standard_normal(k.size) + 1j * rng.standard_normal(k.size)

    def raw(tau: np.ndarray) -> np.ndarray:
        phase = np.exp(2j * np.pi * np.multiply.outer(tau, freqs))
        signal = (phase @ coef).real
        if fade > 0.0:
            ramp_in = 0.5 - 0.5 * np.cos(np.pi * np.clip(tau / fade, 0.0, 1.0))
            ramp_out = 0.5 - 0.5 * np.cos(np.pi * np.clip((duration - tau) / fade, 0.0, 1.0))
            signal = signal * ramp_in * ramp_out
        return signal

    # Scale so the RMS over the window is amplitude_rms: the signal is band-limited
    # to f_max, so a grid at 20 f_max samples it far above Nyquist.
    n_grid = int(np.ceil(duration * 20.0 * f_max)) + 1
    grid = np.linspace(0.0, duration, n_grid)
    ref = raw(grid) ** 2
    rms = np.sqrt(np.sum(0.5 * (ref[1:] + ref[:-1]) * np.diff(grid)) / duration)
    tau = _as_t(t) - t0
    inside = (tau >= 0.0) & (tau <= duration)
    out = np.zeros(tau.shape)
    active = tau[inside]
    values = np.empty(active.shape)
    chunk = 8192  # bounds the (samples x frequencies) work array; not a per-sample loop
    for start in range(0, active.size, chunk):
        values[start : start + chunk] = raw(active[start : start + chunk])
    out[inside] = values * (amplitude_rms / rms)
    return out


def swept_sine_end(f0: float, f1: float, duration: float) -> float:
    """Length (s) of :func:`swept_sine`: the last zero crossing of the sweep at or before ``duration``."""
    if f0 <= 0.0 or f1 <= 0.0 or duration <= 0.0:
        raise ValueError("f0, f1 and duration must be positive")
    # phase(T)/pi = 2 T (f0 + (f1 - f0) T / (2 duration)); zero crossings where it is an integer
    half_cycles = np.floor(2.0 * duration * (f0 + f1) / 2.0 + 1e-9)
    if half_cycles < 1:
        raise ValueError("sweep too short for one half cycle")
    a, b = (f1 - f0) / duration, 2.0 * f0  # solve a T^2 + b T = half_cycles
    return float(2.0 * half_cycles / (b + np.sqrt(b * b + 4.0 * a * half_cycles)))


def swept_sine(
    t: ArrayLike,
    amplitude: float,
    f0: float = 0.2,
    f1: float = 2.0,
    duration: float = 30.0,
    t0: float = 1.0,
) -> np.ndarray:
    """Swept-sine steering input (ISO 7401 continuous sinusoidal input, as a sweep).

    ``SWA = amplitude * sin(2 pi (f0 tau + (f1 - f0) tau^2 / (2 duration)))``, ``tau = t - t0``:
    the instantaneous frequency rises linearly from ``f0`` to ``f1`` (Hz) over
    ``duration`` (s). The sweep stops at its last zero crossing at or before
    ``duration`` (see :func:`swept_sine_end`) so the SWA returns exactly to zero.

    Args:
        t: time (s).
        amplitude: SWA amplitude (rad); positive steers left first.
        f0, f1: start and end frequency (Hz).
        duration: sweep duration (s) at which the frequency would reach ``f1``.
        t0: start (s).
    """
    end = swept_sine_end(f0, f1, duration)
    tau = _as_t(t) - t0
    inside = (tau >= 0.0) & (tau <= end)
    phase = 2.0 * np.pi * (f0 * tau + 0.5 * (f1 - f0) * tau * tau / duration)
    return np.where(inside, amplitude * np.sin(phase), 0.0)


# ---------------------------------------------------------------------- FMVSS 126
def slowly_increasing_steer(
    t: ArrayLike,
    rate: float = float(np.deg2rad(SIS_RATE_DEG_S)),
    t0: float = 1.0,
    direction: int = 1,
    max_angle: float | None = None,
) -> np.ndarray:
    """FMVSS 126 slowly increasing steer (SIS) characterisation manoeuvre.

    At 80 km/h the SWA ramps at ``rate`` (13.5 deg/s) from ``t0`` until the lateral
    acceleration reaches about 0.5 g (the caller stops the run there); six runs,
    three counter-clockwise (``direction=+1``) and three clockwise (``-1``).

    Args:
        t: time (s).
        rate: ramp rate (rad/s), positive.
        t0: start of the ramp (s).
        direction: +1 counter-clockwise (left), -1 clockwise (right).
        max_angle: optional magnitude (rad) at which the SWA stops rising and holds.

    Returns:
        SWA (rad): 0 before ``t0``, ``direction * rate * (t - t0)`` after (held at ``max_angle``).
    """
    if rate <= 0.0:
        raise ValueError("rate must be positive")
    mag = rate * np.maximum(_as_t(t) - t0, 0.0)
    if max_angle is not None:
        mag = np.minimum(mag, max_angle)
    return _direction(direction) * mag


def sis_amplitude_from_ay(
    swa: ArrayLike,
    ay: ArrayLike,
    *,
    ay_target_g: float = 0.3,
    window_g: tuple[float, float] = (0.1, 0.375),
    g: float = G_MPS2,
) -> float:
    """FMVSS 126 quantity "A": the SWA (rad) giving 0.3 g, from a linear regression.

    FMVSS 126 (S7.6.2, read in its GB/T reproduction): "A" is the steering-wheel angle
    that produces a steady-state lateral acceleration of 0.3 g; it is calculated by
    linear regression from each slowly increasing steer run (then the six absolute
    values are averaged and rounded to 0.1 deg, which is left to the caller). The
    standard text seen does not state the fitting window; this function fits
    ``|ay| = a |swa| + b`` to the samples with ``window_g[0] <= |ay|/g <= window_g[1]``
    (0.1-0.375 g by default, a range bracketing 0.3 g in the linear region) taken before
    |ay| first exceeds the window, and returns ``(ay_target - b) / a``.

    Args:
        swa: SWA samples of one SIS run (rad), either sign.
        ay: lateral acceleration samples (m/s^2), same shape, corrected to the centre of mass.
        ay_target_g: lateral-acceleration level defining A (g).
        window_g: fitting window of |ay| (g).
        g: value of g (m/s^2).

    Returns:
        A (rad), positive.
    """
    swa_a = np.abs(np.asarray(swa, dtype=float)).ravel()
    ay_a = np.abs(np.asarray(ay, dtype=float)).ravel() / g
    if swa_a.shape != ay_a.shape:
        raise ValueError("swa and ay must have the same shape")
    lo, hi = window_g
    above = np.flatnonzero(ay_a > hi)
    end = above[0] if above.size else ay_a.size
    idx = np.arange(ay_a.size)
    mask = (ay_a >= lo) & (ay_a <= hi) & (idx < end)
    if np.count_nonzero(mask) < 3:
        raise ValueError("fewer than 3 samples inside the fitting window")
    slope, intercept = np.polyfit(swa_a[mask], ay_a[mask], 1)
    if slope <= 0.0:
        raise ValueError("lateral acceleration does not increase with SWA in the window")
    return float((ay_target_g - intercept) / slope)


def sine_with_dwell_duration(freq: float = SWD_FREQ_HZ, dwell: float = SWD_DWELL_S) -> float:
    """Length (s) of the sine-with-dwell input: one period plus the dwell (1/0.7 + 0.5 = 1.93 s)."""
    return 1.0 / freq + dwell


def sine_with_dwell(
    t: ArrayLike,
    amplitude: float,
    t0: float = 1.0,
    direction: int = 1,
    *,
    freq: float = SWD_FREQ_HZ,
    dwell: float = SWD_DWELL_S,
) -> np.ndarray:
    """FMVSS 126 / NHTSA sine with dwell (ESC oversteer test).

    A 0.7 Hz sine: the SWA rises to +A (quarter period), reverses through zero to
    its second peak -A at three quarters of the period, holds -A for the 500 ms
    dwell, then completes the last quarter period back to zero, where it stays.
    Total length ``1/freq + dwell`` (1.929 s). ``direction=-1`` mirrors it (the
    clockwise series).

    Args:
        t: time (s).
        amplitude: A, magnitude of both peaks (rad), usually from :func:`fmvss126_amplitudes`.
        t0: start (s).
        direction: +1 counter-clockwise (left) first half cycle, -1 clockwise first.
        freq: sine frequency (Hz).
        dwell: hold at the second peak (s).
    """
    if freq <= 0.0 or dwell < 0.0:
        raise ValueError("freq must be positive and dwell non-negative")
    tau = _as_t(t) - t0
    period = 1.0 / freq
    t_peak2 = 0.75 * period
    w = 2.0 * np.pi * freq
    swa = np.select(
        [tau < 0.0, tau < t_peak2, tau < t_peak2 + dwell, tau <= period + dwell],
        [0.0, np.sin(w * tau), -1.0, np.sin(w * (tau - dwell))],
        default=0.0,
    )
    return _direction(direction) * amplitude * swa


def fmvss126_amplitudes(A_0p3g: float) -> np.ndarray:
    """Sine-with-dwell amplitudes (rad) of one FMVSS 126 test series, from A (rad).

    The first run is 1.5A and each next run adds 0.5A up to the final amplitude,
    which is the greater of 6.5A or 270 deg, provided 6.5A <= 300 deg; if any 0.5A
    increment up to 6.5A exceeds 300 deg, the final amplitude is 300 deg (FMVSS 126
    S7.9.3-S7.9.4, wording checked in its GB/T reproduction, 7.7.5-7.7.6). When
    the final amplitude is not a 0.5A step (270 or 300 deg) the last step is shorter.

    Args:
        A_0p3g: SWA giving 0.3 g in the SIS test (rad), positive.

    Returns:
        increasing amplitudes (rad), the last one the final amplitude.
    """
    a = float(A_0p3g)
    if a <= 0.0:
        raise ValueError("A must be positive")
    cap = np.deg2rad(SWD_CAP_DEG)
    six_five = SWD_FINAL_FACTOR * a
    final = max(six_five, np.deg2rad(SWD_FINAL_MIN_DEG)) if six_five <= cap + 1e-12 else cap
    steps = SWD_FIRST_FACTOR * a + SWD_STEP_FACTOR * a * np.arange(int(np.ceil(2.0 * final / a)) + 1)
    steps = steps[steps < final - 1e-9]
    return np.append(steps, final)


# ---------------------------------------------------------------------- NHTSA fishhook
def fishhook_amplitude(A_0p3g: float, scalar: float = FISHHOOK_SCALAR) -> float:
    """NHTSA fishhook handwheel amplitude (rad): steering scalar (default 6.5) times the SIS 0.3 g angle."""
    return scalar * float(A_0p3g)


def fishhook_duration(
    amplitude: float,
    rate: float = float(np.deg2rad(FISHHOOK_RATE_DEG_S)),
    dwell: float = 0.25,
    hold: float = 3.0,
    return_rate: float | None = None,
) -> float:
    """Length (s) of :func:`fishhook` from its start to the return to zero."""
    r_back = rate if return_rate is None else return_rate
    return 3.0 * amplitude / rate + dwell + hold + amplitude / r_back


def fishhook(
    t: ArrayLike,
    amplitude: float,
    t0: float = 1.0,
    rate: float = float(np.deg2rad(FISHHOOK_RATE_DEG_S)),
    dwell: float = 0.25,
    hold: float = 3.0,
    direction: int = 1,
    *,
    return_rate: float | None = None,
) -> np.ndarray:
    """NHTSA fishhook (rollover resistance, NCAP), time-based dwell variant.

    Ramp at ``rate`` (720 deg/s) to +A, dwell, countersteer at ``rate`` to -A, hold
    -A for ``hold`` (3 s), then ramp back to zero at ``return_rate`` (default ``rate``).
    NHTSA triggers the countersteer when the roll rate falls to about 1.5 deg/s (the
    roll-rate-feedback dwell); here the dwell is a fixed time, the simpler form also
    used by NHTSA. Amplitude: ``A = 6.5 * A_0p3g`` (:func:`fishhook_amplitude`).

    Args:
        t: time (s).
        amplitude: A (rad), positive.
        t0: start (s).
        rate: steering rate of the steer and countersteer ramps (rad/s).
        dwell: time at +A before the countersteer (s).
        hold: time at -A (s).
        direction: +1 first steer left (counter-clockwise), -1 right.
        return_rate: rate of the final ramp to zero (rad/s); None = ``rate``.
    """
    if amplitude < 0.0 or rate <= 0.0 or dwell < 0.0 or hold < 0.0:
        raise ValueError("amplitude, rate, dwell and hold must be non-negative (rate > 0)")
    r_back = rate if return_rate is None else return_rate
    if r_back <= 0.0:
        raise ValueError("return_rate must be positive")
    tau = _as_t(t) - t0
    t1 = amplitude / rate
    t2 = t1 + dwell
    t3 = t2 + 2.0 * amplitude / rate
    t4 = t3 + hold
    t5 = t4 + amplitude / r_back
    swa = np.select(
        [tau < 0.0, tau < t1, tau < t2, tau < t3, tau < t4, tau < t5],
        [
            0.0,
            rate * tau,
            amplitude,
            amplitude - rate * (tau - t2),
            -amplitude,
            -amplitude + r_back * (tau - t4),
        ],
        default=0.0,
    )
    return _direction(direction) * swa


# ---------------------------------------------------------------------- ISO 3888-1
class Gate(NamedTuple):
    """A lane of cones: x range (m) and the lateral positions (m) of its left and right cone lines."""

    x_start: float
    x_end: float
    y_left: float
    y_right: float


def double_lane_change_gates(
    vehicle_width: float = 1.8,
    *,
    offset: float = DLC_OFFSET_M,
    direction: int = 1,
    exit_aligned: bool = True,
) -> tuple[Gate, Gate, Gate]:
    """The three cone lanes of the ISO 3888-1 double lane change (severe lane change).

    Sections (m): 1 entry lane 15, 2 lane change 30, 3 side lane 25, 4 lane change
    back 25, 5 exit lane 15, then a run-out. Lane widths (m): 1.1w + 0.25, 1.2w + 0.25,
    1.3w + 0.25 for a vehicle of width w. Entry lane from x = 0 to 15 centred on y = 0.
    The side lane's centreline is ``offset`` (3.5 m) to the left (``direction=+1``) of
    the entry lane's. With ``exit_aligned`` the exit lane shares the entry lane's outer
    (right for a left change) cone line, as drawn in the standard's figure according to
    the public implementations consulted (its centre is then 0.1w to the left); with
    ``exit_aligned=False`` it is centred on y = 0. Caveat: implementations differ on
    the 3.5 m (centreline to centreline here, as in MathWorks' examples; Project Chrono
    measures it from the entry centreline to the side lane's near cone line).

    Returns:
        (entry, side, exit) :class:`Gate` tuples.
    """
    d = _direction(direction)
    w1, w3, w5 = 1.1 * vehicle_width + 0.25, 1.2 * vehicle_width + 0.25, 1.3 * vehicle_width + 0.25
    l1, l2, l3, l4, l5 = DLC_SECTION_LENGTHS_M
    c1, c3 = 0.0, d * offset
    c5 = d * 0.5 * (w5 - w1) if exit_aligned else 0.0
    x = np.cumsum([0.0, l1, l2, l3, l4, l5])

    def gate(x0: float, x1: float, c: float, w: float) -> Gate:
        return Gate(float(x0), float(x1), c + 0.5 * w, c - 0.5 * w)

    return gate(x[0], x[1], c1, w1), gate(x[2], x[3], c3, w3), gate(x[4], x[5], c5, w5)


def double_lane_change_path(
    x: ArrayLike,
    vehicle_width: float = 1.8,
    *,
    offset: float = DLC_OFFSET_M,
    direction: int = 1,
    exit_aligned: bool = True,
) -> np.ndarray:
    """Lateral position y(x) (m) of a C2-smooth centreline through the ISO 3888-1 gates.

    Straight along each lane's centreline inside the lanes (and before and after the
    course), and a quintic blend ``10u^3 - 15u^4 + 6u^5`` across each lane-change
    section (2: 30 m, 4: 25 m), whose slope and curvature vanish at both ends, so the
    path is C2: position, heading and curvature are continuous. It therefore passes
    straight through the middle of every gate. Peak path curvature is about
    5.77 * offset / L^2: 0.022 1/m over section 2 and 0.031 1/m over section 4 (w = 1.8 m),
    i.e. ~10 m/s^2 at 18 m/s on the way back: a severe manoeuvre, as intended.

    Args:
        x: longitudinal position (m), any shape; the entry lane starts at x = 0.
        vehicle_width: w (m), sets the exit lane's centre when ``exit_aligned``.
        offset, direction, exit_aligned: see :func:`double_lane_change_gates`.

    Returns:
        y (m), shape of ``x``.
    """
    entry, side, exit_ = double_lane_change_gates(
        vehicle_width, offset=offset, direction=direction, exit_aligned=exit_aligned
    )
    xa = np.asarray(x, dtype=float)
    c1 = 0.5 * (entry.y_left + entry.y_right)
    c3 = 0.5 * (side.y_left + side.y_right)
    c5 = 0.5 * (exit_.y_left + exit_.y_right)
    up = _smoothstep5((xa - entry.x_end) / (side.x_start - entry.x_end))
    down = _smoothstep5((xa - side.x_end) / (exit_.x_start - side.x_end))
    return c1 + (c3 - c1) * up + (c5 - c3) * down


# ---------------------------------------------------------------------- ISO 4138
class PathArrays(NamedTuple):
    """A sampled path: arc length s (m), position x, y (m), heading (rad), curvature (1/m)."""

    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    curvature: np.ndarray


def circle_path(
    radius: float,
    n_laps: float,
    ds: float = 1.0,
    direction: int = 1,
    *,
    lead_in: float = 30.0,
) -> PathArrays:
    """ISO 4138 constant-radius circular path with a straight lead-in.

    Starts at the origin heading +x, runs straight for ``lead_in`` metres, then joins
    the circle of ``radius`` tangentially (centre at ``(lead_in, direction * radius)``)
    and goes round it ``n_laps`` times: counter-clockwise (left turn) for
    ``direction=+1``, clockwise for -1. Curvature steps from 0 to ``direction/radius``
    at the join (no transition spiral, as on a circle test pad).

    Args:
        radius: circle radius (m).
        n_laps: number of laps (may be fractional).
        ds: sampling step (m); the last sample is exactly at the end of the path.
        direction: +1 counter-clockwise, -1 clockwise.
        lead_in: length of the straight before the circle (m), >= 0.

    Returns:
        :class:`PathArrays` (heading unwrapped, continuous).
    """
    d = _direction(direction)
    if radius <= 0.0 or n_laps <= 0.0 or ds <= 0.0 or lead_in < 0.0:
        raise ValueError("radius, n_laps and ds must be positive and lead_in non-negative")
    total = lead_in + 2.0 * np.pi * radius * n_laps
    n = int(np.ceil(total / ds))
    s = np.linspace(0.0, total, n + 1)
    phi = np.maximum(s - lead_in, 0.0) / radius
    on_circle = s > lead_in
    x = np.where(on_circle, lead_in + radius * np.sin(phi), s)
    y = d * radius * (1.0 - np.cos(phi))
    heading = d * phi
    curvature = np.where(on_circle, d / radius, 0.0)
    return PathArrays(s, x, y, heading, curvature)
