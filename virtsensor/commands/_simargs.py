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
    from virtsensor.commands import _types as t

    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.NAME=VALUE",
                        help="override one car parameter (repeatable), e.g. --set vehicle.mass_kg=1600")
    parser.add_argument("--params", dest="param_files", action="append", default=[], metavar="FILE.toml",
                        type=t.text_file(),
                        help="TOML file of parameter overrides, same shape as sim/data/car_c_segment.toml")
    parser.add_argument("--pressure-bar", type=t.positive_float(10.0), default=None, metavar="P",
                        help="inflation pressure of all four tyres (gauge, bar; > 0 and <= 10, the tyre "
                             "file sets the usable range); without it a campaign draws each run's four pressures")
    parser.add_argument("--tyre", dest="tyres", action="append", default=[], metavar="[front=|rear=]FILE.tir",
                        type=t.tyre_spec(),
                        help="MF 6.1 tyre property file, or a bundled tyre's name (see 'virtsensor tyre'), of all "
                             "four wheels, or with front= / rear= of one axle (repeatable); checked before any "
                             "work; the same as --set tyres.file=FILE (tyres.file_front, tyres.file_rear)")


@contextmanager
def sim_errors() -> Iterator[None]:
    """Turn the simulator's input errors into one-line user errors (exit code 2).

    A simulation that diverged (:class:`FloatingPointError` from :func:`sim.engine.simulate_batch`, in this
    process or re-raised by joblib from a campaign's worker; the campaign has removed its files by then) is
    one too: the last line of defence behind the checks of the car and its tyres, its cause is a car that
    passed them but cannot be integrated. The message names the run(s) and the time.
    """
    from sim.manoeuvres import ManoeuvreError
    from sim.params import ParamError
    from sim.tir import TirError

    try:
        yield
    except (ManoeuvreError, ParamError, TirError) as exc:
        raise UserError(str(exc)) from None
    except FloatingPointError as exc:
        raise UserError(f"{exc}: the car's parameters or tyre coefficients (--set, --params, --tyre) hold a "
                        "value it cannot be simulated with") from None


def car_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The car's parameter tree from --params, --set, --tyre and --pressure-bar (validated)."""
    from sim.api import with_pressure
    from sim.params import ParamError, car_parameters
    from sim.sensors import check_specs
    from sim.vehicle import tyre_for

    overrides = [*args.overrides, *_tyre_overrides(args)]  # --tyre [AXLE=]FILE is --set tyres.file...=FILE
    with sim_errors():
        params = car_parameters(overrides, args.param_files)
        try:
            params = with_pressure(params, args.pressure_bar)
            check_specs(params)
        except ValueError as exc:
            raise ParamError(str(exc)) from None
        tyre_for(params), tyre_for(params, "rear")  # a malformed or missing .tir is reported now, before any work
    return params


#: --tyre prefix -> the car parameter it sets
_TYRE_KEYS = {"": "tyres.file", "front": "tyres.file_front", "rear": "tyres.file_rear"}


def _tyre_overrides(args: argparse.Namespace) -> list[str]:
    """``tyres.file...=<absolute path>`` for each checked --tyre; UserError names what is wrong."""
    from virtsensor.tyres import check_tyre_file

    out: dict[str, str] = {}
    for value in getattr(args, "tyres", None) or []:
        axle, sep, name = value.partition("=")
        if not sep or axle not in ("front", "rear"):
            axle, name = "", value
        key = _TYRE_KEYS[axle]
        if key in out:
            raise UserError(f"--tyre {value}: {axle or 'all four wheels'} already given a tyre by another --tyre")
        if any(o.split("=", 1)[0].strip() == key for o in args.overrides):
            raise UserError(f"--tyre {value} and --set {key}=... both name that tyre file; give one of them")
        out[key] = str(check_tyre_file(name).path.resolve())
    if "tyres.file" in out:  # all four wheels: unless an axle is named otherwise, no axle keeps its own file
        for key in ("tyres.file_front", "tyres.file_rear"):
            if not any(o.split("=", 1)[0].strip() == key for o in args.overrides):
                out.setdefault(key, "")
    return [f"{key}={path}" for key, path in out.items()]
