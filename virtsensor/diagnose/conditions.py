"""What the test engineer knows about each measured run: its conditions.

A real test day is not uniform: runs on the dry pad, the wet circle and the
polished basalt, a tyre topped up at lunch, a passenger on board for the
afternoon. Each run may come with its conditions, from

* a JSON beside it (same stem, ``run03.json``): an object ``{"conditions": {...}}``
  or the quantities at its top level (``{"mu": "0.5..0.8"}``, as in the metadata
  ``simulate`` writes beside a run); a JSON with neither gives no conditions. A
  JSON whose ``file`` names another file is the metadata of another run
  (:mod:`virtsensor.recordings.sidecar`): it is ignored, the run taken as one
  without a JSON, and the run's :attr:`RunConditions.notes` say so (``diagnose``
  prints them and writes them into its JSON's ``run_conditions``);
* ``--conditions FILE.csv``: a ``file`` column (the run's file name, or its
  path as given) and a column per quantity; an empty cell is "not known".
  The CSV wins over a JSON beside the run, quantity by quantity.

Quantities (:data:`QUANTITIES`): ``mu`` (road friction, 1), ``pressure_bar``
(gauge inflation of all four tyres, bar), ``mass_kg`` (the car's total mass
as driven, kg: the difference from the nominal car is a payload behind the
front axle, as :func:`sim.effects.effect_overrides` places it).

Each value is exact (``0.7``) or a range: ``"lo..hi"`` in a CSV cell or JSON
string, or ``[lo, hi]`` in JSON. An exact value is applied to the run's
re-simulation. A range is identified for that run as a nuisance parameter
(:mod:`virtsensor.diagnose.nuisance`) where the run excites it. With no
condition at all, a run's ``mu`` is the ``--mu`` of the command line if given,
else unknown over its :attr:`Quantity.unknown_range`, 0.2..1.2 (a test day's
surfaces are rarely all the same). A stated friction, by file or ``--mu``, may
be any the simulator takes (:data:`sim.params.MU_RANGE`).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sim.params import MU_RANGE
from virtsensor.errors import UserError


@dataclass(frozen=True)
class Quantity:
    """A per-run condition: unit, the range a stated value may take (``bounds``: what the simulator can
    re-simulate), one line of what it is, and the range an unknown one is identified over (``prior``; default
    ``bounds``)."""

    name: str
    unit: str
    bounds: tuple[float, float]
    what: str
    prior: tuple[float, float] | None = None

    @property
    def unknown_range(self) -> tuple[float, float]:
        """The range a run's value is identified over where nothing states it."""
        return self.prior or self.bounds


QUANTITIES: dict[str, Quantity] = {q.name: q for q in (
    # (a stated friction may be any the simulator takes, as `--mu`; an unknown one is searched over the roads of a
    # test day, dry to wet, not ice)
    Quantity("mu", "1", MU_RANGE, "road friction", prior=(0.2, 1.2)),
    Quantity("pressure_bar", "bar", (1.2, 3.4), "inflation pressure of all four tyres (gauge)"),
    Quantity("mass_kg", "kg", (900.0, 2500.0), "total mass of the car as driven"),
)}


@dataclass
class RunConditions:
    """One run's conditions: quantity -> (lo, hi); lo == hi is exact; absent is not known. ``notes``: one line
    each about what was left out of them (a JSON beside the run that is another run's metadata)."""

    values: dict[str, tuple[float, float]] = field(default_factory=dict)
    source: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def exact(self, name: str) -> float | None:
        v = self.values.get(name)
        return v[0] if v is not None and v[0] == v[1] else None

    def unknown(self) -> dict[str, tuple[float, float]]:
        """The ranged quantities (the nuisance parameters of this run)."""
        return {k: v for k, v in self.values.items() if v[0] < v[1]}

    def as_dict(self) -> dict[str, Any]:
        return {k: (v[0] if v[0] == v[1] else [v[0], v[1]]) for k, v in self.values.items()}


def parse_value(name: str, raw: Any, where: str) -> tuple[float, float]:
    """``(lo, hi)`` of one condition value (a number, ``"lo..hi"`` or ``[lo, hi]``); UserError names ``where``."""
    q = QUANTITIES.get(name)
    if q is None:
        raise UserError(f"{where}: unknown condition {name!r} (one of {', '.join(QUANTITIES)})")
    try:
        if isinstance(raw, (list, tuple)):
            if len(raw) != 2:
                raise ValueError
            lo, hi = float(raw[0]), float(raw[1])
        elif isinstance(raw, str) and ".." in raw:
            a, b = raw.split("..", 1)
            lo, hi = float(a), float(b)
        elif isinstance(raw, bool):
            raise ValueError
        else:
            lo = hi = float(raw)
    except (TypeError, ValueError):
        raise UserError(f"{where}: {name} {raw!r} is not a number or a range lo..hi") from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
        raise UserError(f"{where}: {name} {raw!r}: a range needs finite lo <= hi")
    b0, b1 = q.bounds
    if lo < b0 or hi > b1:
        unit = "" if q.unit in ("", "1", "-") else f" {q.unit}"
        raise UserError(f"{where}: {name} {raw!r} is outside {b0:g}..{b1:g}{unit}")
    return lo, hi


