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
    """--set, --params, --pressure-bar."""
    from virtsensor.commands import _types as t

    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.NAME=VALUE",
                        help="override one car parameter (repeatable), e.g. --set vehicle.mass_kg=1600")
    parser.add_argument("--params", dest="param_files", action="append", default=[], metavar="FILE.toml",
                        type=t.text_file(),
                        help="TOML file of parameter overrides, same shape as sim/data/car_c_segment.toml")
    parser.add_argument("--pressure-bar", type=t.positive_float(10.0), default=None, metavar="P",
                        help="inflation pressure of all four tyres (gauge, bar; > 0 and <= 10, the tyre "
                             "file sets the usable range)")


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
    """The car's parameter tree from --params, --set and --pressure-bar (validated)."""
    from sim.api import with_pressure
    from sim.params import ParamError, car_parameters
    from sim.sensors import check_specs
    from sim.vehicle import tyre_for

    with sim_errors():
        params = car_parameters(args.overrides, args.param_files)
        try:
            params = with_pressure(params, args.pressure_bar)
            check_specs(params)
        except ValueError as exc:
            raise ParamError(str(exc)) from None
        tyre_for(params)  # a malformed or missing .tir is reported now, before any work
    return params
