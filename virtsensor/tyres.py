"""Check a tyre property file and compute the figures an engineer looks at first (``virtsensor tyre``).

A ``.tir`` file is checked before anything is built on it: it must parse, have an SI
``[UNITS]`` section and a ``FITTYP`` of 61 or 62 (Magic Formula 6.1/6.2), give every
coefficient the MF 6.1 model needs and MF 6.1 has no default for, give numbers where
numbers belong, give a load, size, pressure, reference speed and stiffnesses that a
passenger-car or light-truck tyre has (a value in the wrong unit is named with the
unit it looks like: :data:`sim.tyre.PLAUSIBLE_RANGES`), and give a model whose
outputs are finite and a tyre's over the figures' range (a coefficient so large that
the Magic Formula overflows, or gives a force over 5 times the load or a moment whose
lever exceeds the tyre's radius, is named: :func:`sim.tyre.overflow_problem`). Every failure is a
:class:`~virtsensor.errors.UserError` whose one-line message names the file, the key
and the line (a ``--set`` key: the file and ``--set``). Optional keys the file
leaves out take their standard MF 6.1 defaults (scaling factors 1, ``LMUV`` 0, other
coefficients 0, operating ranges unbounded, ``VXLOW`` 1 m/s, ``INFLPRES`` =
``NOMPRES``); :attr:`CheckedTyre.defaults` lists them.

Figures (:func:`tyre_figures`), all in the tyre's ISO-W axes (alpha > 0 gives Fy < 0
for the usual coefficient signs), zero camber, at the file's ``LONGVL``, for loads
0.5, 1 and 1.5 x ``FNOMIN`` and pressures 0.9, 1 and 1.1 x ``INFLPRES``:

* cornering stiffness Kya (N/rad, dFy0/dalpha* at zero slip);
* Fy peak: the largest |Fy| in pure side slip over |alpha| <= 30 deg, and its slip angle;
* Mz peak: the largest Mz at alpha > 0 and the smallest at alpha < 0, with their slip angles;
* pneumatic trail t at zero slip (m);
* longitudinal slip stiffness Kxk (N per unit slip, dFx0/dkappa at zero slip).

Peaks are located on a 0.01 deg grid, then on a 0.0001 deg grid around the best point.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sim.tir import TirError, TirFile, bundled_tir, bundled_tyres, read_tir
from sim.tyre import MagicFormula61, overflow_message, overflow_problem
from virtsensor import plotting
from virtsensor.errors import UserError

__all__ = ["CheckedTyre", "LOAD_FACTORS", "PRESSURE_FACTORS", "check_tyre_file", "format_report",
           "parse_overrides", "plot_curves", "require_matplotlib", "resolve_tyre_file", "tyre_figures"]

LOAD_FACTORS = (0.5, 1.0, 1.5)  # x FNOMIN
PRESSURE_FACTORS = (0.9, 1.0, 1.1)  # x INFLPRES
_DEG = math.pi / 180.0


@dataclass(frozen=True)
class CheckedTyre:
    """A property file that passed the checks, its model and the optional keys it leaves out."""

    path: Path
    tir: TirFile
    model: MagicFormula61
    defaults: dict[str, float]  # key the file does not give -> standard value used
    replaced: dict[str, float | str] = field(default_factory=dict)  # --set key -> the value it replaced


def resolve_tyre_file(name: str | Path) -> Path:
    """``name`` as a path if that file exists, else a bundled tyre by name (with or without ``.tir``).

    Raises:
        UserError: neither (the message lists the bundled tyres).
    """
    path = Path(name)
    if path.is_file():
        return path
    if path.name == str(name):  # a bare name: look among the bundled files
        for candidate in (path.name, f"{path.name}.tir"):
            if candidate in bundled_tyres():
                return bundled_tir(candidate)
    if path.is_dir():
        raise UserError(f"{name}: is a directory, give a .tir file")
    if path.exists():  # (a pipe, a device: there, but no file to read)
        raise UserError(f"{name}: not a regular file, give a .tir file")
    raise UserError(f"{name}: no such tyre property file (bundled: {', '.join(bundled_tyres())})")


def parse_overrides(items: Iterable[str]) -> dict[str, float]:
    """``KEY=VALUE`` strings (e.g. ``LMUY=0.7``) -> {KEY: value}; UserError names a malformed one."""
    out: dict[str, float] = {}
    for item in items:
        key, sep, value = item.partition("=")
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not sep or not key.strip() or not math.isfinite(number):
            raise UserError(f"--set {item!r}: expected KEY=NUMBER, e.g. LMUY=0.7")
        out[key.strip().upper()] = number
    return out


def check_tyre_file(name: str | Path, overrides: Mapping[str, float] | None = None) -> CheckedTyre:
    """Read, check and build the MF 6.1 model of a property file (see the module docstring).

    Args:
        name: a path, or the name of a bundled tyre.
        overrides: coefficients KEY -> value that replace (or add to) the file's.

    Raises:
        UserError: one line naming the file, the key and the line of the first problem (an implausible
            value: the unit it looks like; an overflow: the coefficient(s) that cause it).
    """
    path = resolve_tyre_file(name)
    try:
        tir = read_tir(path)
        if not tir.units:
            raise TirError(f"{path}: no [UNITS] section (the model needs an SI file: "
                           "LENGTH 'meter', FORCE 'newton', ANGLE 'radian', MASS 'kg', TIME 'second')")
        if "FITTYP" not in tir:
            line = tir.section_lines.get("MODEL")
            where = f"{path}:{line}: [MODEL]" if line is not None else f"{path}:"
            raise TirError(f"{where} no FITTYP (Magic Formula version; 61 or 62 expected)")
        model = MagicFormula61(tir, source=str(path))
        replaced: dict[str, float | str] = {}
        if overrides:
            unknown = sorted(k for k in overrides if k not in tir and k not in model.params)
            if unknown:
                raise TirError(f"--set {unknown[0]}: not a coefficient of the MF 6.1 model or of {path.name}")
            replaced = {k: model.params.get(k, tir.get(k, "")) for k in overrides}
            for key in overrides:
                tir.lines.pop(key, None)
            tir.update(overrides)
            model = MagicFormula61(tir, source=f"{path} with --set {', '.join(overrides)}")
    except TirError as exc:
        raise UserError(str(exc)) from None
    problem = overflow_problem(model, tir, replaced)
    if problem is not None:
        raise UserError(problem)
    defaults = {k: v for k, v in model.params.items() if k not in tir and isinstance(v, float)}
    return CheckedTyre(path, tir, model, defaults, replaced)


# ---------------------------------------------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------------------------------------------
def _extremum(f: Callable[[np.ndarray], np.ndarray], lo: float, hi: float) -> tuple[float, float]:
    """(max of f, its argument) over [lo, hi] deg: a 0.01 deg grid, then 0.0001 deg around the best point."""
    grid = np.linspace(lo, hi, int(round((hi - lo) / 0.01)) + 1)
    i = int(np.argmax(f(grid)))
    fine = np.linspace(max(lo, grid[i] - 0.01), min(hi, grid[i] + 0.01), 201)
    values = f(fine)
    j = int(np.argmax(values))
    return float(values[j]), float(fine[j])


def _figures_at(model: MagicFormula61, fz: float, pressure: float, vx: float) -> dict[str, float]:
    def side_slip(a_deg: np.ndarray) -> Any:
        return model.steady_state(fz, 0.0, a_deg * _DEG, 0.0, vx, pressure)

    fy_abs, fy_alpha = _extremum(lambda a: np.abs(side_slip(a).fy), -30.0, 30.0)
    mz_max, mz_max_alpha = _extremum(lambda a: side_slip(a).mz, 0.0, 30.0)
    mz_min, mz_min_alpha = _extremum(lambda a: -side_slip(a).mz, -30.0, 0.0)
    fy_peak = float(side_slip(np.array([fy_alpha])).fy[0])
    zero = model.steady_state(fz, 0.0, 0.0, 0.0, vx, pressure)
    return {
        "cornering_stiffness_n_per_rad": float(zero.kya),
        "fy_peak_n": fy_peak,
        "fy_peak_alpha_deg": fy_alpha,
        "mz_max_nm": mz_max,
        "mz_max_alpha_deg": mz_max_alpha,
        "mz_min_nm": -mz_min,
        "mz_min_alpha_deg": mz_min_alpha,
        "trail_at_zero_slip_m": float(zero.t),
        "slip_stiffness_n": float(zero.kxk),
    }


def tyre_figures(tyre: CheckedTyre) -> dict[str, Any]:
    """The figures of the module docstring, one entry per (pressure factor, load factor), as a JSON-able dict.

    Raises:
        UserError: a figure comes out non-finite (a coefficient so large that the Magic Formula overflows);
            the message names the figures and the coefficient(s) that cause it
            (:func:`sim.tyre.overflow_message`).
    """
    m = tyre.model
    p = m.params
    fz0, pres0, vx = float(p["FNOMIN"]), float(p["INFLPRES"]), float(p["LONGVL"])
    conditions = []
    with np.errstate(all="ignore"):  # an overflow shows as a non-finite figure, refused below with its cause
        for pf in PRESSURE_FACTORS:
            for lf in LOAD_FACTORS:
                fig = _figures_at(m, lf * fz0, pf * pres0, vx)
                conditions.append({"load_factor": lf, "pressure_factor": pf, "fz_n": lf * fz0,
                                   "pressure_pa": pf * pres0, **fig})
    bad = [key for key in conditions[0] if not all(math.isfinite(c[key]) for c in conditions)]
    if bad:  # (check_tyre_file's coarser grid saw none)
        raise UserError(overflow_message(m, f"the figures {_figures_named(bad)}", tyre.tir, tyre.replaced))
    return {
        "file": str(tyre.path),
        "fittyp": p.get("FITTYP"),
        "fnomin_n": fz0,
        "inflpres_pa": pres0,
        "nompres_pa": float(p["NOMPRES"]),
        "unloaded_radius_m": float(p["UNLOADED_RADIUS"]),
        "vx_mps": vx,
        "camber_rad": 0.0,
        "axes": "ISO-W",
        "defaults": tyre.defaults,
        "conditions": conditions,
    }


#: rows of the text report: (label, unit, key, scale, format)
_ROWS = (
    ("cornering stiffness", "N/deg", "cornering_stiffness_n_per_rad", _DEG, "{:.0f}"),
    ("Fy peak", "N", "fy_peak_n", 1.0, "{:.0f}"),
    ("  at slip angle", "deg", "fy_peak_alpha_deg", 1.0, "{:.2f}"),
    ("Mz peak, alpha > 0", "Nm", "mz_max_nm", 1.0, "{:.1f}"),
    ("  at slip angle", "deg", "mz_max_alpha_deg", 1.0, "{:.2f}"),
    ("Mz peak, alpha < 0", "Nm", "mz_min_nm", 1.0, "{:.1f}"),
    ("  at slip angle", "deg", "mz_min_alpha_deg", 1.0, "{:.2f}"),
    ("pneumatic trail at zero slip", "mm", "trail_at_zero_slip_m", 1000.0, "{:.1f}"),
    ("longitudinal slip stiffness", "kN", "slip_stiffness_n", 0.001, "{:.0f}"),
)


def _figures_named(figures: list[str]) -> str:
    """The figures' keys by their labels in the report (an "  at slip angle" row: the slip angle of the row above)."""
    labels: dict[str, str] = {}
    previous = ""
    for label, _unit, key, _scale, _fmt in _ROWS:
        labels[key] = f"{previous}: slip angle" if label.startswith(" ") else label.replace(", ", " at ")
        previous = labels[key]
    return ", ".join(labels.get(key, key) for key in figures)