def _from_json(path: Path) -> dict[str, tuple[float, float]] | None:
    """The conditions in a JSON beside a run (None: the file holds none)."""
    from virtsensor.fileio import read_json

    obj = read_json(path, "conditions file")  # (UserError naming it: unreadable, not JSON, nested too deeply)
    if not isinstance(obj, dict):
        raise UserError(f"{path}: expected a JSON object of conditions")
    if "conditions" in obj:
        cond = obj["conditions"]
        if not isinstance(cond, dict):
            raise UserError(f"{path}: 'conditions' must be an object")
        return {k: parse_value(k, v, f"{path}: conditions") for k, v in cond.items()}
    known = {k: v for k, v in obj.items() if k in QUANTITIES}
    if not known:
        return None
    return {k: parse_value(k, v, str(path)) for k, v in known.items()}


def read_csv(path: Path) -> dict[str, dict[str, tuple[float, float]]]:
    """``file -> {quantity: (lo, hi)}`` from a conditions CSV; UserError names the file and the line (a malformed
    header or row, or a last row the file ends inside: cut mid-row, its last value perhaps cut too)."""
    try:
        text = path.read_text(encoding="utf-8-sig")  # (a spreadsheet's "CSV UTF-8" starts with a BOM)
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read ({type(exc).__name__})") from None
    rows = list(csv.reader(io.StringIO(text, newline="")))
    last = text.rstrip(" \t")  # (spaces after the last row's end of line are no row)
    if last.strip() and not last.endswith(("\n", "\r")):
        raise UserError(f"{path}: line {len(last.splitlines())}: truncated: the file ends inside this row (a complete "
                        f"file ends every row with an end of line)")
    if not rows or "file" not in [h.strip() for h in rows[0]]:
        raise UserError(f"{path}: line 1: the header needs a 'file' column")
    head = [h.strip() for h in rows[0]]
    for h in head:
        if h != "file" and h not in QUANTITIES:
            raise UserError(f"{path}: line 1: unknown column {h!r} (file, {', '.join(QUANTITIES)})")
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for i, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue
        if len(row) != len(head):
            raise UserError(f"{path}: line {i}: {len(row)} cells for {len(head)} columns")
        cells = dict(zip(head, (c.strip() for c in row), strict=True))
        name = cells.pop("file")
        if not name:
            raise UserError(f"{path}: line {i}: empty file name")
        if name in out:
            raise UserError(f"{path}: line {i}: {name} listed twice")
        out[name] = {k: parse_value(k, v, f"{path}: line {i}") for k, v in cells.items() if v}
    return out


def load_conditions(paths: Sequence[Path], csv_path: Path | None = None, *,
                    default_mu: float | None = None, also: Sequence[Path | str] = ()) -> list[RunConditions]:
    """The conditions of each run (``paths``: the runs' files, in order); ``also``: files given but left out
    (a CSV may list them). A JSON beside a run that names another file is ignored, with a note (module docstring)."""
    from virtsensor.recordings.sidecar import sidecar_of

    table = read_csv(csv_path) if csv_path is not None else {}
    used: set[str] = {k for p in map(Path, also) for k in (str(p), p.name, p.stem)}
    out = []
    for p in paths:
        rc = RunConditions()
        beside = p.with_suffix(".json")
        if (note := sidecar_of(p, beside).note) is not None:
            rc.notes.append(note)
        elif beside.is_file() and beside != p:
            for k, v in (_from_json(beside) or {}).items():
                rc.values[k], rc.source[k] = v, beside.name
        for key in (str(p), p.name, p.stem):
            if key in table:
                used.add(key)
                for k, v in table[key].items():
                    rc.values[k], rc.source[k] = v, csv_path.name if csv_path else ""
                break
        if "mu" not in rc.values:
            if default_mu is not None:
                rc.values["mu"], rc.source["mu"] = (default_mu, default_mu), "--mu"
            else:
                rc.values["mu"], rc.source["mu"] = QUANTITIES["mu"].unknown_range, "not known"
        out.append(rc)
    extra = sorted(set(table) - used)  # a row naming none of the files given
    if extra and csv_path is not None:
        raise UserError(f"{csv_path}: {extra[0]} is not one of the measured runs")
    return out


def run_overrides(values: Mapping[str, float], params: Mapping[str, Any]) -> dict[str, Any]:
    """Parameter overrides of one run at the condition ``values`` (quantity -> value; ``mu`` is not a
    parameter of the car and is left out)."""
    from sim.effects import effect_overrides

    out: dict[str, Any] = {}
    if "pressure_bar" in values:
        out.update(effect_overrides("tyre_pressure", values["pressure_bar"], params))
    if "mass_kg" in values:
        out.update(effect_overrides("vehicle_mass", values["mass_kg"] - params["vehicle"]["mass_kg"], params))
    return out
