"""Random closed circuits for training: track-like driving on roads that no survey produced.

A circuit drawn by :func:`random_points` is a star-shaped loop ``r(theta) = R exp(sum_k a_k cos(k theta +
phi_k))`` (k = 2..10, amplitudes ``a_k ~ U(0, 0.8) / sqrt(k)``, random phases), scaled to a random lap
length. With these amplitudes the draws' curvature resembles that of surveyed grand-prix circuits: a
tightest corner of about 14 m radius (median of draws) and 6 %, 20 % and 41 % of the lap on radii
under 40, 100 and 300 m (``tests/test_circuit.py`` checks the figures on 16 draws).
A curve of that form meets each ray from its centre once, so it never crosses itself; the modes give
long straights, fast sweepers and slow corners in random order. The loop then goes through the same
derivation as a surveyed centreline (:func:`sim.centreline.track_from_points`: smoothing, resampling,
heading and curvature). A draw whose tightest corner the car cannot steer round, or that the
derivation refuses, is drawn again from the next sub-seed, so every seed gives one circuit,
deterministically.

Name a random circuit ``random:SEED`` wherever a circuit is named (``--track random:17``).
"""

from __future__ import annotations

import numpy as np

from sim.track import Track, TrackError

__all__ = ["PREFIX", "LENGTH_RANGE_M", "random_points", "random_track", "parse_name"]

#: circuit names of the form ``random:SEED``
PREFIX = "random:"
#: lap length range of the draws (m): short club circuits to grand-prix tracks
LENGTH_RANGE_M = (2500.0, 5500.0)
#: tightest corner radius a draw may have (m): a hairpin, and within every car's steering lock
MIN_RADIUS_M = 10.0
#: draws tried per seed before giving up (the acceptance rate is well above one in ten)
MAX_DRAWS = 50
_MODES = np.arange(2, 11)
_N_POINTS = 720


def parse_name(name: str) -> int | None:
    """The seed of ``random:SEED``, None for any other name; TrackError for a malformed seed."""
    if not name.startswith(PREFIX):
        return None
    text = name[len(PREFIX):]
    if not text.isdigit() or int(text) >= 2**32:
        raise TrackError(f"{name!r}: a random circuit is named random:SEED with SEED 0 to 2**32-1")
    return int(text)


def random_points(rng: np.random.Generator) -> np.ndarray:
    """One draw: (N, 2) points (m) of a closed star-shaped loop, counter-clockwise, first point not repeated."""
    theta = np.linspace(0.0, 2.0 * np.pi, _N_POINTS, endpoint=False)
    amp = rng.uniform(0.0, 0.8, size=_MODES.size) / np.sqrt(_MODES)
    phase = rng.uniform(0.0, 2.0 * np.pi, size=_MODES.size)
    log_r = (amp[:, None] * np.cos(_MODES[:, None] * theta[None, :] + phase[:, None])).sum(axis=0)
    r = np.exp(log_r)
    pts = np.column_stack([r * np.cos(theta), r * np.sin(theta)])
    length = float(np.hypot(*np.diff(np.vstack([pts, pts[:1]]), axis=0).T).sum())
    return pts * (rng.uniform(*LENGTH_RANGE_M) / length)


def random_track(seed: int) -> Track:
    """The random circuit of ``seed``: the first draw of its sub-seeds that is a drivable circuit.

    Raises:
        TrackError: no draw of ``MAX_DRAWS`` was drivable (not seen in practice).
    """
    from sim.centreline import track_from_points

    for k in range(MAX_DRAWS):
        rng = np.random.default_rng([seed, k])
        pts = random_points(rng)
        if rng.random() < 0.5:  # half of them run clockwise
            pts = pts[::-1]
        try:
            track = track_from_points(pts, f"{PREFIX}{seed}")
        except TrackError:
            continue
        if np.abs(track.curvature).max() * MIN_RADIUS_M <= 1.0:
            return track
    raise TrackError(f"{PREFIX}{seed}: no drivable circuit in {MAX_DRAWS} draws")
