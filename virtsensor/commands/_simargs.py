"""Options shared by the commands that run the simulator (simulate, campaign, replay).

The simulator is a separate package (``sim``); only these command-line front
ends import it, never the runtime.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from virtsensor.errors import UserError


def add_car_arguments(parser: argparse.ArgumentParser) -> None:
    """--set, --params, --pressure-bar, --tyre."""
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.NAME=VALUE",
                        help="override one car parameter (repeatable), e.g. --set vehicle.mass_kg=1600")
    parser.add_argument("--params", dest="param_files", action="append", default=[], metavar="FILE.toml",
                        help="TOML file of parameter overrides, same shape as sim/data/car_c_segment.toml")
    parser.add_argument("--pressure-bar", type=float, default=None, metavar="P",
                        help="inflation pressure of all four tyres (gauge, bar)")
    parser.add_argument("--tyre", default=None, metavar="FILE.tir",
                        help="MF 6.1 tyre property file of all four wheels, or a bundled tyre's name (see "
                             "'virtsensor tyre'); checked before any work; the same as --set tyres.file=FILE")


@contextmanager
def sim_errors() -> Iterator[None]:
    """Turn the simulator's input errors into one-line user errors (exit code 2)."""
    from sim.manoeuvres import ManoeuvreError
    from sim.params import ParamError
    from sim.tir import TirError

    try:
        yield
    except (ManoeuvreError, ParamError, TirError) as exc:
        raise UserError(str(exc)) from None


def car_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The car's parameter tree from --params, --set, --tyre and --pressure-bar (validated)."""
    from sim.api import with_pressure
    from sim.params import ParamError, car_parameters
    from sim.sensors import check_specs
    from sim.vehicle import tyre_for

    tyre_file = _tyre_option(args)  # --tyre FILE is --set tyres.file=<its absolute path>
    overrides = [*args.overrides, *([f"tyres.file={tyre_file}"] if tyre_file is not None else [])]
    with sim_errors():
        params = car_parameters(overrides, args.param_files)
        try:
            params = with_pressure(params, args.pressure_bar)
            check_specs(params)
        except ValueError as exc:
            raise ParamError(str(exc)) from None
        tyre_for(params)  # a malformed or missing .tir is reported now, before any work
    return params


def _tyre_option(args: argparse.Namespace) -> str | None:
    """The checked --tyre file as an absolute path (None without --tyre); UserError names what is wrong."""
    name = getattr(args, "tyre", None)
    if name is None:
        return None
    if any(o.split("=", 1)[0].strip() == "tyres.file" for o in args.overrides):
        raise UserError("--tyre and --set tyres.file=... both name the tyre file; give one of them")
    from virtsensor.tyres import check_tyre_file

    return str(check_tyre_file(name).path.resolve())