def format_report(figures: Mapping[str, Any]) -> str:
    """The figures as text: a table per load, then the change of each figure at -10 % and +10 % pressure."""
    conds = {(c["pressure_factor"], c["load_factor"]): c for c in figures["conditions"]}
    bar = figures["inflpres_pa"] / 1e5
    fittyp = figures["fittyp"]
    lines = [f"{figures['file']}: Magic Formula {fittyp / 10:.1f} (FITTYP {fittyp:g}), "
             f"FNOMIN {figures['fnomin_n']:g} N, R0 {figures['unloaded_radius_m'] * 1000:.1f} mm, "
             f"INFLPRES {bar:.2f} bar"]
    defaults = figures["defaults"]
    if defaults:
        listed = ", ".join(f"{k}={v:g}" for k, v in sorted(defaults.items()))
        lines.append(f"optional keys not in the file, standard values used ({len(defaults)}): {listed}")
    else:
        lines.append("optional keys not in the file: none")
    lines.append(f"pure slip, zero camber, Vx {figures['vx_mps']:g} m/s, ISO-W axes, {bar:.2f} bar")
    head = f"{'':30s}{'':>6s}" + "".join(f"{f'{lf:g} Fz0':>15s}" for lf in LOAD_FACTORS)
    lines += ["", head, f"{'load':30s}{'N':>6s}" + "".join(f"{lf * figures['fnomin_n']:15.0f}" for lf in LOAD_FACTORS)]
    for label, unit, key, scale, fmt in _ROWS:
        cells = "".join(f"{fmt.format(conds[(1.0, lf)][key] * scale):>15s}" for lf in LOAD_FACTORS)
        lines.append(f"{label:30s}{unit:>6s}{cells}")
    lines += ["", "inflation pressure -10 % / +10 %: change of each figure", head]
    for label, _unit, key, _scale, _fmt in _ROWS:
        changes: list[str] = []
        for lf in LOAD_FACTORS:
            base = conds[(1.0, lf)][key]
            if key.endswith("_deg"):
                changes.append("/".join(f"{conds[(pf, lf)][key] - base:+.2f}" for pf in (0.9, 1.1)))
            else:
                changes.append("/".join(f"{100.0 * (conds[(pf, lf)][key] / base - 1.0):+.1f}%" if base else "n/a"
                                      for pf in (0.9, 1.1)))
        unit = "deg" if key.endswith("_deg") else ""
        lines.append(f"{label:30s}{unit:>6s}" + "".join(f"{c:>15s}" for c in changes))
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------------------
# outputs
# ---------------------------------------------------------------------------------------------------------------
def require_matplotlib() -> None:
    """:class:`~virtsensor.extras.MissingExtra` (a UserError naming the ``plots`` extra) without matplotlib."""
    plotting.require("--plot")


