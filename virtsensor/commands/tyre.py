"""``virtsensor tyre``: check a ``.tir`` tyre property file and print the figures an engineer checks first.

Examples::

    virtsensor tyre my_tyre.tir                           # checks, then the figures as a table
    virtsensor tyre mf61_mfeval_255_55R20                 # a bundled tyre, by name
    virtsensor tyre my_tyre.tir --json figures.json --plot curves.png
    virtsensor tyre my_tyre.tir --set LMUY=0.7            # the same tyre on a 30 % less grippy surface

A malformed file (syntax, non-SI units, FITTYP other than 61/62, a missing coefficient that
MF 6.1 has no default for, a value that is not a number, a load, size, pressure, speed or
stiffness in the wrong unit, a coefficient that makes the Magic Formula overflow) is refused
with one line naming the file, the key and the line (exit code 2). See :mod:`virtsensor.tyres`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "check a .tir tyre property file; cornering stiffness, Fy and Mz peaks, trail, slip stiffness, pressure"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from virtsensor.commands import _types as t

    parser.add_argument("file", metavar="FILE.tir", type=t.tyre_spec(axles=False),
                        help="tyre property file, or the name of a bundled tyre")
    parser.add_argument("--json", dest="json_path", metavar="FILE", default=None, type=t.output_file_or_stdout(),
                        help="write the figures as JSON ('-': to standard output instead of the table)")
    parser.add_argument("--plot", metavar="FILE.png", default=None, type=t.output_file(".png"),
                        help="PNG of Fy, Mz against slip angle and Fx against kappa, 3 loads, 2 pressures "
                             "(needs matplotlib: the 'plots' extra)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="replace one coefficient of the file (repeatable), e.g. --set LMUY=0.7")


def run(args: argparse.Namespace) -> int:
    from virtsensor.fileio import check_writable, dumps, staged_files
    from virtsensor.tyres import (
        check_tyre_file,
        format_report,
        parse_overrides,
        plot_curves,
        require_matplotlib,
        tyre_figures,
    )

    overrides = parse_overrides(args.overrides)
    json_path = None if args.json_path in (None, "-") else Path(args.json_path)
    plot_path = None if args.plot is None else Path(args.plot)
    if json_path is not None:
        check_writable(json_path, "--json")
    if plot_path is not None:
        require_matplotlib()
        check_writable(plot_path, "--plot")
    tyre = check_tyre_file(args.file, overrides)
    figures = tyre_figures(tyre)
    if args.json_path == "-":
        sys.stdout.write(dumps(figures) + "\n")
    else:
        print(format_report(figures))
    for path in (json_path, plot_path):
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
    with staged_files(json_path, plot_path) as (json_tmp, plot_tmp):  # (both or neither)
        if json_tmp is not None:
            json_tmp.write_text(dumps(figures) + "\n", encoding="utf-8")
        if plot_tmp is not None:
            plot_curves(tyre, plot_tmp)
    if plot_path is not None:
        print(f"plot: {plot_path}", file=sys.stderr)
    return 0
