#!/usr/bin/env python3
"""Derive the tyre reference table of the tests from the shared MF 6.1 reference CSV.

Usage::

    python tools/derive_tyre_reference.py REFERENCE_CSV OUTPUT_CSV_GZ

The project's file was made with::

    python tools/derive_tyre_reference.py <path>/tyre/mf61_reference.csv tests/data/mf61_reference.csv.gz

Input: Fx, Fy, Mz of the two 255/55 R20 MF 6.1 files that circulate as
``MagicFormula61_Parameters.tir`` (the Simscape Vehicle Templates copy and MFeval's
own example), steady state (useMode 121, limits on, no turn slip, ISO-W, Vx 20 m/s)
over load, pressure, camber, kappa and slip angle, computed with an independent
numpy port of MFeval's solver equations (one row per point, slip angle in rad
rounded to 9 decimals).

Output: the same rows and the same output figures (copied as text, no rounding
added), with

* the file column renamed to the name of the bundled copy in ``sim/data/tyres``;
* the slip angle as the whole number of degrees it was computed from (the 9-decimal
  radian value alone moves Fy near the peak by ~1e-8 of its peak, more than the
  tolerance the test checks); the tool refuses a row whose angle is not within
  1e-9 rad of a whole degree;
* the constant speed (20 m/s) in the header instead of a column;

gzip-compressed (about a quarter of the size).
"""

from __future__ import annotations

import argparse
import csv
import gzip
import io
import math
import sys
from pathlib import Path

#: shared file name -> bundled copy
BUNDLED = {
    "MagicFormula61_Parameters.tir": "mf61_255_55R20.tir",
    "MagicFormula61_Parameters.mfeval.tir": "mf61_mfeval_255_55R20.tir",
}
VX = 20.0
COLUMNS = ["tyre", "fz_n", "pressure_pa", "camber_rad", "kappa", "alpha_deg", "fx_n", "fy_n", "mz_nm"]


def derive(src: Path, dst: Path) -> int:
    """Write ``dst`` from ``src``; returns the number of rows. Raises ValueError on unexpected input."""
    with src.open(newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].startswith("#")]
    header, body = rows[0], rows[1:]
    expected = ["file", "fz_n", "pressure_pa", "camber_rad", "kappa", "alpha_rad", "vx_mps", "fx_n", "fy_n", "mz_nm"]
    if header != expected:
        raise ValueError(f"{src}: unexpected columns {header}")
    out = []
    for lineno, r in enumerate(body, start=2):
        deg = round(math.degrees(float(r[5])))
        if abs(math.radians(deg) - float(r[5])) > 1e-9 or float(r[6]) != VX or r[0] not in BUNDLED:
            raise ValueError(f"{src}: row {lineno} is not on the expected grid: {r}")
        out.append([BUNDLED[r[0]], r[1], r[2], r[3], r[4], str(deg), r[7], r[8], r[9]])
    # no name and a fixed time in the gzip header: the same input gives the same bytes
    with dst.open("wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0, compresslevel=9) as gz, \
            io.TextIOWrapper(gz, encoding="ascii", newline="") as fh:
        fh.write("# MF 6.1 steady state, useMode 121 (limits on, alpha* = tan(alpha), no turn slip), ISO-W, SI units,\n"
                 f"# Vx = {VX:g} m/s; alpha_deg: slip angle in whole degrees (alpha = alpha_deg * pi / 180 rad).\n"
                 "# Computed with an independent numpy port of MFeval's solver equations; derived by\n"
                 "# tools/derive_tyre_reference.py (see there and NOTICE).\n")
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(COLUMNS)
        writer.writerows(out)
    return len(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reference_csv", type=Path)
    ap.add_argument("output", type=Path)
    args = ap.parse_args(argv)
    n = derive(args.reference_csv, args.output)
    print(f"{args.output}: {n} rows, {args.output.stat().st_size} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
