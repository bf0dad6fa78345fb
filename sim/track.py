"""Race-track centrelines and the quasi-steady lap speed profile.

Frames and signs (ISO 8855): x, y in an earth-fixed horizontal frame (z up);
``heading`` is the angle of the path tangent from +x towards +y (rad, yaw
sense, unwrapped so it is continuous along the path); ``curvature`` is
d(heading)/ds (1/m), positive when the path turns left. All lengths in m,
speeds in m/s, accelerations in m/s^2.

The bundled Magny-Cours centreline (``sim/data/magny_cours_centreline.csv``)
is derived by ``tools/derive_track.py`` from bacinger/f1-circuits
``circuits/fr-1960.geojson`` (MIT licence); the lap runs clockwise, as raced,
so its heading falls by 2 pi per lap and its long-run curvature is negative.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["Track", "TrackSample", "TrackError", "BUNDLED_TRACKS", "MAX_LAP_M", "MIN_LAP_M", "check_lap_length",
           "load_magny_cours", "load_track", "numeric_csv", "speed_profile", "lap_time"]

COLUMNS = ("s_m", "x_m", "y_m", "heading_rad", "curvature_1pm")
MAGNY_COURS_CSV = "magny_cours_centreline.csv"
#: circuits bundled with the package, by name: file under ``sim/data`` (derived centrelines,
#: provenance in each file's header and in NOTICE). Magny-Cours is the report circuit: it is
#: never used for training or tuning; the others are for development.
BUNDLED_TRACKS: dict[str, str] = {
    "magny-cours": MAGNY_COURS_CSV,
    "hungaroring": "tracks/hungaroring.csv",
    "zandvoort": "tracks/zandvoort.csv",
    "red-bull-ring": "tracks/red_bull_ring.csv",
}


#: shortest lap accepted (m): a few smoothing wavelengths, room for one corner and a straight
MIN_LAP_M = 200.0
#: longest lap accepted (m). The longest road circuits are about 25 km (the Nordschleife 20.8 km, with the GP
#: circuit 25.4 km; Le Mans 13.6 km): twice that leaves room for any of them, while a centreline in the wrong
#: unit (millimetres give 1000 times the length) falls far outside. It also bounds the work that a lap's length
#: sets: its derivation samples the loop every metre and every 5 cm, and a lap of 6e9 m asked for 47 GiB.
MAX_LAP_M = 50_000.0


class TrackError(ValueError):
    """A centreline that cannot be driven: unreadable, open, crossing itself, too short or too tight."""


def check_lap_length(length: float, origin: str) -> None:
    """Refuse a lap shorter than :data:`MIN_LAP_M` or longer than :data:`MAX_LAP_M` (or not finite).

    Raises:
        TrackError: naming ``origin`` (the file), the length found and the unit it suggests.
    """
    if MIN_LAP_M <= length <= MAX_LAP_M:
        return
    if length > MAX_LAP_M:
        units = [name for scale, name in ((1e-3, "millimetres"), (1e-2, "centimetres"))
                 if MIN_LAP_M <= length * scale <= MAX_LAP_M]
        raise TrackError(f"{origin}: the loop is {length / 1000.0:.6g} km long, longer than the "
                         f"{MAX_LAP_M / 1000.0:g} km any circuit is (the longest, about 25 km); wrong unit? "
                         f"(coordinates in metres{', not ' + units[0] if units else ''})")
    units = [name for scale, name in ((1e3, "kilometres"), (1609.344, "miles")) if length * scale >= MIN_LAP_M]
    raise TrackError(f"{origin}: the loop is {length:.3g} m long, shorter than the {MIN_LAP_M:.0f} m a circuit "
                     f"needs; wrong unit? (coordinates in metres{', not ' + units[0] if units else ''})")


class TrackSample(NamedTuple):
    """Centreline quantities at queried arc lengths (arrays shaped like the query)."""

    x: np.ndarray  #: position x (m)
    y: np.ndarray  #: position y (m)
    heading: np.ndarray  #: tangent angle from +x towards +y (rad), continuous across laps
    curvature: np.ndarray  #: curvature (1/m), > 0 turning left


def numeric_csv(text: str, origin: str, columns: tuple[str, ...]) -> np.ndarray:
    """The rows of a CSV of finite numbers under the header ``columns`` (blank and ``#`` lines skipped), as an
    ``(n, len(columns))`` array in file order.

    Raises:
        TrackError: one line naming ``origin`` and the line: another header, a row of another width, a cell that is
            no finite number (its column named), or a last row the text ends inside (no end of line: a file cut
            mid-row, whose last number may be cut too).
    """
    raw = text.splitlines(keepends=True)
    rows = [(i, ln) for i, ln in enumerate(raw, 1) if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows or tuple(c.strip() for c in rows[0][1].split(",")) != columns:
        raise TrackError(f"{origin}: expected a header line {','.join(columns)}")
    if len(rows) > 1 and not rows[-1][1].endswith(("\n", "\r")):
        raise TrackError(f"{origin}, line {rows[-1][0]}: truncated: the file ends inside this row (a complete file "
                         f"ends every row with an end of line)")
    out = np.empty((len(rows) - 1, len(columns)))
    for k, (line_no, line) in enumerate(rows[1:]):
        cells = line.split(",")
        if len(cells) != len(columns):
            raise TrackError(f"{origin}, line {line_no}: expected {len(columns)} numbers {','.join(columns)}, "
                             f"got {line.strip()!r}")
        for j, cell in enumerate(cells):
            try:
                out[k, j] = float(cell)
            except ValueError:
                raise TrackError(f"{origin}, line {line_no}: {columns[j]} {cell.strip()!r} is not a number") from None
            if not np.isfinite(out[k, j]):
                raise TrackError(f"{origin}, line {line_no}: {columns[j]} must be finite, got {cell.strip()!r}")
    return out


def _readonly(a: ArrayLike) -> np.ndarray:
    arr = np.array(a, dtype=float)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Track:
    """A closed centreline sampled along its arc length.

    The arrays include a closing sample: ``s[0] == 0``, ``s[-1] == length`` and the
    last position equals the first; ``heading[-1] - heading[0]`` is the net turn of
    one lap (-2 pi for a clockwise circuit).

    Attributes:
        s: arc length (m), strictly increasing, from 0 to ``length``.
        x, y: position (m).
        heading: tangent angle (rad), unwrapped.
        curvature: curvature (1/m), > 0 turning left.
        length: lap length (m).
    """

    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    curvature: np.ndarray
    length: float

    def __post_init__(self) -> None:
        for name in ("s", "x", "y", "heading", "curvature"):
            object.__setattr__(self, name, _readonly(getattr(self, name)))
        object.__setattr__(self, "length", float(self.length))
        n = self.s.shape
        if len(n) != 1 or n[0] < 3:
            raise ValueError("Track arrays must be 1-D with at least 3 samples")
        if any(getattr(self, k).shape != n for k in ("x", "y", "heading", "curvature")):
            raise ValueError("Track arrays must all have the same shape")
        if self.s[0] != 0.0 or np.any(np.diff(self.s) <= 0.0):
            raise ValueError("Track.s must start at 0 and increase strictly")
        if not np.isclose(self.s[-1], self.length, rtol=0.0, atol=1e-6):
            raise ValueError("Track.s must end at Track.length (closing sample)")

    # ------------------------------------------------------------------ queries
    @property
    def turn_per_lap(self) -> float:
        """Net heading change over one lap (rad); -2 pi for a clockwise circuit."""
        return float(self.heading[-1] - self.heading[0])

    def at(self, s: ArrayLike) -> TrackSample:
        """Interpolate the centreline at arc lengths ``s`` (m, any shape, any real value).

        ``s`` wraps periodically with ``length``. Position uses cubic Hermite
        interpolation with the unit tangents (error ~ ds^4 |dkappa/ds|, well under
        1 mm at 2 m spacing); heading and curvature interpolate linearly. The heading
        gains ``turn_per_lap`` per lap, so it is continuous for s beyond one lap.
        """
        s_arr = np.asarray(s, dtype=float)
        lap = np.floor(s_arr / self.length)
        sm = s_arr - lap * self.length
        i = np.clip(np.searchsorted(self.s, sm, side="right") - 1, 0, len(self.s) - 2)
        h = self.s[i + 1] - self.s[i]
        t = (sm - self.s[i]) / h
        t2, t3 = t * t, t * t * t
        h00, h10, h01, h11 = 2 * t3 - 3 * t2 + 1, t3 - 2 * t2 + t, -2 * t3 + 3 * t2, t3 - t2
        c0, s0 = np.cos(self.heading[i]), np.sin(self.heading[i])
        c1, s1 = np.cos(self.heading[i + 1]), np.sin(self.heading[i + 1])
        x = h00 * self.x[i] + h10 * h * c0 + h01 * self.x[i + 1] + h11 * h * c1
        y = h00 * self.y[i] + h10 * h * s0 + h01 * self.y[i + 1] + h11 * h * s1
        heading = (1 - t) * self.heading[i] + t * self.heading[i + 1] + lap * self.turn_per_lap
        curvature = (1 - t) * self.curvature[i] + t * self.curvature[i + 1]
        return TrackSample(x, y, heading, curvature)

    def laps(self, n: int) -> Track:
        """The centreline driven ``n`` times as one path (``n >= 1``).

        s runs continuously from 0 to ``n * length``; the heading stays continuous
        (it gains ``turn_per_lap`` each lap); the result is again a closed Track.
        """
        if int(n) != n or n < 1:
            raise ValueError("n must be a positive integer")
        n = int(n)
        body = slice(0, -1)
        k = np.repeat(np.arange(n), len(self.s) - 1)

        def tile(a: np.ndarray) -> np.ndarray:
            return np.concatenate([np.tile(a[body], n), a[-1:]])

        s = np.concatenate([np.tile(self.s[body], n) + k * self.length, [n * self.length]])
        heading = np.concatenate(
            [
                np.tile(self.heading[body], n) + k * self.turn_per_lap,
                [self.heading[-1] + (n - 1) * self.turn_per_lap],
            ]
        )
        return Track(s, tile(self.x), tile(self.y), heading, tile(self.curvature), n * self.length)

    def aligned_to_start(self) -> Track:
        """The same track moved and rotated so s = 0 is at the origin heading +x."""
        c, sn = np.cos(-self.heading[0]), np.sin(-self.heading[0])
        dx, dy = self.x - self.x[0], self.y - self.y[0]
        return Track(
            self.s,
            c * dx - sn * dy,
            sn * dx + c * dy,
            self.heading - self.heading[0],
            self.curvature,
            self.length,
        )

    def started_at(self, s0: float) -> Track:
        """The same circuit with its line moved to arc length ``s0`` (m, taken modulo the lap, snapped to the
        nearest sample): the same positions, headings and curvatures, driven from there."""
        n = len(self.s) - 1  # (samples of one lap, the closing one left out)
        d = np.abs(self.s[: n + 1] - float(s0) % self.length)
        i0 = int(np.argmin(d)) % n  # (the closing sample is the line: s0 just short of a lap snaps to it)
        if i0 == 0:
            return self
        order = np.r_[i0:n, 0:i0]
        s = np.r_[self.s[i0:n] - self.s[i0], self.s[:i0] + self.length - self.s[i0], self.length]
        wrap = np.r_[np.zeros(n - i0), np.ones(i0)] * self.turn_per_lap
        heading = np.r_[self.heading[order] + wrap, self.heading[i0] + self.turn_per_lap]
        return Track(s, np.r_[self.x[order], self.x[i0]], np.r_[self.y[order], self.y[i0]], heading,
                     np.r_[self.curvature[order], self.curvature[i0]], self.length)

    def next_straight(self, max_curvature: float = 0.002, length: float = 10.0) -> float:
        """Arc length (m) of the first point, from the line on, where the next ``length`` m all bend less than
        ``max_curvature`` (1/m): 0 when the line is on such a straight. A lap with no such stretch gives the start
        of its least bent one (the smallest largest curvature over ``length`` m; 0 when none bends less than
        the line's)."""
        n = len(self.s) - 1
        ds = float(np.median(np.diff(self.s)))
        k = min(max(int(np.ceil(length / ds)), 1), n)
        bend = np.abs(self.curvature[:n])
        ahead = np.lib.stride_tricks.sliding_window_view(np.r_[bend, bend[:k]], k + 1).max(axis=1)[:n]
        ok = np.flatnonzero(ahead <= max_curvature)
        i = int(ok[0]) if ok.size else int(np.argmin(ahead))
        return float(self.s[i]) if ahead[i] < ahead[0] or ok.size else 0.0

    # ------------------------------------------------------------------ I/O
    @classmethod
    def from_csv(cls, path: str | Path) -> Track:
        """Read a centreline CSV (``#`` comments, header ``s_m,x_m,y_m,heading_rad,curvature_1pm``)."""
        return cls._from_text(Path(path).read_text(encoding="utf-8"), str(path))

    @classmethod
    def _from_text(cls, text: str, origin: str) -> Track:
        """A derived centreline from its CSV text; TrackError names ``origin`` (:func:`numeric_csv`, or arrays
        that are no centreline: fewer than 3 samples, ``s`` not increasing from 0)."""
        s, x, y, heading, curvature = numeric_csv(text, origin, COLUMNS).T
        try:
            return cls(s, x, y, heading, curvature, float(s[-1]) if s.size else 0.0)
        except ValueError as exc:
            raise TrackError(f"{origin}: {exc}") from None


def load_magny_cours() -> Track:
    """Load the bundled Magny-Cours centreline (4445 m, clockwise, start/finish straight at s = 0)."""
    return load_track("magny-cours")


def check_readable(path: Path) -> None:
    """Refuse a centreline file that is missing, not a regular file (a directory, a pipe) or not readable, naming it.

    Raises:
        TrackError: ``<path>: no such file`` / ``not a regular file`` / ``not readable (<reason>)``.
    """
    if not path.exists():
        raise TrackError(f"{path}: no such file")
    if not path.is_file():
        raise TrackError(f"{path}: not a regular file")
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        raise TrackError(f"{path}: not readable ({exc.strerror or exc})") from None


def load_track(spec: str | Path, **derive_options: float) -> Track:
    """A circuit by bundled name (:data:`BUNDLED_TRACKS`), a random one (``random:SEED``,
    :mod:`sim.randomtrack`) or from a file.

    Files: a derived centreline CSV (header ``s_m,x_m,y_m,heading_rad,curvature_1pm``,
    used as is), or a loop of surveyed points, a CSV with header ``x_m,y_m`` or a GeoJSON
    LineString of lon/lat, closed, smoothed and resampled by :mod:`sim.centreline`
    (``derive_options``: ``ds``, ``smoothing_length``) in the direction listed.

    Raises:
        TrackError: unknown name, missing or malformed file, or a centreline that is
            open, crosses itself other than at a bridge, or shorter or longer than a circuit (:func:`check_lap_length`).
    """
    name = str(spec)
    from sim.randomtrack import parse_name, random_track

    seed = parse_name(name)
    if seed is not None:
        return random_track(seed)
    if name in BUNDLED_TRACKS:
        rel = BUNDLED_TRACKS[name]
        text = resources.files("sim").joinpath("data", *rel.split("/")).read_text(encoding="utf-8")
        return Track._from_text(text, f"sim/data/{rel}")
    path = Path(name)
    if path.suffix == "" and not path.exists():
        raise TrackError(f"unknown circuit {name!r}: name one of {', '.join(BUNDLED_TRACKS)}, random:SEED, "
                         "or give a .csv or .geojson file")
    if path.suffix.lower() == ".csv":  # (a GeoJSON is checked by read_points)
        check_readable(path)
        text = path.read_text(encoding="utf-8-sig", errors="replace")
        header = next((ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")), "")
        if tuple(c.strip() for c in header.split(",")) == COLUMNS:
            track = Track._from_text(text, str(path))
            check_lap_length(track.length, str(path))
            return track
    from sim.centreline import read_points, track_from_points

    points, _ = read_points(path)
    return track_from_points(points, str(path), **derive_options)


# ---------------------------------------------------------------------- speed profile
def speed_profile(
    track_or_path_curvature: Track | ArrayLike,
    s: ArrayLike,
    mu: float | ArrayLike,
    *,
    v_max_mps: float,
    ay_frac: float = 0.85,
    ax_accel_mps2: float = 3.0,
    ax_brake_frac: float = 0.8,
    ax_accel_frac: float | None = None,
    g: float = 9.81,
    v_start_mps: float | None = None,
    v_end_mps: float | None = None,
) -> np.ndarray:
    """Quasi-steady speed profile v(s) (m/s) of a car driven briskly along a path.

    The classic three-step construction:

    1. cornering limit ``v_lim = min(v_max, sqrt(ay_lim / |kappa|))`` with the lateral
       budget ``ay_lim = ay_frac * mu * g`` (0.85 of the friction limit by default);
    2. forward pass (acceleration): ``v[i+1]^2 <= v[i]^2 + 2 * ax * ds`` with
       ``ax = ax_max * sqrt(1 - (ay / ay_lim)^2)``, ``ay = v[i]^2 |kappa[i]|``, where
       ``ax_max = min(ax_accel_mps2, ax_accel_frac * mu * g)``: the powertrain's limit
       or, on a slippery road, the driven wheels' grip;
    3. backward pass (braking): ``v[i]^2 <= v[i+1]^2 + 2 * ab * ds`` with
       ``ab = ax_brake_frac * mu * g * sqrt(1 - (ay / ay_lim)^2)``, ``ay = v[i+1]^2 |kappa[i+1]|``,

    so the longitudinal and lateral accelerations share a friction ellipse
    (semi-axes ``ax_accel_mps2`` or ``ax_brake_frac * mu * g`` and ``ay_lim``). On each
    step the friction is the lower of its two ends, so a step onto a wetter surface
    is braked for in advance. The two passes are plain loops over the samples
    (they run once per run, not per simulation step).

    Args:
        track_or_path_curvature: a :class:`Track` (curvature taken at ``s``, wrapping per
            lap) or the path curvature (1/m) already sampled at ``s`` (same shape).
        s: arc length (m), 1-D, strictly increasing.
        mu: road friction coefficient (-), scalar or array over ``s`` (e.g. 1.0 on lap 1
            and 0.7 on lap 2 of ``track.laps(2)``).
        v_max_mps: speed cap (m/s), e.g. the car's top speed or a target.
        ay_frac: fraction of the friction used laterally at the cornering limit (-).
        ax_accel_mps2: acceleration available from the powertrain (m/s^2).
        ax_brake_frac: braking deceleration as a fraction of ``mu * g`` (-).
        ax_accel_frac: acceleration at most this fraction of ``mu * g`` (-), what the
            driven axle's tyres transmit (None: the powertrain's limit only).
        g: gravity (m/s^2).
        v_start_mps: speed at ``s[0]`` (None: as fast as the limits allow, a flying start).
        v_end_mps: speed required at ``s[-1]`` (None: unconstrained).

    Returns:
        v (m/s), same shape as ``s``.
    """
    s_arr = np.asarray(s, dtype=float)
    if s_arr.ndim != 1 or s_arr.size < 2 or np.any(np.diff(s_arr) <= 0.0):
        raise ValueError("s must be 1-D, with at least 2 samples, strictly increasing")
    if isinstance(track_or_path_curvature, Track):
        kappa = track_or_path_curvature.at(s_arr).curvature
    else:
        kappa = np.asarray(track_or_path_curvature, dtype=float)
        if kappa.shape != s_arr.shape:
            raise ValueError("path curvature must have the shape of s")
    mu_arr = np.broadcast_to(np.asarray(mu, dtype=float), s_arr.shape)
    if np.any(mu_arr <= 0.0) or v_max_mps <= 0.0 or not 0.0 < ay_frac <= 1.0:
        raise ValueError("mu, v_max_mps and ay_frac must be positive (ay_frac <= 1)")

    abs_k = np.abs(kappa)
    ay_lim = ay_frac * mu_arr * g
    with np.errstate(divide="ignore"):
        v_lim = np.minimum(v_max_mps, np.sqrt(ay_lim / abs_k))
    ds = np.diff(s_arr)
    mu_seg = np.minimum(mu_arr[:-1], mu_arr[1:])
    ay_lim_seg = ay_frac * mu_seg * g
    brake_seg = ax_brake_frac * mu_seg * g
    accel_seg = np.full(len(ds), float(ax_accel_mps2))
    if ax_accel_frac is not None:
        accel_seg = np.minimum(accel_seg, ax_accel_frac * mu_seg * g)

    def ellipse(v: float, k: float, ay_max: float) -> float:
        r = (v * v * k) / ay_max
        return np.sqrt(max(0.0, 1.0 - r * r))

    v = v_lim.copy()
    if v_start_mps is not None:
        v[0] = min(v[0], float(v_start_mps))
    if v_end_mps is not None:
        v[-1] = min(v[-1], float(v_end_mps))
    n = len(v)
    for i in range(n - 1):  # forward: acceleration limit
        ax = accel_seg[i] * ellipse(v[i], abs_k[i], ay_lim_seg[i])
        v[i + 1] = min(v[i + 1], np.sqrt(v[i] * v[i] + 2.0 * ax * ds[i]))
    for i in range(n - 2, -1, -1):  # backward: braking limit
        ab = brake_seg[i] * ellipse(v[i + 1], abs_k[i + 1], ay_lim_seg[i])
        v[i] = min(v[i], np.sqrt(v[i + 1] * v[i + 1] + 2.0 * ab * ds[i]))
    return v


def lap_time(s: ArrayLike, v: ArrayLike) -> float:
    """Time (s) to cover the samples ``s`` (m) at speeds ``v`` (m/s), trapezoidal in 1/v."""
    s_arr, v_arr = np.asarray(s, dtype=float), np.asarray(v, dtype=float)
    return float(np.sum(np.diff(s_arr) * 0.5 * (1.0 / v_arr[1:] + 1.0 / v_arr[:-1])))
