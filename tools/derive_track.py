#!/usr/bin/env python3
"""Derive a bundled circuit centreline CSV from a GeoJSON trace of bacinger/f1-circuits.

Usage::

    python tools/derive_track.py GEOJSON OUTPUT_CSV [--ds 2.0] [--smoothing-length 8.0] [--direction D]

The computation is the library's (:mod:`sim.centreline`, the same code ``virtsensor
simulate circuit`` runs on any centreline); this tool adds the provenance header and a
report. The project's files were made with (GeoJSON files from bacinger/f1-circuits,
``circuits/<code>.geojson``, MIT licence, saved under the names shown)::

    python tools/derive_track.py magny-cours_fr-1960.geojson sim/data/magny_cours_centreline.csv
    python tools/derive_track.py hungaroring_hu-1986.geojson sim/data/tracks/hungaroring.csv
    python tools/derive_track.py zandvoort_nl-1948.geojson sim/data/tracks/zandvoort.csv
    python tools/derive_track.py red-bull-ring_at-1969.geojson sim/data/tracks/red_bull_ring.csv

Magny-Cours (``circuits/fr-1960.geojson``): 95 WGS84 lon/lat points, the last one
repeating the first, stated length 4412 m. All four are raced clockwise (the default
``--direction``).

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
   The circuits bundled are raced clockwise; the points are reversed (keeping
   the first point first) only if they run the other way. The script prints
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
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from sim.centreline import derive, read_points  # noqa: E402
from sim.track import TrackError  # noqa: E402

REPOSITORY = "bacinger/f1-circuits"
LICENCE = "MIT License, Copyright (c) 2019 Tomislav Bacinger, https://github.com/bacinger/f1-circuits"
COLUMNS = "s_m,x_m,y_m,heading_rad,curvature_1pm"


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
    props = facts["properties"]
    name, code = props.get("Name", "circuit"), props.get("id", "?")
    direction = facts["direction"]
    turn = "heading - 2 pi" if direction == "clockwise" else "heading + 2 pi"
    header = [
        f"{name} centreline: metric, closed, smoothed; lap {direction} (race direction).",
        f"Source: {REPOSITORY} circuits/{code}.geojson ({name}).",
        f"Licence of the source data: {LICENCE}.",
        f"Derived with: {command}",
        "Projection: equirectangular about the point centroid "
        f"(lon0 {facts['lon0_deg']:.7f} deg, lat0 {facts['lat0_deg']:.7f} deg) with WGS84 radii; "
        f"x east, y north [m]; max deviation from exact ENU {facts['projection_error_m'] * 100:.2f} cm.",
        f"Smoothing: periodic penalised quintic B-spline, knots every ~2 m, 3rd-derivative penalty, "
        f"smoothing length {facts['smoothing_length_m']:g} m; GeoJSON vertices within "
        f"{facts['vertex_dev_max_m']:.2f} m (rms {facts['vertex_dev_rms_m']:.2f} m) of the curve.",
        f"Length {facts['length_m']:.1f} m (stated {float(props.get('length', float('nan'))):.0f} m); "
        f"{facts['n_samples']} steps of {facts['ds_m']:.4f} m; last row closes the lap (s = length, {turn}).",
        "Lap starts at the spline point nearest the first GeoJSON point (start/finish straight).",
        "heading_rad: angle of the tangent from +x towards +y, unwrapped; curvature_1pm: > 0 turning left.",
    ]
    data = np.column_stack([cols[name] for name in COLUMNS.split(",")])
    with path.open("w", encoding="utf-8", newline="\n") as fh:
        for line in header:
            fh.write(f"# {line}\n")
        fh.write(COLUMNS + "\n")
        np.savetxt(fh, data, fmt=["%.4f", "%.4f", "%.4f", "%.8f", "%.8f"], delimiter=",")


def report(facts: dict[str, object], cols: dict[str, np.ndarray], output: Path) -> None:
    """Print what the derivation found."""
    props = facts["properties"]
    length = float(facts["length_m"])
    stated = float(props.get("length", length))
    s, kappa = cols["s_m"], cols["curvature_1pm"]
    print(f"input: {facts['n_points']} distinct points, mean spacing {facts['mean_spacing_m']:.1f} m, "
          f"polygon length {facts['polygon_length_m']:.1f} m")
    print(f"projection: equirectangular about ({facts['lon0_deg']:.6f}, {facts['lat0_deg']:.6f}); "
          f"max error vs exact ENU {facts['projection_error_m'] * 100:.2f} cm")
    print(f"GeoJSON point order: {facts['input_order']} (signed area {facts['signed_area_m2']:.0f} m^2); "
          f"race direction: {facts['direction']}"
          + (" (points reversed)" if facts["input_order"] != facts["direction"] else ""))
    print(f"smoothing length {facts['smoothing_length_m']:g} m: vertices within {facts['vertex_dev_max_m']:.2f} m "
          f"(rms {facts['vertex_dev_rms_m']:.2f} m); lap start {facts['start_offset_m']:.2f} m from point 0")
    print(f"length: {length:.1f} m vs stated {stated:.0f} m ({100 * (length / stated - 1):+.2f} %)")
    print(f"total heading change: {facts['total_turn_rad'] / (2 * np.pi):+.4f} turns")
    print(f"curvature: min {kappa.min():+.4f} 1/m (right, R {1 / abs(kappa.min()):.1f} m at s "
          f"{s[np.argmin(kappa)]:.0f} m), max {kappa.max():+.4f} 1/m (left, R {1 / kappa.max():.1f} m at s "
          f"{s[np.argmax(kappa)]:.0f} m)")
    print("tightest corners (s [m], R [m], side): " + ", ".join(
        f"({sc:.0f}, {1 / abs(kc):.1f}, {'L' if kc > 0 else 'R'})" for sc, kc in tightest_corners(s, kappa)))
    print(f"wrote {output} ({facts['n_samples'] + 1} rows)")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("geojson", type=Path, help="centreline GeoJSON (LineString of lon/lat points)")
    parser.add_argument("output", type=Path, help="output CSV path")
    parser.add_argument("--ds", type=float, default=2.0, help="resampling step [m] (default 2)")
    parser.add_argument("--smoothing-length", type=float, default=8.0,
                        help="P-spline smoothing length ell [m]; cut-off wavelength ~ 2 pi ell (default 8)")
    parser.add_argument("--direction", choices=("clockwise", "counter-clockwise"), default="clockwise",
                        help="race direction (default clockwise)")
    args = parser.parse_args(argv)
    if args.geojson.suffix.lower() not in (".geojson", ".json"):
        print(f"error: {args.geojson}: expected a .geojson file", file=sys.stderr)
        return 2
    try:
        points, facts = read_points(args.geojson)
        cols, derived = derive(points, ds=args.ds, smoothing_length=args.smoothing_length,
                               direction=args.direction, origin=str(args.geojson))
    except TrackError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    facts.update(derived, direction=args.direction)
    command = (
        f"python tools/derive_track.py {args.geojson.name} {args.output.as_posix()} "
        f"--ds {args.ds:g} --smoothing-length {args.smoothing_length:g}"
        + ("" if args.direction == "clockwise" else f" --direction {args.direction}")
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    write_csv(args.output, cols, facts, command)
    report(facts, cols, args.output)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