def plot_curves(tyre: CheckedTyre, path: Path) -> None:
    """PNG of Fy and Mz against slip angle and Fx against kappa, at 0.5/1/1.5 x FNOMIN, INFLPRES and +10 %."""
    m = tyre.model
    p = m.params
    fz0, pres0, vx = float(p["FNOMIN"]), float(p["INFLPRES"]), float(p["LONGVL"])
    a_deg = np.linspace(-15.0, 15.0, 601)
    kappa = np.linspace(-0.3, 0.3, 601)
    fig = plotting.figure(13, 4.2, what="--plot")
    ax_fy, ax_mz, ax_fx = fig.subplots(1, 3)
    colours = ("tab:blue", "tab:orange", "tab:green")
    for lf, colour in zip(LOAD_FACTORS, colours, strict=True):
        for pf, style in ((1.0, "-"), (1.1, "--")):
            label = f"{lf:g} Fz0 ({lf * fz0 / 1000:.1f} kN), {pf * pres0 / 1e5:.2f} bar"
            side = m.steady_state(lf * fz0, 0.0, a_deg * _DEG, 0.0, vx, pf * pres0)
            longi = m.steady_state(lf * fz0, kappa, 0.0, 0.0, vx, pf * pres0)
            ax_fy.plot(a_deg, side.fy / 1000.0, style, color=colour, label=label)
            ax_mz.plot(a_deg, side.mz, style, color=colour)
            ax_fx.plot(kappa, longi.fx / 1000.0, style, color=colour)
    for ax, xlabel, ylabel in ((ax_fy, "slip angle alpha (deg)", "Fy (kN)"),
                               (ax_mz, "slip angle alpha (deg)", "Mz (Nm)"),
                               (ax_fx, "longitudinal slip kappa (-)", "Fx (kN)")):
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, alpha=0.3)
        ax.axhline(0.0, color="k", lw=0.5)
        ax.axvline(0.0, color="k", lw=0.5)
    ax_fy.legend(fontsize=7)
    fig.suptitle(f"{tyre.path.name}: pure slip, zero camber, Vx {vx:g} m/s, ISO-W (solid {pres0 / 1e5:.2f} bar, "
                 "dashed +10 %)", fontsize=10)
    plotting.save(fig, path)
