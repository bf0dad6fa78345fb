"""Closed race-track centrelines from surveyed points: read, check, smooth, resample.

Input is a closed loop of points in the order of travel: a CSV with header
``x_m,y_m`` (metres, any spacing, first point not repeated) or a GeoJSON
LineString of WGS84 lon/lat (the format of public circuit collections; a
repeated last point is dropped). The result is a :class:`sim.track.Track`.

Method
------
1. **Projection** (GeoJSON only). Equirectangular projection about the
   centroid of the points with the WGS84 radii of curvature at the centroid
   latitude (prime vertical N for east, meridional M for north)::

       x = N(lat0) cos(lat0) (lon - lon0),   y = M(lat0) (lat - lat0)    [m]

   x east, y north, z up (ISO 8855 earth-fixed axes). Over a few km the east
   scale varies by tan(lat0) * dlat, a few centimetres; :func:`enu_exact`
   measures that error against the exact geodetic -> ECEF -> ENU transform.
2. **Direction.** Kept as listed unless a direction is asked for; the
   shoelace (signed) area tells clockwise (< 0 with x east, y north) from
   counter-clockwise. Reversal keeps the first point first.
3. **Smoothing.** The loop is sampled every 1 m along its edges (so long
   straight edges stay straight) and fitted with a *periodic penalised
   quintic B-spline* (P-spline, Eilers & Marx): uniform knots every ~2 m, the
   least-squares misfit plus ``ell**6 * int |P'''(u)|**2 du``. The penalty on
   the third derivative acts on the rate of change of curvature, so curvature
   varies smoothly (clothoid-like). A sinusoidal wiggle of wavelength lambda
   keeps the fraction ``1 / (1 + (2 pi ell / lambda)**6)``: with ell = 8 m,
   features shorter than about 50 m are treated as tracing noise.
4. **Resampling.** The spline is parametrised by arc length; the lap starts
   at the spline point nearest the first input point and is sampled every
   ``L / N`` m with ``N = round(L / ds)``; a closing sample at ``s = L``
   repeats the first position, its heading shifted by the lap's net turn.
   Heading (rad, from +x towards +y, unwrapped) and curvature (1/m, > 0
   turning left) come analytically from the spline.

Checks (each raises :class:`TrackError` with one line naming the file): too
few points, a loop that is open (the gap from the last point back to the
first is longer than ``OPEN_GAP_M`` and than ``OPEN_GAP_RATIO`` times any other
step), shorter than
``MIN_LENGTH_M`` or longer than ``MAX_LENGTH_M`` (a file in the wrong unit: checked before
any work is sized by the length), a smoothed centreline that crosses itself other than at a bridge (below), and a corner
tighter than the car can steer round (:func:`check_steerable`).

A centreline may cross itself where one stretch of road passes over another, as Suzuka's
figure of eight does: the two passes cross at more than ``BRIDGE_MIN_ANGLE_DEG`` and
the loop between them, either way round, is at least ``BRIDGE_MIN_LOOP_M`` long (the path
follower looks for the car along the road just ahead of it, so it never takes the other
pass for its own). A crossing at a glancing angle, or round a short loop (a knot a
trace out of order or a hairpin drawn too tightly leaves), is refused.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg
from scipy import interpolate
from scipy.spatial import cKDTree

from sim.track import MAX_LAP_M, MIN_LAP_M, Track, TrackError, check_lap_length, check_readable, numeric_csv

__all__ = [
    "BRIDGE_MIN_ANGLE_DEG", "BRIDGE_MIN_LOOP_M",
    "MAX_LENGTH_M", "MIN_LENGTH_M", "OPEN_GAP_M", "OPEN_GAP_RATIO", "derive", "read_points", "read_geojson_lonlat",
    "equirectangular", "enu_exact", "signed_area", "fit_periodic_pspline", "check_steerable", "track_from_points",
]

# WGS84 ellipsoid.
WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)

#: shortest and longest lap accepted (m), see :data:`sim.track.MIN_LAP_M` and :data:`sim.track.MAX_LAP_M`
MIN_LENGTH_M = MIN_LAP_M
MAX_LENGTH_M = MAX_LAP_M
#: a closing gap (last point back to the first) longer than this and than ``OPEN_GAP_RATIO`` times
#: the longest other step is an open line (a sparse trace may close with one long straight edge)
OPEN_GAP_M = 30.0
OPEN_GAP_RATIO = 2.5
#: spacing (m) of the centreline checked for self-intersection
_CROSSING_STEP_M = 4.0
#: a crossing is a bridge (one pass over the other) only at more than this angle between the passes (deg) ...
BRIDGE_MIN_ANGLE_DEG = 30.0
#: ... and with at least this much road (m) between the two passes, either way round the loop
BRIDGE_MIN_LOOP_M = 200.0


# ---------------------------------------------------------------------- reading
def read_geojson_lonlat(path: Path) -> tuple[np.ndarray, dict]:
    """The (n, 2) lon/lat array (deg) of the first LineString in a GeoJSON file, and its properties.

    Raises:
        TrackError: unreadable JSON, no LineString, or coordinates that are not lon/lat.
    """
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise TrackError(f"{path}: not a readable GeoJSON file ({exc})") from None
    if not isinstance(data, dict):
        raise TrackError(f"{path}: not a GeoJSON object")
    features = data.get("features") if data.get("type") == "FeatureCollection" else [data]
    for feature in features or []:
        geometry = (feature.get("geometry") if feature.get("type") == "Feature" else feature) or {}
        if geometry.get("type") == "LineString":
            try:
                coords = np.asarray(geometry["coordinates"], dtype=float)
            except (KeyError, TypeError, ValueError):
                raise TrackError(f"{path}: LineString coordinates are not numbers") from None
            if coords.ndim != 2 or coords.shape[1] < 2:
                raise TrackError(f"{path}: LineString coordinates must be [lon, lat] pairs")
            lonlat = coords[:, :2]
            if not np.all(np.isfinite(lonlat)) or np.any(np.abs(lonlat[:, 0]) > 180) \
                    or np.any(np.abs(lonlat[:, 1]) > 90):
                raise TrackError(f"{path}: LineString coordinates are not WGS84 lon/lat in degrees")
            return lonlat, dict(feature.get("properties") or {})
    raise TrackError(f"{path}: no LineString feature found (a circuit is one LineString of lon/lat points)")


def _read_xy_csv(path: Path) -> np.ndarray:
    try:
        text = Path(path).read_text(encoding="utf-8-sig")  # (a spreadsheet's "CSV UTF-8" starts with a BOM)
    except (OSError, UnicodeDecodeError) as exc:
        raise TrackError(f"{path}: cannot read ({exc})") from None
    return numeric_csv(text, str(path), ("x_m", "y_m"))


def read_points(path: str | Path) -> tuple[np.ndarray, dict[str, Any]]:
    """The loop's points (n, 2) in metres and facts about the source, from a CSV or a GeoJSON file.

    CSV (``.csv``): header ``x_m,y_m``, ``#`` comments allowed. GeoJSON (``.geojson``,
    ``.json``): lon/lat projected as in step 1 of the module's method; a repeated last
    point is dropped. Facts: ``source`` ("csv" or "geojson"), for GeoJSON ``lon0_deg``,
    ``lat0_deg``, ``projection_error_m`` and ``properties``.

    Raises:
        TrackError: unknown suffix, missing file, malformed content.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".csv", ".geojson", ".json"):
        raise TrackError(f"{p}: unknown centreline format {suffix or '(none)'}; use .csv (x_m,y_m) or .geojson")
    check_readable(p)
    if suffix == ".csv":
        return _read_xy_csv(p), {"source": "csv"}
    lonlat, props = read_geojson_lonlat(p)
    if len(lonlat) > 1 and np.allclose(lonlat[0], lonlat[-1]):
        lonlat = lonlat[:-1]
    lon0, lat0 = (float(v) for v in lonlat.mean(axis=0))
    pts = equirectangular(lonlat, lon0, lat0)
    err = float(np.max(np.hypot(*(pts - enu_exact(lonlat, lon0, lat0)).T)))
    return pts, {"source": "geojson", "lon0_deg": lon0, "lat0_deg": lat0, "projection_error_m": err,
                 "properties": props}


