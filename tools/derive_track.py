#!/usr/bin/env python3
"""Derive the bundled Magny-Cours centreline CSV from a GeoJSON trace.

Usage::

    python tools/derive_track.py GEOJSON OUTPUT_CSV [--ds 2.0] [--smoothing-length 8.0]

The project's file was made with::

    python tools/derive_track.py <path>/magny-cours_fr-1960.geojson sim/data/magny_cours_centreline.csv

Input: the Circuit de Nevers Magny-Cours centreline from bacinger/f1-circuits
(``circuits/fr-1960.geojson``, MIT licence): 95 WGS84 lon/lat points, the last
one repeating the first, stated length 4412 m.

Method
------
1. **Projection.** Equirectangular projection about the centroid of the
   points, using the WGS84 radii of curvature at the centroid latitude
   (prime vertical N for east, meridional M for north)::

       x = N(lat0) cos(lat0) (lon - lon0),   y = M(lat0) (lat - lat0)    [m]

   x points east, y north, z up (an ENU frame, ISO 8855 earth-fixed axes).
   Over the ~1 km extent of the circuit the east scale varies by
   tan(lat0) * dlat < 1e-4, i.e. a few centimetres; the script measures the
   error against an exact geodetic -> ECEF -> ENU transformation and prints it.
2. **Direction.** The shoelace (signed) area tells whether the points run
   clockwise (negative area with x east, y north) or counter-clockwise.
   Magny-Cours is raced clockwise; the points are reversed (keeping the
   first point first) only if they run the other way. The script prints
   what it finds.
3. **Smoothing.** The trace is a polygon: long straights have vertices
   up to 350 m apart and corners are drawn with vertices 7-10 m apart and
   vertex turns up to 65 deg. The polygon is sampled every 1 m along its
   edges (so straights stay straight) and fitted with a *periodic penalised
   quintic B-spline* (P-spline, Eilers & Marx): uniform knots every ~2 m, the
   least-squares misfit to the polygon plus ``ell**6 * int |P'''(u)|**2 du``.
   The third-derivative penalty acts on the rate of change of curvature, so
   curvature varies smoothly (clothoid-like) rather than in kinks. For a
   sinusoidal wiggle of wavelength lambda the fit keeps the fraction
   1 / (1 + (2 pi ell / lambda)**6): with ell = 8 m features shorter than
   about 2 pi ell = 50 m (the trace's mean vertex spacing is 47 m) are
   treated as tracing noise.
   scipy's ``splprep(per=1, s=...)`` was tried first: its automatic knot
   placement packs knots at the polygon's corners and gives radii of 4-6 m.
4. **Resampling.** The spline is parametrised by true arc length. The lap
   starts at the point of the spline closest to the first GeoJSON point
   (on the start/finish straight) and is sampled every ``L/N`` metres with
   ``N = round(L/ds)`` (uniform, ~2 m); a closing row at ``s = L`` repeats the
   first position, its heading lowered by 2 pi (clockwise lap).
   Heading (rad, from +x towards +y, unwrapped) and curvature
   (1/m, positive to the left) are computed analytically from the spline.

Output columns: ``s_m,x_m,y_m,heading_rad,curvature_1pm``, preceded by ``#``
comment lines that name the source, licence, and derivation command.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg
from scipy import interpolate

# WGS84 ellipsoid.
WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)

STATED_LENGTH_M = 4412.0  # "length" property of the GeoJSON feature
SOURCE = "bacinger/f1-circuits circuits/fr-1960.geojson (Circuit de Nevers Magny-Cours)"
LICENCE = "MIT License, Copyright (c) 2019 Tomislav Bacinger, https://github.com/bacinger/f1-circuits"
COLUMNS = "s_m,x_m,y_m,heading_rad,curvature_1pm"


def read_geojson_lonlat(path: Path) -> tuple[np.ndarray, dict]:
    """Return the (n, 2) lon/lat array [deg] of the first LineString and its properties."""
    data = json.loads(path.read_text(encoding="utf-8"))
    features = data["features"] if data.get("type") == "FeatureCollection" else [data]
    for feature in features:
        geometry = feature.get("geometry") or {}
        if geometry.get("type") == "LineString":
            return np.asarray(geometry["coordinates"], dtype=float)[:, :2], feature.get("properties", {})
    raise ValueError(f"{path}: no LineString feature found")


def wgs84_radii(lat_rad: float) -> tuple[float, float]:
    """Meridional radius M and prime-vertical radius N [m] at a geodetic latitude [rad]."""
    w2 = 1.0 - WGS84_E2 * np.sin(lat_rad) ** 2
    n = WGS84_A_M / np.sqrt(w2)
    m = WGS84_A_M * (1.0 - WGS84_E2) / w2**1.5
    return m, n


def equirectangular(lonlat_deg: np.ndarray, lon0_deg: float, lat0_deg: float) -> np.ndarray:
    """Project lon/lat [deg] to local east/north [m] about (lon0, lat0) with WGS84 radii."""
    lat0 = np.deg2rad(lat0_deg)
    m, n = wgs84_radii(lat0)
    x = n * np.cos(lat0) * np.deg2rad(lonlat_deg[:, 0] - lon0_deg)
    y = m * np.deg2rad(lonlat_deg[:, 1] - lat0_deg)
    return np.column_stack([x, y])


def enu_exact(lonlat_deg: np.ndarray, lon0_deg: float, lat0_deg: float) -> np.ndarray:
    """Exact geodetic -> ECEF -> ENU east/north [m] (height 0) about (lon0, lat0); for the error check."""

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
    """Shoelace area [m^2] of a closed polygon (no repeated last vertex); < 0 means clockwise."""
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
    and ``ell = smoothing_length`` [same unit as u]. The penalty integral is approximated by
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


def derive(
    lonlat_deg: np.ndarray, ds: float, smoothing_length: float
) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """Run the derivation; return the resampled columns and a dict of facts for the report/header."""
    facts: dict[str, object] = {}
    if np.allclose(lonlat_deg[0], lonlat_deg[-1]):
        lonlat_deg = lonlat_deg[:-1]
        facts["closed_input"] = True
    else:
        facts["closed_input"] = False
    lon0, lat0 = (float(v) for v in lonlat_deg.mean(axis=0))
    facts["lon0_deg"], facts["lat0_deg"] = lon0, lat0
    pts = equirectangular(lonlat_deg, lon0, lat0)
    facts["projection_error_m"] = float(np.max(np.hypot(*(pts - enu_exact(lonlat_deg, lon0, lat0)).T)))

    area = signed_area(pts)
    facts["signed_area_m2"] = area
    facts["input_order"] = "clockwise" if area < 0 else "counter-clockwise"
    if area > 0:  # make it clockwise (race direction), keeping the first point first
        pts = np.vstack([pts[:1], pts[:0:-1]])
        lonlat_deg = np.vstack([lonlat_deg[:1], lonlat_deg[:0:-1]])

    closed = np.vstack([pts, pts[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    u_vert = np.concatenate([[0.0], np.cumsum(seg)])
    period = float(u_vert[-1])
    facts["polygon_length_m"] = period
    facts["n_points"] = len(pts)
    facts["mean_spacing_m"] = period / len(pts)

    n_dense = int(round(period / 1.0))
    u_dense = np.arange(n_dense) * (period / n_dense)
    dense = np.column_stack(
        [np.interp(u_dense, u_vert, closed[:, 0]), np.interp(u_dense, u_vert, closed[:, 1])]
    )
    spline = fit_periodic_pspline(u_dense, dense, period, smoothing_length)
    d1 = spline.derivative(1)
    d2 = spline.derivative(2)

    # Arc length along the spline parameter (fine trapezoid; the curve is smooth).
    n_fine = int(round(period / 0.05))
    u_fine = np.arange(n_fine + 1) * (period / n_fine)
    speed = np.hypot(*d1(u_fine).T)
    s_fine = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(u_fine))])
    length = float(s_fine[-1])

    # Lap start: the spline point closest to the first GeoJSON point.
    p_fine = spline(u_fine[:-1])
    i0 = int(np.argmin(np.hypot(*(p_fine - pts[0]).T)))
    u_start, s_start = float(u_fine[i0]), float(s_fine[i0])
    facts["start_offset_m"] = float(np.hypot(*(p_fine[i0] - pts[0])))

    n_samples = int(round(length / ds))
    s_out = np.arange(n_samples + 1) * (length / n_samples)
    s_on_param = np.mod(s_out + s_start, length)
    s_on_param[-1] = s_start  # closing row: exactly the first position
    u_out = np.interp(s_on_param, s_fine, u_fine)
    u_out[-1] = u_start
    u_out[0] = u_start
    xy = spline(u_out)
    dxy = d1(u_out)
    ddxy = d2(u_out)
    heading = np.unwrap(np.arctan2(dxy[:, 1], dxy[:, 0]))
    heading[-1] = heading[0] + np.round((heading[-2] - heading[0]) / (2 * np.pi)) * 2 * np.pi
    curvature = (dxy[:, 0] * ddxy[:, 1] - dxy[:, 1] * ddxy[:, 0]) / np.hypot(*dxy.T) ** 3

    # Fit quality: distance from each GeoJSON vertex to the smooth curve.
    tree_pts = spline(np.linspace(0.0, period, int(period / 0.25), endpoint=False))
    dev = np.min(np.hypot(*(tree_pts[None, :, :] - pts[:, None, :]).transpose(2, 0, 1)), axis=1)
    facts.update(
        length_m=length,
        ds_m=length / n_samples,
        n_samples=n_samples,
        vertex_dev_max_m=float(dev.max()),
        vertex_dev_rms_m=float(np.sqrt(np.mean(dev**2))),
        total_turn_rad=float(heading[-1] - heading[0]),
    )
    cols = {
        "s_m": s_out,
        "x_m": xy[:, 0],
        "y_m": xy[:, 1],
        "heading_rad": heading,
        "curvature_1pm": curvature,
    }
    return cols, facts


def tightest_corners(s: np.ndarray, curvature: np.ndarray, count: int = 6, separation_m: float = 60.0):
    """Return [(s, curvature)] of the ``count`` largest |curvature| peaks at least ``separation_m`` apart."""
    picks: list[int] = []
    for i in np.argsort(-np.abs(curvature)):
        if all(abs(s[i] - s[j]) > separation_m for j in picks):
            picks.append(int(i))
        if len(picks) >= count:
            break
    return [(float(s[i]), float(curvature[i])) for i in picks]


def write_csv(path: Path, cols: dict[str, np.ndarray], facts: dict[str, object], command: str) -> None:
    """Write the centreline CSV with its provenance header."""
    header = [
        "Circuit de Nevers Magny-Cours centreline: metric, closed, smoothed; lap clockwise (race direction).",
        f"Source: {SOURCE}.",
        f"Licence of the source data: {LICENCE}.",
        f"Derived with: {command}",
        "Projection: equirectangular about the point centroid "
        f"(lon0 {facts['lon0_deg']:.7f} deg, lat0 {facts['lat0_deg']:.7f} deg) with WGS84 radii; "
        f"x east, y north [m]; max deviation from exact ENU {facts['projection_error_m'] * 100:.2f} cm.",
        f"Smoothing: periodic penalised quintic B-spline, knots every ~2 m, 3rd-derivative penalty, "
        f"smoothing length {facts['smoothing_length_m']:g} m; GeoJSON vertices within "
        f"{facts['vertex_dev_max_m']:.2f} m (rms {facts['vertex_dev_rms_m']:.2f} m) of the curve.",
        f"Length {facts['length_m']:.1f} m (stated 4412 m); {facts['n_samples']} steps of "
        f"{facts['ds_m']:.4f} m; last row closes the lap (s = length, heading - 2 pi).",
        "Lap starts at the spline point nearest the first GeoJSON point (start/finish straight).",
        "heading_rad: angle of the tangent from +x towards +y, unwrapped; curvature_1pm: > 0 turning left.",
    ]
    data = np.column_stack([cols[name] for name in COLUMNS.split(",")])
    with path.open("w", encoding="utf-8", newline="\n") as fh:
        for line in header:
            fh.write(f"# {line}\n")
        fh.write(COLUMNS + "\n")
        np.savetxt(fh, data, fmt=["%.4f", "%.4f", "%.4f", "%.8f", "%.8f"], delimiter=",")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("geojson", type=Path, help="centreline GeoJSON (LineString of lon/lat points)")
    parser.add_argument("output", type=Path, help="output CSV path")
    parser.add_argument("--ds", type=float, default=2.0, help="resampling step [m] (default 2)")
    parser.add_argument(
        "--smoothing-length",
        type=float,
        default=8.0,
        help="P-spline smoothing length ell [m]; cut-off wavelength ~ 2 pi ell (default 8)",
    )
    args = parser.parse_args(argv)
    if not args.geojson.is_file():
        print(f"error: {args.geojson}: no such file", file=sys.stderr)
        return 2

    lonlat, props = read_geojson_lonlat(args.geojson)
    cols, facts = derive(lonlat, args.ds, args.smoothing_length)
    facts["smoothing_length_m"] = args.smoothing_length
    command = (
        f"python tools/derive_track.py {args.geojson.name} {args.output.as_posix()} "
        f"--ds {args.ds:g} --smoothing-length {args.smoothing_length:g}"
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    write_csv(args.output, cols, facts, command)

    stated = float(props.get("length", STATED_LENGTH_M))
    length = float(facts["length_m"])
    s, kappa = cols["s_m"], cols["curvature_1pm"]
    print(
        f"input: {facts['n_points']} distinct points (closed input: {facts['closed_input']}), "
        f"mean spacing {facts['mean_spacing_m']:.1f} m, polygon length {facts['polygon_length_m']:.1f} m"
    )
    print(
        f"projection: equirectangular about ({facts['lon0_deg']:.6f}, {facts['lat0_deg']:.6f}); "
        f"max error vs exact ENU {facts['projection_error_m'] * 100:.2f} cm"
    )
    print(
        f"GeoJSON point order: {facts['input_order']} (signed area {facts['signed_area_m2']:.0f} m^2); "
        "race direction: clockwise" + (" (points reversed)" if facts["input_order"] != "clockwise" else "")
    )
    print(
        f"smoothing length {args.smoothing_length:g} m: vertices within {facts['vertex_dev_max_m']:.2f} m "
        f"(rms {facts['vertex_dev_rms_m']:.2f} m); lap start {facts['start_offset_m']:.2f} m from point 0"
    )
    print(f"length: {length:.1f} m vs stated {stated:.0f} m ({100 * (length / stated - 1):+.2f} %)")
    print(f"total heading change: {facts['total_turn_rad'] / (2 * np.pi):+.4f} turns")
    print(
        f"curvature: min {kappa.min():+.4f} 1/m (right, R {1 / abs(kappa.min()):.1f} m at s "
        f"{s[np.argmin(kappa)]:.0f} m), max {kappa.max():+.4f} 1/m (left, R {1 / kappa.max():.1f} m at s "
        f"{s[np.argmax(kappa)]:.0f} m)"
    )
    print(
        "tightest corners (s [m], R [m], side): "
        + ", ".join(
            f"({sc:.0f}, {1 / abs(kc):.1f}, {'L' if kc > 0 else 'R'})"
            for sc, kc in tightest_corners(s, kappa)
        )
    )
    print(f"wrote {args.output} ({facts['n_samples'] + 1} rows)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