# ---------------------------------------------------------------------- geometry
def wgs84_radii(lat_rad: float) -> tuple[float, float]:
    """Meridional radius M and prime-vertical radius N (m) at a geodetic latitude (rad)."""
    w2 = 1.0 - WGS84_E2 * np.sin(lat_rad) ** 2
    n = WGS84_A_M / np.sqrt(w2)
    m = WGS84_A_M * (1.0 - WGS84_E2) / w2**1.5
    return m, n


def equirectangular(lonlat_deg: np.ndarray, lon0_deg: float, lat0_deg: float) -> np.ndarray:
    """Project lon/lat (deg) to local east/north (m) about (lon0, lat0) with WGS84 radii."""
    lat0 = np.deg2rad(lat0_deg)
    m, n = wgs84_radii(lat0)
    x = n * np.cos(lat0) * np.deg2rad(lonlat_deg[:, 0] - lon0_deg)
    y = m * np.deg2rad(lonlat_deg[:, 1] - lat0_deg)
    return np.column_stack([x, y])


def enu_exact(lonlat_deg: np.ndarray, lon0_deg: float, lat0_deg: float) -> np.ndarray:
    """Exact geodetic -> ECEF -> ENU east/north (m), height 0, about (lon0, lat0)."""

    def ecef(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        return np.column_stack(
            [n * np.cos(lat) * np.cos(lon), n * np.cos(lat) * np.sin(lon), n * (1.0 - WGS84_E2) * np.sin(lat)]
        )

    lon, lat = np.deg2rad(lonlat_deg[:, 0]), np.deg2rad(lonlat_deg[:, 1])
    lon0, lat0 = np.deg2rad(lon0_deg), np.deg2rad(lat0_deg)
    d = ecef(lon, lat) - ecef(np.array([lon0]), np.array([lat0]))
    east = -np.sin(lon0) * d[:, 0] + np.cos(lon0) * d[:, 1]
    north = (
        -np.sin(lat0) * np.cos(lon0) * d[:, 0]
        - np.sin(lat0) * np.sin(lon0) * d[:, 1]
        + np.cos(lat0) * d[:, 2]
    )
    return np.column_stack([east, north])


def signed_area(p: np.ndarray) -> float:
    """Shoelace area (m^2) of a closed polygon (no repeated last vertex); < 0 means clockwise."""
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def fit_periodic_pspline(
    u: np.ndarray,
    points: np.ndarray,
    period: float,
    smoothing_length: float,
    knot_spacing: float = 2.0,
    degree: int = 5,
    penalty_order: int = 3,
) -> interpolate.BSpline:
    """Periodic penalised B-spline fit of ``points`` (n, d) sampled at parameters ``u`` in [0, period).

    Minimises ``sum_i w_i |P(u_i) - p_i|^2 + ell^(2m) * int |P^(m)(u)|^2 du`` with uniform
    weights ``w_i = period / n`` (so the misfit is an integral over u), ``m = penalty_order``
    and ``ell = smoothing_length`` (same unit as u). The penalty integral is approximated by
    m-th differences of the periodic coefficients (uniform knots). Returns a vector-valued
    scipy ``BSpline`` with ``extrapolate='periodic'``.
    """
    n_int = max(int(round(period / knot_spacing)), degree + 2)
    h = period / n_int
    k = degree
    knots = np.arange(-k, n_int + k + 1) * h  # base interval [knots[k], knots[-k-1]] = [0, period]
    design = interpolate.BSpline.design_matrix(np.mod(u, period), knots, k).tocsr()
    n_basis = n_int + k
    fold = sparse.csr_matrix(
        (np.ones(n_basis), (np.arange(n_basis), np.arange(n_basis) % n_int)), shape=(n_basis, n_int)
    )
    basis = design @ fold  # periodic basis: coefficient j and j + n_int are the same
    shift = sparse.csr_matrix(
        (np.ones(n_int), (np.arange(n_int), (np.arange(n_int) + 1) % n_int)), shape=(n_int, n_int)
    )
    diff_op = sparse.identity(n_int, format="csr")
    for _ in range(penalty_order):
        diff_op = (shift - sparse.identity(n_int, format="csr")) @ diff_op
    weight = period / len(u)
    lhs = weight * (basis.T @ basis) + smoothing_length ** (2 * penalty_order) * h ** (
        1 - 2 * penalty_order
    ) * (diff_op.T @ diff_op)
    rhs = weight * (basis.T @ points)
    coef = sparse_linalg.spsolve(lhs.tocsc(), rhs)
    coef = np.asarray(coef).reshape(n_int, -1)
    return interpolate.BSpline(knots, coef[np.arange(n_basis) % n_int], k, extrapolate="periodic")


def _segments_cross(p: np.ndarray) -> list[tuple[int, int]]:
    """Every pair (i, j), i < j, of non-adjacent edges of the closed polygon ``p`` (n, 2) that cross."""
    a, b = p, np.roll(p, -1, axis=0)
    n = len(p)
    idx = np.arange(n)

    def orient(o: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        return (q[..., 0] - o[..., 0]) * (r[..., 1] - o[..., 1]) - (q[..., 1] - o[..., 1]) * (r[..., 0] - o[..., 0])

    pairs: list[tuple[int, int]] = []
    for lo in range(0, n, 256):
        i = idx[lo:lo + 256]
        ai, bi = a[i][:, None, :], b[i][:, None, :]
        d1, d2 = orient(ai, bi, a[None]), orient(ai, bi, b[None])
        d3, d4 = orient(a[None], b[None], ai), orient(a[None], b[None], bi)
        cross = (d1 * d2 < 0) & (d3 * d4 < 0)
        gap = np.abs(i[:, None] - idx[None, :])
        cross &= (np.minimum(gap, n - gap) > 1) & (i[:, None] < idx[None, :])
        pairs += [(int(i[r]), int(c)) for r, c in np.argwhere(cross)]
    return pairs


def _check_crossings(ring: np.ndarray, period: float, origin: str) -> None:
    """Refuse a smoothed centreline ``ring`` (n, 2; evenly spaced over ``period`` m) that crosses itself
    anywhere but at a bridge (module docstring: ``BRIDGE_MIN_ANGLE_DEG``, ``BRIDGE_MIN_LOOP_M``).

    Raises:
        TrackError: naming where the crossing is, at what angle and round how long a loop.
    """
    step = np.roll(ring, -1, axis=0) - ring
    heading = np.arctan2(step[:, 1], step[:, 0])
    for i, j in _segments_cross(ring):
        turn = float(np.degrees(np.abs(np.angle(np.exp(1j * (heading[j] - heading[i]))))))
        angle = min(turn, 180.0 - turn)  # between the two roads, whichever way each is driven
        s_i, s_j = period * i / len(ring), period * j / len(ring)
        loop = min(s_j - s_i, period - (s_j - s_i))
        if angle >= BRIDGE_MIN_ANGLE_DEG and loop >= BRIDGE_MIN_LOOP_M:
            continue  # one pass over the other, as at Suzuka
        raise TrackError(f"{origin}: the smoothed centreline crosses itself (near {s_i:.0f} m and {s_j:.0f} m from "
                         f"the first point, at {angle:.0f} deg, round a loop of {loop:.0f} m); a circuit may cross "
                         f"itself only at a bridge, at more than {BRIDGE_MIN_ANGLE_DEG:.0f} deg with at least "
                         f"{BRIDGE_MIN_LOOP_M:.0f} m of road between the passes")


def check_steerable(track: Track, params: Mapping[str, Any], origin: str) -> None:
    """Refuse a centreline with a corner tighter than the car can steer round.

    The path follower turns the road wheels at most ``steer_slip_margin_rad`` past the
    kinematic angle ``atan(L * kappa)`` and the rack stops at ``max_road_wheel_angle_rad``:
    the tightest radius it can follow is ``L / tan(max_angle - margin)``.

    Raises:
        TrackError: naming the corner (s, radius) and the car's limit.
    """
    wheelbase = float(params["vehicle"]["wheelbase_m"])
    max_angle = float(params["steering"]["max_road_wheel_angle_rad"])
    margin = float(params["driver"]["steer_slip_margin_rad"])
    r_min = wheelbase / np.tan(max(max_angle - margin, 1e-3))
    i = int(np.argmax(np.abs(track.curvature)))
    k = abs(float(track.curvature[i]))
    if k * r_min > 1.0:
        raise TrackError(f"{origin}: the corner at s = {track.s[i]:.0f} m has a radius of {1.0 / k:.1f} m after "
                         f"smoothing, tighter than the car's {r_min:.1f} m at full lock")


# ---------------------------------------------------------------------- derivation
def _close(pts: np.ndarray, origin: str) -> np.ndarray:
    """Drop repeated points and check the loop closes; returns the distinct points in order."""
    if len(pts) < 4:
        raise TrackError(f"{origin}: a closed centreline needs at least 4 distinct points, the file has {len(pts)}")
    keep = np.concatenate([[True], np.hypot(*np.diff(pts, axis=0).T) > 1e-6])
    pts = pts[keep]
    if len(pts) > 1 and np.hypot(*(pts[-1] - pts[0])) <= 1e-6:
        pts = pts[:-1]
    if len(pts) < 4:
        raise TrackError(f"{origin}: a closed centreline needs at least 4 distinct points, got {len(pts)}")
    steps = np.hypot(*np.diff(pts, axis=0).T)
    gap = float(np.hypot(*(pts[-1] - pts[0])))
    if gap > OPEN_GAP_M and gap > OPEN_GAP_RATIO * float(steps.max()):
        raise TrackError(f"{origin}: the centreline is open: its last point is {gap:.0f} m from its first "
                         f"(the longest step between points is {steps.max():.0f} m); list a closed loop")
    return pts


def _arc_parameter(closed: np.ndarray, smoothing_length: float) -> np.ndarray:
    """Distance along the loop (m) at each vertex of ``closed`` (n + 1, 2; last = first).

    A sparse trace (points further apart than about a smoothing length, as a drawn
    polygon) is measured along its own edges. A dense trace (a GPS log, points every
    metre or so) zigzags with its noise, and its edges add up to more than the road's
    length (by half, for 2 m of noise every metre), which would shrink the smoothing
    length measured in metres of road: it is measured along its periodic moving average
    over about two smoothing lengths instead. Only the parameter changes; the fit is still
    to the points themselves.
    """
    seg = np.hypot(*np.diff(closed, axis=0).T)
    pts = closed[:-1]
    n = len(pts)
    k = min(10, n // 2)
    # typical spacing along the road: chords over k points see through the noise of each point
    spacing = float(np.median(np.hypot(*(np.roll(pts, -k, axis=0) - pts).T))) / k
    half = int(smoothing_length / max(spacing, 1e-9))
    if half < 1:
        return np.concatenate([[0.0], np.cumsum(seg)])
    half = min(half, (n - 1) // 2)
    kernel = np.full(2 * half + 1, 1.0 / (2 * half + 1))
    padded = np.concatenate([pts[-half:], pts, pts[:half]])
    mean = np.column_stack([np.convolve(padded[:, j], kernel, mode="valid") for j in range(2)])
    steps = np.hypot(*np.diff(np.vstack([mean, mean[:1]]), axis=0).T)
    return np.concatenate([[0.0], np.cumsum(np.maximum(steps, 1e-6))])


def derive(
    points: np.ndarray,
    *,
    ds: float = 2.0,
    smoothing_length: float = 8.0,
    direction: str | None = None,
    origin: str = "centreline",
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Close, smooth and resample a loop of points (n, 2) in metres, in the order of travel.

    Args:
        points: the loop, first point not repeated (a repeated one is dropped).
        ds: resampling step (m), approximate (the lap is split into equal steps).
        smoothing_length: P-spline smoothing length ell (m); cut-off wavelength ~ 2 pi ell.
        direction: None (as listed), "clockwise" or "counter-clockwise" (points
            reversed if they run the other way, first point kept first).
        origin: the file or name quoted in error messages.

    Returns:
        The columns ``s_m, x_m, y_m, heading_rad, curvature_1pm`` (closing sample
        included) and facts (length, input order, fit quality...).

    Raises:
        TrackError: too few points, an open loop, too short or too long, or a centreline that
            crosses itself other than at a bridge.
    """
    if direction not in (None, "clockwise", "counter-clockwise"):
        raise ValueError(f"direction must be None, 'clockwise' or 'counter-clockwise', got {direction!r}")
    pts = _close(np.asarray(points, dtype=float), origin)
    area = signed_area(pts)
    facts: dict[str, Any] = {"signed_area_m2": area, "input_order": "clockwise" if area < 0 else "counter-clockwise",
                             "n_points": len(pts)}
    if direction is not None and facts["input_order"] != direction:
        pts = np.vstack([pts[:1], pts[:0:-1]])
    closed = np.vstack([pts, pts[:1]])
    # the length along the points, before any work is sized by it (points every metre, knots every 2 m, a
    # 5 cm arc-length grid; up to here the work is linear in the number of points), and before the smoothing
    # length is measured in steps between points (a file in km has thousands in 8 "m")
    check_lap_length(float(np.sum(np.hypot(*np.diff(closed, axis=0).T))), origin)
    u_vert = _arc_parameter(closed, smoothing_length)
    period = float(u_vert[-1])
    facts.update(polygon_length_m=period, mean_spacing_m=period / len(pts))
    check_lap_length(period, origin)  # a dense trace is measured along its moving average: shorter

    n_dense = int(round(period / 1.0))
    u_dense = np.arange(n_dense) * (period / n_dense)
    dense = np.column_stack(
        [np.interp(u_dense, u_vert, closed[:, 0]), np.interp(u_dense, u_vert, closed[:, 1])]
    )
    spline = fit_periodic_pspline(u_dense, dense, period, smoothing_length)
    cols = _resample(spline, period, pts[0], ds, facts)
    ring = spline(np.linspace(0.0, period, max(int(period / _CROSSING_STEP_M), 8), endpoint=False))
    _check_crossings(ring, period, origin)
    # fit quality: distance from each input point to the smooth curve (sampled every 0.25 m)
    dev, _ = cKDTree(spline(np.linspace(0.0, period, int(period / 0.25), endpoint=False))).query(pts)
    facts.update(vertex_dev_max_m=float(dev.max()), vertex_dev_rms_m=float(np.sqrt(np.mean(dev**2))),
                 total_turn_rad=float(cols["heading_rad"][-1] - cols["heading_rad"][0]),
                 smoothing_length_m=smoothing_length)
    return cols, facts


def _resample(spline: interpolate.BSpline, period: float, first: np.ndarray, ds: float,
              facts: dict[str, Any]) -> dict[str, np.ndarray]:
    """Sample the closed spline every ~ds m of arc length from its point nearest ``first``."""
    d1, d2 = spline.derivative(1), spline.derivative(2)
    # arc length along the spline parameter (fine trapezoid; the curve is smooth)
    n_fine = int(round(period / 0.05))
    u_fine = np.arange(n_fine + 1) * (period / n_fine)
    speed = np.hypot(*d1(u_fine).T)
    s_fine = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(u_fine))])
    length = float(s_fine[-1])
    p_fine = spline(u_fine[:-1])
    i0 = int(np.argmin(np.hypot(*(p_fine - first).T)))
    u_start, s_start = float(u_fine[i0]), float(s_fine[i0])
    facts["start_offset_m"] = float(np.hypot(*(p_fine[i0] - first)))

    n_samples = int(round(length / ds))
    s_out = np.arange(n_samples + 1) * (length / n_samples)
    s_on_param = np.mod(s_out + s_start, length)
    s_on_param[-1] = s_start  # closing row: exactly the first position
    u_out = np.interp(s_on_param, s_fine, u_fine)
    u_out[-1] = u_start
    u_out[0] = u_start
    xy, dxy, ddxy = spline(u_out), d1(u_out), d2(u_out)
    heading = np.unwrap(np.arctan2(dxy[:, 1], dxy[:, 0]))
    heading[-1] = heading[0] + np.round((heading[-2] - heading[0]) / (2 * np.pi)) * 2 * np.pi
    curvature = (dxy[:, 0] * ddxy[:, 1] - dxy[:, 1] * ddxy[:, 0]) / np.hypot(*dxy.T) ** 3
    facts.update(length_m=length, ds_m=length / n_samples, n_samples=n_samples)
    return {"s_m": s_out, "x_m": xy[:, 0], "y_m": xy[:, 1], "heading_rad": heading, "curvature_1pm": curvature}


def track_from_points(points: np.ndarray, origin: str, **kwargs: Any) -> Track:
    """:func:`derive` as a :class:`~sim.track.Track` (same arguments and errors)."""
    cols, _ = derive(points, origin=origin, **kwargs)
    return Track(cols["s_m"], cols["x_m"], cols["y_m"], cols["heading_rad"], cols["curvature_1pm"],
                 float(cols["s_m"][-1]))
