"""Magic Formula 6.1 steady-state tyre model (MF-Tyre 6.1, Besselink/Pacejka 2010).

The equations are those of Pacejka, *Tire and Vehicle Dynamics* 3rd ed. (2012),
Ch. 4.3.2 / App. 3, with the amendments of Besselink, Schmeitz & Pacejka,
"An improved Magic Formula/Swift tyre model that can handle inflation pressure
changes" (VSD 48, 2010, Appendix) that MFeval (M. Furlan Tassara) adopted to
match the TNO solver: Dt (A60), Bt (A58), alpha_r,eq / alpha_t,eq (A54/A55),
s (A56), My (A48), ``t`` multiplied by LFZO, Amu = 1 (no digressive friction),
LMUV = 0 unless given. Turn slip is not modelled (phi_t = 0, all zeta = 1).
This module is an independent implementation written from those equations.

Frames, units and signs (ISO-W / TYDEX W-axis system)
----------------------------------------------------
* Wheel axes: x forward along the wheel heading in the road plane, y to the left,
  z up. Forces act from the road on the tyre at the contact centre.
* Inputs: ``fz`` N (>= 0, tyre load), ``kappa`` (-), ``alpha`` rad, ``gamma`` rad,
  ``vx`` m/s, ``pressure`` Pa, ``omega`` rad/s.
* ``vx`` = Vcx, longitudinal speed of the wheel centre in wheel axes.
* Slip angle ``alpha = atan(Vsy / |Vcx|)`` with Vsy the lateral velocity of the wheel
  centre in wheel axes (+ to the left). With the usual coefficient signs (the
  bundled files: Kya < 0) a positive alpha gives a NEGATIVE Fy and, below the Mz
  peak, a POSITIVE Mz (the torque turns the wheel back towards its velocity).
* Longitudinal slip ``kappa = (omega * Re - Vcx) / |Vcx|``: positive (driving) kappa
  gives positive Fx.
* Inclination ``gamma``: rotation of the wheel plane about the x axis (ISO).
* Outputs ``fx``, ``fy`` N along x/y, ``mz`` Nm about z (aligning torque),
  ``my`` Nm about y (rolling resistance, negative when rolling forwards).

Mounting side: the coefficients describe the tyre as measured (``TYRESIDE`` is
informational only). Mirroring for the other side of the car is the caller's job:
alpha -> -alpha, gamma -> -gamma, and negate Fy and Mz.

Input handling as in MFeval (``useMode`` 1x1, steady state): negative Fz -> 0;
Fz clipped to FZMAX (FZMIN only bounds the load used by the Mz terms, as MFeval);
kappa, alpha, gamma, pressure clipped to KPUMIN/KPUMAX, ALPMIN/ALPMAX,
CAMMIN/CAMMAX, PRESMIN/PRESMAX; below VXLOW the low-speed model reduces kappa and
alpha linearly and fades the curve shifts, the trail and the residual torque with
a smooth (cosine) factor; backwards rolling flips the signs as MFeval does.
``use_alpha_star=True`` (default, MFeval ``useMode`` 121) uses the book's
alpha* = tan(alpha) sign(Vcx) and gamma* = sin(gamma); ``False`` gives ``useMode``
111 (alpha* = alpha, gamma* = gamma, the TNO choice). The two differ only to third
order in the slip angle and the inclination (tan a - a and sin g - g).

Friction scaling: ``mu_scale`` multiplies LMUX and LMUY (the road friction
relative to the surface the tyre was measured on). Through the MF equations this
also scales, as the standard intends, the vertical curve shifts (SVx, SVy, SVyk,
via LMU'), the residual torque peak Dr, and divides the trail and residual-torque
slope factors Bt and Br by LMUY (on a slippery road the trail collapses at a
smaller slip angle). Slip and cornering stiffnesses (Kxk, Kya) and the peak trail
Dt are unchanged: at small slip the contact patch does not slide, so the road
friction does not matter there.

Cost: one call evaluates arrays of any shape in a fixed number of numpy calls
(about 40 transcendental functions per element, which dominate at simulator batch
sizes); array pressures are cached by content, scalar pressure and mu_scale are
folded into the cached coefficient matrix.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sim.tir import TirError, TirFile, bundled_tir, read_tir, require_keys

__all__ = ["MagicFormula61", "TyreOutput", "REQUIRED_KEYS", "SCALING_FACTORS", "PLAUSIBLE_RANGES",
           "PlausibleRange", "TYPICAL_TYRE", "FORCE_RATIO_LIMIT", "beyond_a_tyre", "implausible",
           "non_finite_outputs", "overflow_message", "overflow_problem", "overflowing"]

FloatArray = NDArray[np.float64]

#: Coefficients without a usable default: the model refuses a file without them.
REQUIRED_KEYS: tuple[str, ...] = (
    "FNOMIN",
    "UNLOADED_RADIUS",
    "LONGVL",
    "NOMPRES",
    "VERTICAL_STIFFNESS",
    "LONGITUDINAL_STIFFNESS",
    "LATERAL_STIFFNESS",
    "PCX1",
    "PDX1",
    "PKX1",
    "PCY1",
    "PDY1",
    "PKY1",
    "PKY2",
    "PKY4",
    "QBZ1",
    "QCZ1",
    "QDZ1",
)

#: MF 6.1 scaling factors; missing ones default to 1 (LMUV, absent from MF 6.1 files, to 0).
SCALING_FACTORS: tuple[str, ...] = (
    "LFZO", "LCX", "LMUX", "LEX", "LKX", "LHX", "LVX", "LCY", "LMUY", "LEY", "LKY", "LHY",
    "LVY", "LTR", "LRES", "LXAL", "LYKA", "LVYKA", "LS", "LKYC", "LKZC", "LVMX", "LMX",
    "LMY", "LMP",
)

#: Every coefficient the steady-state model reads (missing optional ones default to 0).
_COEFFICIENTS: tuple[str, ...] = (
    # longitudinal
    "PCX1", "PDX1", "PDX2", "PDX3", "PEX1", "PEX2", "PEX3", "PEX4", "PKX1", "PKX2", "PKX3",
    "PHX1", "PHX2", "PVX1", "PVX2", "PPX1", "PPX2", "PPX3", "PPX4",
    "RBX1", "RBX2", "RBX3", "RCX1", "REX1", "REX2", "RHX1",
    # lateral
    "PCY1", "PDY1", "PDY2", "PDY3", "PEY1", "PEY2", "PEY3", "PEY4", "PEY5",
    "PKY1", "PKY2", "PKY3", "PKY4", "PKY5", "PKY6", "PKY7",
    "PHY1", "PHY2", "PVY1", "PVY2", "PVY3", "PVY4", "PPY1", "PPY2", "PPY3", "PPY4", "PPY5",
    "RBY1", "RBY2", "RBY3", "RBY4", "RCY1", "REY1", "REY2", "RHY1", "RHY2",
    "RVY1", "RVY2", "RVY3", "RVY4", "RVY5", "RVY6",
    # rolling resistance
    "QSY1", "QSY2", "QSY3", "QSY4", "QSY5", "QSY6", "QSY7", "QSY8",
    # aligning
    "QBZ1", "QBZ2", "QBZ3", "QBZ4", "QBZ5", "QBZ9", "QBZ10", "QCZ1",
    "QDZ1", "QDZ2", "QDZ3", "QDZ4", "QDZ6", "QDZ7", "QDZ8", "QDZ9", "QDZ10", "QDZ11",
    "QEZ1", "QEZ2", "QEZ3", "QEZ4", "QEZ5", "QHZ1", "QHZ2", "QHZ3", "QHZ4",
    "PPZ1", "PPZ2", "SSZ1", "SSZ2", "SSZ3", "SSZ4",
    # vertical / effective rolling radius / structural
    "BREFF", "DREFF", "FREFF", "Q_RE0", "Q_V1", "PFZ1",
    "PCFX1", "PCFX2", "PCFX3", "PCFY1", "PCFY2", "PCFY3",
)

#: Largest magnitude of a scaling factor (``L...``, 1 = the fitted tyre): the MF 6.1 documentation uses them
#: within a few units (a surface's friction, a tyre's wear); 100 is far outside any such use. A scaling factor
#: multiplies a force or a moment as it is: 1e300 overflows nothing and gives forces of 1e301 N.
SCALING_LIMIT = 100.0

#: Operating ranges: missing limits mean "unbounded" (FZMIN: 0).
_RANGE_DEFAULTS: dict[str, float] = {
    "FZMIN": 0.0,
    "FZMAX": math.inf,
    "KPUMIN": -math.inf,
    "KPUMAX": math.inf,
    "ALPMIN": -math.inf,
    "ALPMAX": math.inf,
    "CAMMIN": -math.inf,
    "CAMMAX": math.inf,
    "PRESMIN": 0.0,
    "PRESMAX": math.inf,
}


class PlausibleRange(NamedTuple):
    """Where a key lies for a passenger-car or light-truck tyre, and the unit slips that would move it out.

    ``slips``: (factor, phrase) pairs: a value that lands in [low, high] once multiplied by the
    factor was probably written in that other unit ("is it in kN?", "is it the diameter?").
    """

    low: float
    high: float
    unit: str
    what: str  #: what the key is, for the message ("a nominal load")
    slips: tuple[tuple[float, str], ...]


_PRESSURE = PlausibleRange(1.0e5, 6.5e5, "Pa", "an inflation pressure",
                           ((1e5, "in bar"), (1e3, "in kPa"), (6894.757, "in psi"), (1e6, "in MPa")))
_CARCASS = ((1e3, "in N/mm (kN/m)"),)

#: Plausible values of the keys whose unit slips are common, for a passenger-car or light-truck tyre (the
#: model's domain: the sizes run from a 105/70 R14 temporary spare to a 40 x 15.50 R20 LT tyre). Each range
#: is a few times wider than those sizes need, so that only a value in the wrong unit (or no tyre of this
#: class) falls out, and each slip it names lands well inside:
#:
#: * FNOMIN 1-25 kN: the nominal load is a part of the tyre's maximum load, from load index 60 (250 kg,
#:   2.5 kN) to light-truck index 130 (1900 kg, 18.6 kN). A file in kN gives 1-25, one in daN 100-2500.
#: * UNLOADED_RADIUS 0.2-0.6 m: rim radius plus section height, 0.23 m (145/70 R10) to 0.51 m (40 in LT).
#:   A radius in mm, cm or inches, or the diameter, falls out.
#: * WIDTH 0.08-0.45 m: section width, 105 mm (spare) to 355 mm (355/25 R21) or 15.5 in (LT).
#: * RIM_RADIUS 0.12-0.35 m: 10 to 26 in rims. The rim's size in inches is its diameter.
#: * NOMPRES, INFLPRES 1-6.5 bar: passenger tyres run 1.6-3.5 bar, temporary spares 4.2 bar, light-truck
#:   load range E 5.5 bar (80 psi); below 1 bar the tyre is flat, above 6.5 bar it is a truck tyre. A
#:   pressure in bar, kPa, psi or MPa falls out (the file's [UNITS] cannot say: pressure has no entry).
#: * LONGVL 1-40 m/s: the reference speed of the measurements, 10-30 m/s on flat-track and trailer rigs
#:   (TNO: 16.7 m/s, 60 km/h). 60 (km/h) falls out; a speed in mph (1.6 times the m/s) does not always.
#: * VERTICAL_STIFFNESS 50-1500 kN/m (passenger tyres 150-350, light trucks up to 700), LONGITUDINAL_ and
#:   LATERAL_STIFFNESS 20-3000 kN/m (carcass stiffnesses, 150-600 kN/m measured): a value in N/mm falls out.
#:
#: Every other number of the model must only be finite (:class:`MagicFormula61` checks it).
PLAUSIBLE_RANGES: dict[str, PlausibleRange] = {
    "FNOMIN": PlausibleRange(1.0e3, 2.5e4, "N", "a nominal load",
                             ((1e3, "in kN"), (10.0, "in daN"), (9.80665, "in kgf"))),
    "UNLOADED_RADIUS": PlausibleRange(0.2, 0.6, "m", "a free radius",
                                      ((1e-3, "in mm"), (1e-2, "in cm"), (0.0254, "in inches"),
                                       (0.5, "the diameter"), (0.0127, "the diameter in inches"))),
    "WIDTH": PlausibleRange(0.08, 0.45, "m", "a section width", ((1e-3, "in mm"), (0.0254, "in inches"))),
    "RIM_RADIUS": PlausibleRange(0.12, 0.35, "m", "a rim radius",
                                 ((1e-3, "in mm"), (0.5, "the diameter"), (0.0127, "the rim size in inches"))),
    "NOMPRES": _PRESSURE,
    "INFLPRES": _PRESSURE,
    "LONGVL": PlausibleRange(1.0, 40.0, "m/s", "a reference speed", ((1.0 / 3.6, "in km/h"),)),
    "VERTICAL_STIFFNESS": PlausibleRange(5.0e4, 1.5e6, "N/m", "a vertical stiffness", _CARCASS),
    "LONGITUDINAL_STIFFNESS": PlausibleRange(2.0e4, 3.0e6, "N/m", "a longitudinal carcass stiffness", _CARCASS),
    "LATERAL_STIFFNESS": PlausibleRange(2.0e4, 3.0e6, "N/m", "a lateral carcass stiffness", _CARCASS),
}


def implausible(key: str, value: float) -> str | None:
    """Why ``value`` of ``key`` is no passenger-car or light-truck tyre's (see :data:`PLAUSIBLE_RANGES`), with
    the likely unit slip; None when it is plausible or ``key`` has no range."""
    r = PLAUSIBLE_RANGES.get(key)
    if r is None or r.low <= value <= r.high:
        return None
    side = "below" if value < r.low else "above"
    slips = [phrase for factor, phrase in r.slips if r.low <= value * factor <= r.high]
    hint = f"is it {' or '.join(slips)}?" if slips else "is it in another unit?"
    return (f"{key} = {value:g} {r.unit}: {r.what} {side} the {r.low:g} to {r.high:g} {r.unit} of a "
            f"passenger-car or light-truck tyre; {hint}")


_EPS = 1e-6  # Pacejka (4.E6a): epsilon_x,y,k,v
_TWO_OVER_PI = 2.0 / math.pi


#: Monomials of the polynomial coefficient block: d = dfz, g = gamma*, c = gamma.
_MONOMIALS: tuple[str, ...] = (
    "1", "d", "d2", "g", "dg", "d2g", "g2", "dg2", "ag", "gag", "dgag",
    "c", "dc", "d2c", "c2", "dc2", "ac", "dac", "d2ac",
)
_M = {name: i for i, name in enumerate(_MONOMIALS)}

#: Rows of the coefficient block, ordered so that the quantities of the three pure-slip
#: curves (Fx0, Fy0, Fy0 at gamma = 0) form contiguous 3-row blocks (D, E0, E1, SH, SV, K).
#: SHY and KYA0 are computed, not polynomials (zero rows in the weight matrix).
_ROW_NAMES: tuple[str, ...] = (
    "MUX", "MUY", "MUY0",  # D = mu * Fz
    "EX0", "EYA", "EY0A",  # E = E0 + E1 sign(x)
    "EX1", "EYB", "EY0B",
    "SHX", "SHY", "SHY0",  # horizontal shifts
    "SVX", "SVY", "SVY0",  # vertical shifts / Fz
    "KXK", "KYA", "KYA0",  # slip stiffnesses Kxk, Kya, Kya(gamma = 0)
    "EXA", "EYK",  # combined-slip curvatures
    "BXA", "BYK",  # combined-slip stiffness numerators
    "SHYK", "KYAD", "KYGG", "SVYG", "DVYK", "SHT", "DT", "BT", "ET1", "ET2", "DRA", "DRB", "S0",
)
_R = {name: i for i, name in enumerate(_ROW_NAMES)}
#: Rows multiplied by a pressure factor (attribute of _PressureTerms) when the pressure is an array.
_PRESSURE_ROWS = (("MUX", "mux"), ("MUY", "muy"), ("MUY0", "muy"), ("KXK", "kxk"), ("KYA", "kya"),
                  ("KYAD", "pky2"), ("KYGG", "kyg"), ("DT", "dt"), ("DRB", "dr"))
_NROWS = len(_ROW_NAMES)
_D, _E0, _E1, _SH, _SV, _K = (slice(_R[r], _R[r] + 3) for r in ("MUX", "EX0", "EX1", "SHX", "SVX", "KXK"))

_COS = 0.5 * math.pi  # phase that turns the Magic Formula sine into a cosine: cos x = sin(x + pi/2)


def _magic_formula(b: FloatArray, x: FloatArray, e: FloatArray, c: FloatArray | float,
                   phase: float | None = None) -> FloatArray:
    """sin(C atan(B x - E (B x - atan(B x))) + phase), element-wise (4.E8 without D and SV).

    Several curves are evaluated together as rows of ``b``, ``x``, ``e`` (``c`` a
    column or a scalar). Overwrites ``b`` and ``x``; returns ``x``.
    """
    u = np.multiply(b, x, out=b)
    v = np.arctan(u, out=x)
    v -= u
    v *= e
    v += u
    np.arctan(v, out=v)
    v *= c
    if phase is not None:
        v += phase
    np.sin(v, out=v)
    return v


class _OperatingPoint(NamedTuple):
    """Flattened inputs after the input limits, low-speed and backwards-rolling handling."""

    shape: tuple[int, ...]  # broadcast shape of the call
    n: int  # number of elements
    pt: _PressureTerms
    pt_arr: bool  # pressure given per element
    mu: FloatArray | float  # mu_scale (flattened when an array)
    mu_arr: bool
    kappa: FloatArray  # reduced at low speed, clipped to KPUMIN/KPUMAX
    ukappa: FloatArray  # as given
    gamma: FloatArray  # clipped to CAMMIN/CAMMAX
    absvx: FloatArray  # |Vcx|
    vmin: float  # min Vcx
    ufz: FloatArray  # max(Fz, 0)
    fzc: FloatArray  # ... clipped to FZMAX
    fz_mz: FloatArray  # ... at least FZMIN where > 0 (the load of the Mz terms)
    low: FloatArray | None  # 1 - W_vlow, only when some |Vcx| <= VXLOW
    neg: FloatArray | None  # -1 where Vcx < 0, else 1 (only if some Vcx <= 0)
    sgn: FloatArray | None  # sign(Vcx) (only if some Vcx <= 0)
    a_s: FloatArray  # alpha* (4.E3) or alpha
    cos_ap: FloatArray  # cos(alpha') (4.E6)


class _PureSlip(NamedTuple):
    """Results of the pure-slip step that the combined-slip and aligning-moment steps use."""

    kxk: FloatArray  # Kxk, N
    kya: FloatArray  # Kya, N/rad
    kya_p: FloatArray  # Kya' = Kya + eps sign(Kya)
    sh: FloatArray  # rows SHx, SHy, SHy0
    sv: FloatArray  # rows SVx, SVy, SVy0, N
    dd: FloatArray  # rows Dx, Dy, Dy0, N
    by: FloatArray  # By
    fx0: FloatArray
    fy0: FloatArray
    fy0_g0: FloatArray  # Fy0 at zero camber


class TyreOutput(NamedTuple):
    """Steady-state tyre outputs (arrays of the broadcast input shape; SI units).

    fx, fy: forces N (wheel axes, ISO-W). mz: aligning torque Nm. my: rolling
    resistance moment Nm. t: pneumatic trail m (combined slip, incl. cos(alpha')
    and LFZO, as MFeval). mzr: residual torque Nm (combined slip). s: moment arm
    of Fx in Mz, m. kya: cornering stiffness N/rad (dFy0/dalpha_y at alpha_y = 0,
    at the actual camber; negative for the bundled files). kxk: longitudinal slip
    stiffness N (dFx0/dkappa). mu_x, mu_y: peak friction coefficients (incl.
    mu_scale). fx0, fy0: pure-slip forces N (fy0 at the actual camber). mz0:
    pure-slip aligning torque Nm, or None unless requested (it costs one more
    trail evaluation).
    """

    fx: FloatArray
    fy: FloatArray
    mz: FloatArray
    my: FloatArray
    t: FloatArray
    mzr: FloatArray
    s: FloatArray
    kya: FloatArray
    kxk: FloatArray
    mu_x: FloatArray
    mu_y: FloatArray
    fx0: FloatArray
    fy0: FloatArray
    mz0: FloatArray | None


class MagicFormula61:
    """MF 6.1 steady-state tyre (see the module docstring for frames and signs).

    Args:
        params: coefficients KEY -> value as read from a ``.tir`` file (upper-case keys);
            a :class:`~sim.tir.TirFile` makes the error messages name the line.
        use_alpha_star: use alpha* = tan(alpha) sign(Vcx) and gamma* = sin(gamma)
            (book, MFeval useMode 121) instead of alpha and gamma (TNO, useMode 111).
        source: name used in error messages (the file path).

    Raises:
        TirError: a required coefficient is missing (MF 6.1 gives it no default), a
            value is not a finite number or out of its range, a size, load, pressure,
            speed or stiffness no passenger-car or light-truck tyre has (a unit slip:
            :data:`PLAUSIBLE_RANGES`), or FITTYP is not 61/62.

    Implementation: every coefficient that is a polynomial in dfz, gamma* and gamma
    (with the scaling factors, and the pressure and friction factors when they are
    scalars, folded in) is evaluated by one matrix product; each step then evaluates
    its Magic Formula curves as rows of one array (pure slip: Fx0, Fy0, Fy0 at zero
    camber; combined slip: Gxa, Gyk and their normalisers; aligning moment: the
    trail, and the pure-slip trail on request). The coefficients do
    not change after construction; the small caches (pressure factors, weight
    matrices) are only ever added to, so an instance can be shared between threads.
    """

    params: dict[str, float | str]

    def __init__(
        self,
        params: Mapping[str, float | str],
        *,
        use_alpha_star: bool = True,
        source: str | None = None,
    ) -> None:
        src = source or str(getattr(params, "path", "") or "coefficient set")
        given = {str(k).upper(): v for k, v in params.items()}
        require_keys(params if isinstance(params, TirFile) else given, REQUIRED_KEYS, src, "the MF 6.1 tyre model")
        lines = params.lines if isinstance(params, TirFile) else {}

        def at(key: str) -> str:  # "<file>:<line>" of a key given in a file, else the source
            return f"{src}:{lines[key]}" if key in lines else src

        fittyp = given.get("FITTYP")
        if fittyp is not None and fittyp not in (61, 62, 61.0, 62.0):
            raise TirError(f"{at('FITTYP')}: FITTYP = {fittyp!r}: only Magic Formula 6.1/6.2 files are supported")

        full: dict[str, float | str] = dict(given)
        for key in SCALING_FACTORS:
            full.setdefault(key, 1.0)
        full.setdefault("LMUV", 0.0)
        for key in _COEFFICIENTS:
            full.setdefault(key, 0.0)
        for key, value in _RANGE_DEFAULTS.items():
            full.setdefault(key, value)
        full.setdefault("VXLOW", 1.0)
        full.setdefault("INFLPRES", full["NOMPRES"])

        numeric = dict.fromkeys((*REQUIRED_KEYS, *_COEFFICIENTS, *SCALING_FACTORS, "LMUV", "VXLOW",
                                 "INFLPRES", *_RANGE_DEFAULTS))
        for key in numeric:
            value = full[key]
            ok = isinstance(value, int | float) and not isinstance(value, bool)
            if not ok or (not math.isfinite(float(value)) and key not in _RANGE_DEFAULTS):
                raise TirError(f"{at(key)}: coefficient {key} = {value!r} is not a finite number")
            full[key] = float(value)
        for key in ("FNOMIN", "UNLOADED_RADIUS", "LONGVL", "NOMPRES", "VERTICAL_STIFFNESS",
                    "LONGITUDINAL_STIFFNESS", "LATERAL_STIFFNESS", "VXLOW", "LFZO", "LMUX", "LMUY"):
            if full[key] <= 0.0:
                raise TirError(f"{at(key)}: coefficient {key} = {full[key]!r} must be > 0")
        for key in ("PKY2", "PCY1", "PCX1", "QCZ1"):
            if full[key] == 0.0:
                raise TirError(f"{at(key)}: coefficient {key} must not be 0")
        for key in SCALING_FACTORS:  # (a coefficient that overflows the formula is refused by its figures' check)
            if abs(full[key]) > SCALING_LIMIT:
                raise TirError(f"{at(key)}: scaling factor {key} = {full[key]:g} is beyond +-{SCALING_LIMIT:g}: no "
                               "tyre is scaled so (a typing slip?)")
        if full["LMUV"] != 0.0:
            raise TirError(f"{at('LMUV')}: LMUV (speed-decaying friction) is not supported; set it to 0")
        for key in PLAUSIBLE_RANGES:  # a unit slip in a key the model reads or that states the tyre's size
            value = full.get(key)
            if value is None:
                continue
            if not isinstance(value, int | float) or isinstance(value, bool) or not math.isfinite(value):
                raise TirError(f"{at(key)}: {key} = {value!r} is not a finite number")
            why = implausible(key, float(value))
            if why is not None:
                raise TirError(f"{at(key)}: {why}")

        self.params = full
        self.use_alpha_star = bool(use_alpha_star)
        self.source = src
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            self._setup()  # coefficients so large that this overflows give non-finite outputs: overflow_problem

    @classmethod
    def from_tir(cls, path: str | Path, *, use_alpha_star: bool = True) -> MagicFormula61:
        """Build the model from a TNO ``.tir`` file (errors name the file and key/line)."""
        tir = read_tir(path)
        return cls(tir.params, use_alpha_star=use_alpha_star, source=tir.path)

    # ------------------------------------------------------------------ constants
    def _setup(self) -> None:
        p = {k: v for k, v in self.params.items() if isinstance(v, float)}
        self._p = p
        self.fz0 = p["FNOMIN"]
        self.r0 = p["UNLOADED_RADIUS"]
        self.v0 = p["LONGVL"]
        self.pi0 = p["NOMPRES"]
        self.inflpres = p["INFLPRES"]
        self.fz0p = p["LFZO"] * self.fz0  # Fz0' (4.E1)
        self.vxlow = p["VXLOW"]
        self._inv_fz0p = 1.0 / self.fz0p
        self._cx = p["PCX1"] * p["LCX"]  # (4.E11)
        self._cy = p["PCY1"] * p["LCY"]  # (4.E21)
        self._ct = p["QCZ1"]  # (4.E41)
        self._kya_base = p["PKY1"] * self.fz0p * p["LKY"]
        self._kya_fast = p["PKY4"] == 2.0  # sin(2 atan q) = 2 q / (1 + q^2)
        self._rows = self._row_definitions(p)
        # C of the curves evaluated together: Fx0, Fy0, Fy0(gamma = 0); Gxa, Gyk and their normalisers
        self._c3 = np.array([self._cx, self._cy, self._cy])[:, None]
        self._c_comb = np.array([p["RCX1"], p["RCY1"], p["RCX1"], p["RCY1"]])[:, None]
        self._my_k = -self.r0 * self.fz0 * p["LMY"]
        self._s_fy = self.r0 * p["LS"] * p["SSZ2"] / self.fz0  # s = s0 + this * Fy (A56)
        self._svyk_on = (p["LVYKA"] != 0.0 and p["RVY5"] != 0.0
                         and (p["RVY1"], p["RVY2"], p["RVY3"]) != (0.0, 0.0, 0.0))
        self._clip = {k: (p[k + "MIN"], p[k + "MAX"]) for k in ("KPU", "ALP", "CAM")}
        self._pressure_cache: dict[float, _PressureTerms] = {}
        self._pressure_array_cache: dict[tuple[tuple[int, ...], bytes], _PressureTerms] = {}
        self._weight_cache: dict[tuple[float | None, float | None], FloatArray] = {
            (None, None): self._build_weights(None, None)}

    @staticmethod
    def _row_definitions(p: Mapping[str, float]) -> dict[str, tuple[dict[str, float], int, str | None]]:
        """Coefficient polynomials: name -> (monomial -> coefficient, power of mu, pressure factor).

        Each row is one MF quantity with the scaling factors folded in; rows with a mu
        power are multiplied by (LMUX or LMUY) * mu_scale to that power, rows with a
        pressure factor by that attribute of :class:`_PressureTerms`.
        """
        g = p.__getitem__
        lkyc, ley, r0 = g("LKYC"), g("LEY"), p["UNLOADED_RADIUS"]
        ex = {"1": g("PEX1") * g("LEX"), "d": g("PEX2") * g("LEX"), "d2": g("PEX3") * g("LEX")}
        kdt = r0 / (p["LFZO"] * p["FNOMIN"]) * g("LTR") * g("LFZO")  # t is multiplied by LFZO (MFeval)
        kbt = g("LKY")
        k2p = _TWO_OVER_PI
        return {
            # pure longitudinal (4.E11-4.E18)
            "MUX": ({"1": g("PDX1"), "d": g("PDX2"), "c2": -g("PDX1") * g("PDX3"),
                     "dc2": -g("PDX2") * g("PDX3")}, 1, "mux"),
            "KXK": ({"1": g("PKX1") * g("LKX"), "d": g("PKX2") * g("LKX")}, 0, "kxk"),
            "SHX": ({"1": g("PHX1") * g("LHX"), "d": g("PHX2") * g("LHX")}, 0, None),
            "SVX": ({"1": g("PVX1") * g("LVX"), "d": g("PVX2") * g("LVX")}, 1, None),
            "EX0": (ex, 0, None),
            "EX1": ({k: -g("PEX4") * v for k, v in ex.items()}, 0, None),
            # pure lateral (4.E19-4.E30); KYA is PKY1 Fz0' LKY (1 - PKY3 |g*|) before the sine
            "KYA": ({"1": 1.0, "ag": -g("PKY3")}, 0, "kya"),
            "KYAD": ({"1": g("PKY2"), "g2": g("PKY5")}, 0, "pky2"),
            "KYGG": ({"g": g("PKY6") * lkyc, "dg": g("PKY7") * lkyc}, 0, "kyg"),  # Kyg0 g* / Fz
            "SVYG": ({"g": g("PVY3") * lkyc, "dg": g("PVY4") * lkyc}, 1, None),  # SVyg / Fz
            "SHY0": ({"1": g("PHY1") * g("LHY"), "d": g("PHY2") * g("LHY")}, 0, None),
            "SVY0": ({"1": g("PVY1") * g("LVY"), "d": g("PVY2") * g("LVY")}, 1, None),
            "SVY": ({"1": g("PVY1") * g("LVY"), "d": g("PVY2") * g("LVY"), "g": g("PVY3") * lkyc,
                     "dg": g("PVY4") * lkyc}, 1, None),
            "MUY0": ({"1": g("PDY1"), "d": g("PDY2")}, 1, "muy"),
            "MUY": ({"1": g("PDY1"), "d": g("PDY2"), "g2": -g("PDY1") * g("PDY3"),
                     "dg2": -g("PDY2") * g("PDY3")}, 1, "muy"),
            "EYA": ({"1": g("PEY1") * ley, "d": g("PEY2") * ley, "g2": g("PEY1") * g("PEY5") * ley,
                     "dg2": g("PEY2") * g("PEY5") * ley}, 0, None),
            "EYB": ({"1": -g("PEY1") * g("PEY3") * ley, "d": -g("PEY2") * g("PEY3") * ley,
                     "g": -g("PEY1") * g("PEY4") * ley, "dg": -g("PEY2") * g("PEY4") * ley}, 0, None),
            "EY0A": ({"1": g("PEY1") * ley, "d": g("PEY2") * ley}, 0, None),
            "EY0B": ({"1": -g("PEY1") * g("PEY3") * ley, "d": -g("PEY2") * g("PEY3") * ley}, 0, None),
            # combined slip (4.E50-4.E67)
            "EXA": ({"1": g("REX1"), "d": g("REX2")}, 0, None),
            "BXA": ({"1": g("RBX1") * g("LXAL"), "g2": g("RBX3") * g("LXAL")}, 0, None),
            "DVYK": ({"1": g("RVY1") * g("LVYKA"), "d": g("RVY2") * g("LVYKA"),
                      "g": g("RVY3") * g("LVYKA")}, 0, None),
            "SHYK": ({"1": g("RHY1"), "d": g("RHY2")}, 0, None),
            "EYK": ({"1": g("REY1"), "d": g("REY2")}, 0, None),
            "BYK": ({"1": g("RBY1") * g("LYKA"), "g2": g("RBY4") * g("LYKA")}, 0, None),
            # aligning torque (4.E34-4.E47, A56-A60)
            "SHT": ({"1": g("QHZ1"), "d": g("QHZ2"), "g": g("QHZ3"), "dg": g("QHZ4")}, 0, None),
            "DT": ({"1": g("QDZ1") * kdt, "d": g("QDZ2") * kdt, "c": g("QDZ1") * g("QDZ3") * kdt,
                    "dc": g("QDZ2") * g("QDZ3") * kdt, "c2": g("QDZ1") * g("QDZ4") * kdt,
                    "dc2": g("QDZ2") * g("QDZ4") * kdt}, 0, "dt"),
            "BT": ({"1": g("QBZ1") * kbt, "d": g("QBZ2") * kbt, "d2": g("QBZ3") * kbt,
                    "c": g("QBZ1") * g("QBZ4") * kbt, "dc": g("QBZ2") * g("QBZ4") * kbt,
                    "d2c": g("QBZ3") * g("QBZ4") * kbt, "ac": g("QBZ1") * g("QBZ5") * kbt,
                    "dac": g("QBZ2") * g("QBZ5") * kbt, "d2ac": g("QBZ3") * g("QBZ5") * kbt}, -1, None),
            "ET1": ({"1": g("QEZ1"), "d": g("QEZ2"), "d2": g("QEZ3")}, 0, None),
            "ET2": ({"1": g("QEZ1") * g("QEZ4") * k2p, "d": g("QEZ2") * g("QEZ4") * k2p,
                     "d2": g("QEZ3") * g("QEZ4") * k2p, "g": g("QEZ1") * g("QEZ5") * k2p,
                     "dg": g("QEZ2") * g("QEZ5") * k2p, "d2g": g("QEZ3") * g("QEZ5") * k2p}, 0, None),
            "DRA": ({"1": g("QDZ6") * g("LRES") * r0, "d": g("QDZ7") * g("LRES") * r0,
                     "gag": g("QDZ10") * g("LKZC") * r0, "dgag": g("QDZ11") * g("LKZC") * r0}, 1, None),
            "DRB": ({"g": g("QDZ8") * g("LKZC") * r0, "dg": g("QDZ9") * g("LKZC") * r0}, 1, "dr"),
            "S0": ({"1": g("SSZ1") * r0 * g("LS"), "c": g("SSZ3") * r0 * g("LS"),
                    "dc": g("SSZ4") * r0 * g("LS")}, 0, None),
        }

    def _weights(self, pt: _PressureTerms | None, mu: float | None) -> tuple[FloatArray, bool]:
        """Matrix of the coefficient polynomials and whether pressure/friction are folded in.

        Scalar pressure and mu_scale are folded into the (cached) matrix; when the cache
        is full the base matrix is returned and the caller scales the rows instead.
        """
        key = (None if pt is None else pt.key, mu)
        w = self._weight_cache.get(key)
        if w is not None:
            return w, True
        if len(self._weight_cache) >= 64:
            return self._weight_cache[(None, None)], False
        w = self._weight_cache[key] = self._build_weights(pt, mu)
        return w, True

    def _build_weights(self, pt: _PressureTerms | None, mu: float | None) -> FloatArray:
        p = self._p
        w = np.zeros((_NROWS, len(_MONOMIALS)))
        for name, (coefs, mu_pow, pname) in self._rows.items():
            factor = 1.0
            if mu_pow:
                factor *= _pow(p["LMUX"] if name in ("MUX", "SVX") else p["LMUY"], mu_pow)
                if mu is not None:
                    factor *= _pow(mu, mu_pow)
            if pname is not None and pt is not None:
                factor *= getattr(pt, pname)
            if name == "KYA":
                factor *= self._kya_base
            for mono, coef in coefs.items():
                if coef != 0.0:
                    w[_R[name], _M[mono]] = coef * factor
        return w

    def _pressure_terms(
        self, pressure: float | FloatArray | None, shape: tuple[int, ...] | None = None
    ) -> _PressureTerms:
        """Pressure factors for a pressure clipped to PRESMIN/PRESMAX.

        A scalar is cached by value; an array is broadcast to ``shape``, flattened and
        cached by content (the simulator passes the same per-wheel pressures at every
        call), so its factors are computed once.
        """
        p = self._p
        pres = self.inflpres if pressure is None else _as_float(pressure)
        if isinstance(pres, float):
            pres = min(max(pres, p["PRESMIN"]), p["PRESMAX"])
            if not pres > 0.0:
                raise ValueError(f"inflation pressure must be > 0 Pa, got {pressure!r}")
            cached = self._pressure_cache.get(pres)
            if cached is None:
                cached = _PressureTerms(p, pres)
                if len(self._pressure_cache) < 64:
                    self._pressure_cache[pres] = cached
            return cached
        arr = _flat(pres, shape if shape is not None else pres.shape)
        key = (arr.shape, arr.tobytes())
        cached = self._pressure_array_cache.get(key)
        if cached is None:
            clipped = np.minimum(np.maximum(arr, p["PRESMIN"]), p["PRESMAX"])
            if not np.all(clipped > 0.0):
                raise ValueError("inflation pressure must be > 0 Pa")
            cached = _PressureTerms(p, clipped)
            if len(self._pressure_array_cache) >= 8:
                self._pressure_array_cache.pop(next(iter(self._pressure_array_cache)))
            self._pressure_array_cache[key] = cached
        return cached

    # ------------------------------------------------------------------ public API
    def steady_state(
        self,
        fz: ArrayLike,
        kappa: ArrayLike,
        alpha: ArrayLike,
        gamma: ArrayLike,
        vx: ArrayLike,
        pressure: ArrayLike | None = None,
        mu_scale: ArrayLike = 1.0,
        *,
        pure_slip_mz: bool = False,
    ) -> TyreOutput:
        """Steady-state forces and moments (ISO-W, see the module docstring).

        Args:
            fz: tyre load Fz, N (negative -> 0).
            kappa: longitudinal slip (omega Re - Vcx) / |Vcx|, -.
            alpha: slip angle atan(Vsy / |Vcx|), rad.
            gamma: inclination angle, rad.
            vx: longitudinal speed Vcx of the wheel centre in wheel axes, m/s.
            pressure: inflation pressure, Pa; None -> INFLPRES of the file.
            mu_scale: road friction relative to the test surface (> 0); multiplies
                LMUX and LMUY.
            pure_slip_mz: also compute the pure-slip Mz0 (one more trail evaluation).

        All array inputs (pressure and mu_scale included) broadcast against each
        other, e.g. (B, 4) loads with a (B, 1) speed. Returns a :class:`TyreOutput`
        of arrays of the broadcast shape (0-d for scalar inputs).

        Steps: operating point (input limits, low speed, backwards rolling),
        coefficient polynomials, pure slip (Fx0, Fy0), combined slip (Fx, Fy),
        aligning moment (Mz), rolling resistance (My).
        """
        op = self._operating_point(fz, kappa, alpha, gamma, vx, pressure, mu_scale)
        pc, dfz = self._coefficients(op)
        pure = self._pure_slip(op, pc, dfz)
        fx, fy, gyk = self._combined_slip(op, pc, pure)
        t, mzr, s, mz, mz0 = self._aligning_moment(op, pc, pure, fx, fy, gyk, pure_slip_mz)
        my = self._rolling_resistance(op.ufz, fx, op.absvx, op.vmin if op.vmin > self.vxlow else None, op.gamma,
                                      op.pt, op.ukappa, op.sgn)
        out = TyreOutput(fx, fy, mz, my, t, mzr, s, pure.kya, pure.kxk, pc[_R["MUX"]], pc[_R["MUY"]], pure.fx0,
                         pure.fy0, mz0)
        if op.shape != (op.n,):
            return TyreOutput._make(None if a is None else a.reshape(op.shape) for a in out)
        return out

    def _operating_point(
        self,
        fz: ArrayLike,
        kappa: ArrayLike,
        alpha: ArrayLike,
        gamma: ArrayLike,
        vx: ArrayLike,
        pressure: ArrayLike | None,
        mu_scale: ArrayLike,
    ) -> _OperatingPoint:
        """Broadcast and flatten the inputs; input limits, low speed, backwards rolling (MFeval parseInputs)."""
        p = self._p
        pres = None if pressure is None else _as_float(pressure)
        pt_arr = isinstance(pres, np.ndarray)
        mu = _as_float(mu_scale)
        mu_arr = not isinstance(mu, float)
        if not mu_arr and not mu > 0.0:
            raise ValueError(f"mu_scale must be > 0, got {mu_scale!r}")

        # copy-free when the inputs share one shape
        ins = (_f64(fz), _f64(kappa), _f64(alpha), _f64(gamma), _f64(vx))
        shape = ins[0].shape
        if any(a.shape != shape for a in ins) or pt_arr or mu_arr:
            extra = [np.shape(x) for x, is_arr in ((pres, pt_arr), (mu, mu_arr)) if is_arr]
            shape = np.broadcast_shapes(*(a.shape for a in ins), *extra)
        n = math.prod(shape)
        fz, kappa, alpha, gamma, vx = (_flat(a, shape) for a in ins)
        pt = self._pressure_terms(pres, shape)
        if mu_arr:
            mu = _flat(mu, shape)  # type: ignore[arg-type]

        ukappa = kappa
        ufz = np.maximum(fz, 0.0)
        vxlow = self.vxlow
        vmin = float(vx.min()) if n else 1.0
        low: FloatArray | None = None  # smooth reduction 1 - W_vlow, only below VXLOW
        neg: FloatArray | None = None  # -1 where Vcx < 0, else 1 (only if some Vcx <= 0)
        sgn: FloatArray | None = None  # sign(Vcx)
        if vmin > vxlow:
            absvx = vx
        else:
            absvx = np.abs(vx)
            if vmin <= 0.0:
                sgn = np.sign(vx)
                neg = np.where(vx < 0.0, -1.0, 1.0)
            is_low = absvx <= vxlow
            if is_low.any():
                lin = np.where(is_low, absvx / vxlow, 1.0)
                low = np.where(is_low, 0.5 - 0.5 * np.cos(math.pi / vxlow * vx), 1.0)
                kappa = kappa * lin
                speed_sum = absvx + np.abs(np.tan(alpha) * vx)
                alpha = np.where(speed_sum < vxlow, alpha * (speed_sum / vxlow), alpha)
        fzc = np.minimum(ufz, p["FZMAX"]) if p["FZMAX"] < math.inf else ufz
        kappa = _clip(kappa, *self._clip["KPU"])
        alpha = _clip(alpha, *self._clip["ALP"])
        gamma = _clip(gamma, *self._clip["CAM"])
        fzmin = p["FZMIN"]
        fz_mz = fzc if fzmin <= 0.0 else np.where(fzc <= 0.0, 0.0, np.maximum(fzc, fzmin))

        # basic variables (MFeval calculateBasic)
        tan_a = np.tan(alpha)
        cos_ap = np.multiply(tan_a, tan_a)
        cos_ap += 1.0
        np.sqrt(cos_ap, out=cos_ap)
        cos_ap *= absvx
        cos_ap += _EPS
        np.divide(vx, cos_ap, out=cos_ap)  # cos(alpha') = Vcx / (Vc + eps) (4.E6)
        if self.use_alpha_star:
            a_s = tan_a if sgn is None else tan_a * sgn  # alpha* (4.E3)
        else:
            a_s = alpha
        return _OperatingPoint(shape, n, pt, pt_arr, mu, mu_arr, kappa, ukappa, gamma, absvx, vmin, ufz, fzc,
                               fz_mz, low, neg, sgn, a_s, cos_ap)

    def _coefficients(self, op: _OperatingPoint) -> tuple[FloatArray, FloatArray]:
        """(rows of _ROW_NAMES, dfz): every coefficient polynomial in (dfz, gamma*, gamma) by one matrix product.

        The scaling factors, and the pressure and friction factors, are folded in.
        Row ``KYA0`` (zero) is filled by :meth:`_pure_slip`.
        """
        n, gamma = op.n, op.gamma
        w, folded = self._weights(None if op.pt_arr else op.pt, None if op.mu_arr else op.mu)  # type: ignore[arg-type]
        x = np.empty((len(_MONOMIALS), n))
        x[0] = 1.0
        d = x[1]
        np.multiply(op.fzc, self._inv_fz0p, out=d)
        d -= 1.0  # dfz (4.E2a)
        d2 = np.multiply(d, d, out=x[2])
        g = x[3]
        if self.use_alpha_star:
            np.sin(gamma, out=g)  # gamma* (4.E4)
        else:
            g[:] = gamma
        np.multiply(d, g, out=x[4])
        np.multiply(d2, g, out=x[5])
        g2 = np.multiply(g, g, out=x[6])
        np.multiply(d, g2, out=x[7])
        ag = np.abs(g, out=x[8])
        gag = np.multiply(g, ag, out=x[9])
        np.multiply(d, gag, out=x[10])
        c = x[11]
        c[:] = gamma
        np.multiply(d, c, out=x[12])
        np.multiply(d2, c, out=x[13])
        c2 = np.multiply(c, c, out=x[14])
        np.multiply(d, c2, out=x[15])
        ac = np.abs(c, out=x[16])
        np.multiply(d, ac, out=x[17])
        np.multiply(d2, ac, out=x[18])
        pc = w @ x  # (rows, n), see _ROW_NAMES
        if op.pt_arr or not folded:
            for name, attr in _PRESSURE_ROWS:
                pc[_R[name]] *= getattr(op.pt, attr)
        if op.mu_arr or not folded:
            mu = op.mu
            pc[_D] *= mu
            pc[_SV] *= mu
            for name in ("SVYG", "DRA", "DRB"):
                pc[_R[name]] *= mu
            pc[_R["BT"]] /= mu
        return pc, d

    def _pure_slip(self, op: _OperatingPoint, pc: FloatArray, dfz: FloatArray) -> _PureSlip:
        """Pure-slip Fx0 (4.E9-4.E18), Fy0 and Fy0 at zero camber (4.E19-4.E30), with their stiffnesses and shifts."""
        p = self._p
        eps = _EPS
        pt, fzc = op.pt, op.fzc
        r_ = _R
        # slip stiffnesses Kxk (4.E15), Kya (4.E25) and Kya at gamma = 0
        kxk = pc[r_["KXK"]]
        kxk *= fzc
        if p["PKX3"] != 0.0:
            kxk *= np.exp(p["PKX3"] * dfz)
        fz_n = dfz + 1.0
        kya, kya0 = pc[r_["KYA"]], pc[r_["KYA0"]]
        if op.pt_arr:
            q0 = fz_n / (p["PKY2"] * pt.pky2)
        else:
            q0 = fz_n * (1.0 / (p["PKY2"] * pt.pky2))  # type: ignore[operator]
        if self._kya_fast:  # PKY4 = 2: sin(2 atan q) = 2 q / (1 + q^2)
            q = np.divide(fz_n, pc[r_["KYAD"]])
            kya *= q
            q *= q
            q += 1.0
            kya /= q
            kya *= 2.0
            np.multiply(q0, q0, out=kya0)
            kya0 += 1.0
            np.divide(q0, kya0, out=kya0)
            kya0 *= 2.0
        else:
            qq = np.empty((2, op.n))
            np.divide(fz_n, pc[r_["KYAD"]], out=qq[0])
            qq[1] = q0
            np.arctan(qq, out=qq)
            qq *= p["PKY4"]
            np.sin(qq, out=qq)
            kya *= qq[0]
            kya0[:] = qq[1]
        kya0 *= self._kya_base * pt.kya
        kya_p = np.copysign(eps, kya)
        kya_p += kya  # Kya' (4.E39)

        # shifts of Fx0, Fy0, Fy0(gamma = 0) (4.E17, 4.E18, 4.E27-4.E29)
        sh = pc[_SH]  # rows SHx, SHy, SHy0
        shy = np.subtract(pc[r_["KYGG"]], pc[r_["SVYG"]], out=sh[1])  # (Kyg0 gamma* - SVyg) / Fz
        shy *= fzc
        shy /= kya_p
        shy += sh[2]
        sv = pc[_SV]  # rows SVx, SVy, SVy0
        sv *= fzc
        if op.low is not None:
            sh *= op.low
            sv *= op.low
        x = np.empty((3, op.n))  # kappa_x, alpha_y, alpha_y(gamma = 0)
        np.add(op.kappa, sh[0], out=x[0])
        np.add(sh[1:], op.a_s, out=x[1:])
        # D, B = K / (C D + eps sign D), E = min(E0 + E1 sign(x), 1) of the three curves
        dd = np.multiply(pc[_D], fzc)  # Dx, Dy, Dy0 (4.E12, 4.E22)
        den = np.multiply(dd, self._c3)
        den += np.copysign(eps, dd)
        b = np.divide(pc[_K], den)
        by = b[1].copy()
        e = np.sign(x)
        e *= pc[_E1]
        e += pc[_E0]
        np.minimum(e, 1.0, out=e)

        f0 = _magic_formula(b, x, e, self._c3)
        f0 *= dd
        f0 += sv  # Fx0, Fy0, Fy0(gamma = 0) (4.E9, 4.E19)
        if op.neg is not None:
            if self.use_alpha_star:
                f0 *= op.neg
            else:
                f0[0] *= op.neg
        return _PureSlip(kxk, kya, kya_p, sh, sv, dd, by, f0[0], f0[1], f0[2])

    def _combined_slip(
        self, op: _OperatingPoint, pc: FloatArray, pure: _PureSlip
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(Fx, Fy, Gyk): combined-slip weighting functions Gxa, Gyk and kappa-induced SVyk (4.E50-4.E67)."""
        p = self._p
        r_ = _R
        n, a_s, kappa = op.n, op.a_s, op.kappa
        rr = np.empty((2, n))
        np.multiply(kappa, p["RBX2"], out=rr[0])
        np.subtract(a_s, p["RBY3"], out=rr[1])
        rr[1] *= p["RBY2"]
        rr *= rr
        rr += 1.0
        np.sqrt(rr, out=rr)
        # rows: Gxa and Gyk numerators, their normalisers (the curves at alpha* = 0, kappa = 0)
        b = np.empty((4, n))
        np.divide(pc[r_["BXA"]:r_["BYK"] + 1], rr, out=b[:2])  # B cos(atan(...))
        b[2:] = b[:2]
        shyk = pc[r_["SHYK"]]
        x = np.empty((4, n))
        np.add(a_s, p["RHX1"], out=x[0])
        np.add(kappa, shyk, out=x[1])
        x[2] = p["RHX1"]
        x[3] = shyk
        e = np.empty((4, n))
        np.minimum(pc[r_["EXA"]:r_["EYK"] + 1], 1.0, out=e[:2])
        e[2:] = e[:2]
        v = _magic_formula(b, x, e, self._c_comb, _COS)
        gg = np.divide(v[:2], v[2:])  # Gxa, Gyk (4.E51, 4.E59)
        fx = np.multiply(gg[0], pure.fx0)  # (4.E50)
        gyk = gg[1]
        fy = np.multiply(gyk, pure.fy0)
        if self._svyk_on:  # kappa-induced side force SVyk (4.E66/4.E67)
            r = np.multiply(a_s, p["RVY4"])
            r *= r
            r += 1.0
            np.sqrt(r, out=r)
            svyk = np.multiply(pc[r_["DVYK"]], pure.dd[1])
            svyk /= r
            np.multiply(kappa, p["RVY6"], out=r)
            np.arctan(r, out=r)
            r *= p["RVY5"]
            np.sin(r, out=r)
            svyk *= r
            if op.low is not None:
                svyk *= op.low
            fy += svyk  # (4.E58)
        return fx, fy, gyk

    def _aligning_moment(
        self, op: _OperatingPoint, pc: FloatArray, pure: _PureSlip, fx: FloatArray, fy: FloatArray,
        gyk: FloatArray, pure_slip_mz: bool,
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray | None]:
        """(t, Mzr, s, Mz, Mz0): Mz = -t Fy' + Mzr + s Fx (4.E31-4.E47, 4.E71-4.E75, A54-A60)."""
        p = self._p
        r_ = _R
        n, a_s = op.n, op.a_s
        br = np.multiply(pure.by, p["QBZ10"] * self._cy)  # Br (4.E45)
        br += p["QBZ9"] * p["LKY"] / (p["LMUY"] * op.mu)
        # alpha_t,eq and alpha_r,eq (A54/A55)
        ang = np.empty((2, n))
        alpha_t = np.add(a_s, pc[r_["SHT"]], out=ang[0])  # (4.E34)
        alpha_r = np.divide(pure.sv[1], pure.kya_p, out=ang[1])
        alpha_r += pure.sh[1]
        alpha_r += a_s  # alpha_r = alpha* + SHy + SVy / Kya' (4.E37/4.E38)
        ratio = np.divide(pure.kxk, pure.kya_p)
        ratio *= op.kappa
        ratio *= ratio
        eq = np.tan(ang)
        eq *= eq
        eq += ratio
        np.sqrt(eq, out=eq)
        np.arctan(eq, out=eq)
        np.copysign(eq, ang, out=eq)
        # trail curve at alpha_t,eq (and at alpha_t for Mz0): Bt (A58), Ct, Et (4.E44)
        rows = 2 if pure_slip_mz else 1
        b, x, e = np.empty((rows, n)), np.empty((rows, n)), np.empty((rows, n))
        bt = pc[r_["BT"]]
        b[0] = bt
        x[0] = eq[0]
        et = np.multiply(bt, alpha_t, out=e[0])
        et *= self._ct
        np.arctan(et, out=et)
        et *= pc[r_["ET2"]]
        et += pc[r_["ET1"]]
        np.minimum(et, 1.0, out=et)
        if pure_slip_mz:
            b[1] = bt
            x[1] = alpha_t
            e[1] = et
        v = _magic_formula(b, x, e, self._ct, _COS)

        dt = pc[r_["DT"]]
        dt *= op.fz_mz
        t = np.multiply(v[0], dt)
        t *= op.cos_ap  # (4.E73), LFZO folded into the Dt row
        dr = np.add(pc[r_["DRA"]], pc[r_["DRB"]])
        dr *= op.fz_mz
        dr *= np.cos(a_s)
        if op.sgn is not None:
            dr *= op.sgn  # (4.E47)
        mzr = np.multiply(br, eq[1])
        mzr *= mzr
        mzr += 1.0
        np.sqrt(mzr, out=mzr)
        np.divide(dr, mzr, out=mzr)  # Dr cos(atan(Br alpha_r,eq)), Cr = 1 (4.E75)
        if op.low is not None:
            t *= op.low
            mzr *= op.low
        s = np.multiply(fy, self._s_fy)
        s += pc[r_["S0"]]  # (A56)
        mz = np.multiply(t, gyk)
        mz *= pure.fy0_g0  # t Fy', Fy' = Gyk Fy0(gamma = 0) (4.E74)
        np.subtract(mzr, mz, out=mz)
        mz += s * fx

        mz0 = None
        if pure_slip_mz:  # (4.E31-4.E36)
            t0 = v[1] * dt * op.cos_ap / p["LFZO"]
            br *= alpha_r
            br *= br
            br += 1.0
            np.sqrt(br, out=br)
            mz0 = dr * op.cos_ap / br - t0 * pure.fy0_g0
        return t, mzr, s, mz, mz0

    def _rolling_resistance(
        self,
        ufz: FloatArray,
        fx: FloatArray,
        absvx: FloatArray,
        min_absvx: float | None,
        gamma: FloatArray,
        pt: _PressureTerms,
        ukappa: FloatArray,
        sgn: FloatArray | None,
    ) -> FloatArray:
        """My (Besselink 2010 A48) with MFeval's low-Fz, backwards and low-speed handling.

        My = -R0 Fz0 LMY (QSY1 + QSY2 Fx/Fz0 + QSY3 |Vcx/V0| + QSY4 (Vcx/V0)^4
              + (QSY5 + QSY6 Fz/Fz0) gamma^2) (Fz/Fz0)^QSY7 (p/p0)^QSY8
        with the unclipped load Fz (below FZMIN: Fz^2/FZMIN, as MFeval).
        """
        p = self._p
        fz0 = self.fz0
        fzmin = p["FZMIN"]
        fz = ufz if fzmin <= 0.0 else np.where(ufz < fzmin, ufz * ufz / fzmin, ufz)
        acc = np.multiply(absvx, p["QSY3"] / self.v0)
        acc += p["QSY1"]
        if p["QSY4"] != 0.0:
            v4 = np.multiply(absvx, absvx)
            v4 *= v4
            v4 *= p["QSY4"] / self.v0**4
            acc += v4
        if p["QSY2"] != 0.0:
            acc += (p["QSY2"] / fz0) * fx
        if p["QSY5"] != 0.0 or p["QSY6"] != 0.0:
            acc += (p["QSY5"] + (p["QSY6"] / fz0) * fz) * gamma * gamma
        qsy7 = p["QSY7"]
        k = self._my_k * pt.my
        if qsy7 == 1.0:
            acc *= fz
            k /= fz0
        elif qsy7 != 0.0:
            acc *= np.power(fz, qsy7)
            k /= _pow(fz0, qsy7)
        acc *= k
        my = acc
        if sgn is not None:
            my *= sgn  # backwards: sign flipped; Vcx = 0: My = 0 (MFeval)
        # MFeval's low-speed / locked-wheel handling: a sine ramp of My for kappa in
        # [-1 - VXLOW - h, h], h = VXLOW/|Vcx| - 1, and a sign change below that band.
        if min_absvx is None:
            min_absvx = float(absvx.min()) if absvx.size else 1.0
        if ukappa.size and float(ukappa.min()) <= self.vxlow / max(min_absvx, 1e-300) - 1.0:
            with np.errstate(divide="ignore", invalid="ignore"):
                high = self.vxlow / absvx - 1.0
                low_lim = -1.0 - self.vxlow - high
                in_band = (ukappa >= low_lim) & (ukappa <= high)
                red = np.sin(0.5 * math.pi * (ukappa + 1.0) / (high + 1.0))
                my = np.where(in_band, my * red, np.where(ukappa < low_lim, -my, my))
        return my

    def relaxation_lengths(
        self, fz: ArrayLike, pressure: ArrayLike | None = None, gamma: ArrayLike = 0.0
    ) -> tuple[FloatArray, FloatArray]:
        """MF 6.1 relaxation lengths (sigma_kappa, sigma_alpha) in m at zero slip.

        sigma_kappa = |Kxk / Cx| and sigma_alpha = |Kya / Cy| (Besselink 2010 eq. 19,
        as MFeval) with Cx = LONGITUDINAL_STIFFNESS (1 + PCFX1 dfz + PCFX2 dfz^2)
        (1 + PCFX3 dpi) and Cy = LATERAL_STIFFNESS (1 + PCFY1 dfz + PCFY2 dfz^2)
        (1 + PCFY3 dpi). Fz, pressure and gamma are clipped as in :meth:`steady_state`;
        Kxk and Kya do not depend on mu_scale.
        """
        kxk, kya, cx, cy = self.stiffnesses(fz, pressure, gamma)
        return np.abs(kxk / cx), np.abs(kya / cy)

    def stiffnesses(
        self, fz: ArrayLike, pressure: ArrayLike | None = None, gamma: ArrayLike = 0.0
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """(Kxk N, Kya N/rad, Cx N/m, Cy N/m): slip stiffnesses and overall carcass stiffnesses.

        Kxk (4.E15) and Kya (4.E25) at zero slip, Cx and Cy (Besselink 2010 eqs. 17/18).
        """
        p = self._p
        pres = None if pressure is None else _as_float(pressure)
        fz_a, g_a = _f64(fz), _f64(gamma)
        shape = np.broadcast_shapes(fz_a.shape, g_a.shape, np.shape(pres) if pres is not None else ())
        pt = self._pressure_terms(pres, shape)
        fzc = np.maximum(_flat(fz_a, shape), 0.0)
        if p["FZMAX"] < math.inf:
            np.minimum(fzc, p["FZMAX"], out=fzc)
        g = _clip(_flat(g_a, shape), *self._clip["CAM"])
        g_s = np.sin(g) if self.use_alpha_star else g
        dfz = fzc * self._inv_fz0p
        fz_n = dfz.copy()
        dfz -= 1.0
        kxk = dfz * p["PKX2"]
        kxk += p["PKX1"]
        kxk *= fzc
        if p["PKX3"] != 0.0:
            kxk *= np.exp(p["PKX3"] * dfz)
        kxk *= pt.kxk * p["LKX"]
        g2 = g_s * g_s
        q = fz_n / ((p["PKY2"] + p["PKY5"] * g2) * pt.pky2)
        if self._kya_fast:  # sin(2 atan q) = 2 q / (1 + q^2)
            kya = 2.0 * q
            q *= q
            q += 1.0
            kya /= q
        else:
            kya = np.arctan(q)
            kya *= p["PKY4"]
            np.sin(kya, out=kya)
        kya *= self._kya_base * pt.kya
        if p["PKY3"] != 0.0:
            kya *= 1.0 - p["PKY3"] * np.abs(g_s)
        cx = (p["PCFX2"] * dfz + p["PCFX1"]) * dfz
        cx += 1.0
        cx *= p["LONGITUDINAL_STIFFNESS"] * pt.cx
        cy = (p["PCFY2"] * dfz + p["PCFY1"]) * dfz
        cy += 1.0
        cy *= p["LATERAL_STIFFNESS"] * pt.cy
        return kxk.reshape(shape), kya.reshape(shape), cx.reshape(shape), cy.reshape(shape)

    def effective_rolling_radius(
        self, fz: ArrayLike, omega: ArrayLike, pressure: ArrayLike | None = None
    ) -> FloatArray:
        """MF 6.1 effective rolling radius Re in m (Besselink 2010 eqs. 1, 5, 7; as MFeval).

        Re = R0 (Q_RE0 + Q_V1 (omega R0 / V0)^2)
             - Fz0 / Cz (DREFF atan(BREFF Fz / Fz0) + FREFF Fz / Fz0),
        Cz = VERTICAL_STIFFNESS (1 + PFZ1 dpi); Fz is the unclipped load (>= 0),
        omega the wheel spin rate in rad/s.
        """
        p = self._p
        pres = None if pressure is None else _as_float(pressure)
        fz_a, om_a = _f64(fz), _f64(omega)
        shape = np.broadcast_shapes(fz_a.shape, om_a.shape, np.shape(pres) if pres is not None else ())
        pt = self._pressure_terms(pres, shape)
        fz_n = np.maximum(_flat(fz_a, shape), 0.0)
        fz_n *= 1.0 / self.fz0
        w = _flat(om_a, shape) * (self.r0 / self.v0)
        w *= w
        w *= p["Q_V1"]
        w += p["Q_RE0"]
        w *= self.r0  # R_omega (eq. 1)
        defl = np.arctan(p["BREFF"] * fz_n)
        defl *= p["DREFF"]
        fz_n *= p["FREFF"]
        defl += fz_n
        defl *= self.fz0 / (p["VERTICAL_STIFFNESS"] * pt.cz)
        w -= defl
        return w.reshape(shape)


# ------------------------------------------------------------------ overflow
#: the tyre whose coefficients stand for "a typical passenger-car tyre" when :func:`overflowing` looks for the
#: coefficient that makes a model overflow (the default car's tyre)
TYPICAL_TYRE = "c_segment_205_55R16.tir"
#: most coefficients :func:`overflowing` names together
_MOST_NAMED = 5
#: outputs checked by :func:`non_finite_outputs`, by name
_OUTPUT_NAMES = {"fx": "Fx", "fy": "Fy", "mz": "Mz", "my": "My", "t": "trail", "kya": "cornering stiffness",
                 "kxk": "slip stiffness"}


#: The largest force a tyre gives per unit of its load in its usual range (Fx or Fy over Fz): a racing slick on a
#: dry track gives about 2, a road tyre 0.8-1.3; five times its load is no tyre's (a coefficient typed wrong).
FORCE_RATIO_LIMIT = 5.0


def _usual_range(model: MagicFormula61) -> tuple[TyreOutput, TyreOutput, FloatArray]:
    """The model's pure side-slip and pure longitudinal-slip outputs over the usual range of
    :func:`non_finite_outputs`, and the wheel loads they are at (N, broadcastable to them)."""
    p = model._p
    fz = np.array([0.5, 1.0, 1.5])[:, None, None] * p["FNOMIN"]
    pres = np.array([0.9, 1.0, 1.1])[None, :, None] * p["INFLPRES"]
    with np.errstate(all="ignore"):
        side = model.steady_state(fz, 0.0, np.linspace(-30.0, 30.0, 61) * (math.pi / 180.0), 0.0, p["LONGVL"], pres)
        longi = model.steady_state(fz, np.linspace(-0.3, 0.3, 61), 0.0, 0.0, p["LONGVL"], pres)
    return side, longi, fz


def non_finite_outputs(model: MagicFormula61, sweep: tuple[TyreOutput, TyreOutput, FloatArray] | None = None
                       ) -> dict[str, int]:
    """The outputs that are not finite somewhere in the tyre's usual range (name -> how many points).

    The range: pure side slip to 30 deg (1 deg steps) and pure longitudinal slip to 0.3 (0.01 steps), at
    0.5, 1 and 1.5 x FNOMIN, 0.9, 1 and 1.1 x INFLPRES, zero camber, LONGVL (the range of the figures and
    plots of ``virtsensor tyre``). Finite coefficients can still overflow there (PKY1 = 1e308: Kya = inf),
    and a model that does would make any simulation diverge. ``sweep``: :func:`_usual_range` of ``model`` if
    already computed.
    """
    side, longi, _ = _usual_range(model) if sweep is None else sweep
    counts = {name: int(np.sum(~np.isfinite(getattr(side, key))) + np.sum(~np.isfinite(getattr(longi, key))))
              for key, name in _OUTPUT_NAMES.items()}
    return {name: n for name, n in counts.items() if n}


def beyond_a_tyre(model: MagicFormula61, sweep: tuple[TyreOutput, TyreOutput, FloatArray] | None = None
                  ) -> dict[str, float]:
    """The outputs that are finite but no tyre's somewhere in the usual range of :func:`non_finite_outputs`
    (name -> the worst of them): ``Fx``, ``Fy`` over :data:`FORCE_RATIO_LIMIT` times the load (the worst ratio),
    ``Mz``, ``My`` with a lever ``|M| / Fz`` over the unloaded radius (the worst lever, m: the aligning moment's
    lever, pneumatic trail and residual, lies within the contact patch, itself shorter than the radius; the rolling
    resistance's is a hundredth of it). Such a tyre (PDY1 = 1e30 gives Fy of 1e30 times the load) would drive the
    simulation anywhere but where a car goes. ``sweep``: as for :func:`non_finite_outputs`."""
    side, longi, fz = _usual_range(model) if sweep is None else sweep
    radius = model._p["UNLOADED_RADIUS"]
    out: dict[str, float] = {}
    with np.errstate(all="ignore"):
        for key, name, limit in (("fx", "Fx", FORCE_RATIO_LIMIT), ("fy", "Fy", FORCE_RATIO_LIMIT),
                                 ("mz", "Mz", radius), ("my", "My", radius)):
            ratios = [np.abs(getattr(o, key)) / fz for o in (side, longi)]
            worst = max(float(np.max(np.where(np.isfinite(r), r, 0.0))) for r in ratios)
            if worst > limit:
                out[name] = worst
    return out


def _bad_outputs(model: MagicFormula61) -> int:
    """How many outputs of the usual range are not finite, plus how many kinds are beyond a tyre's."""
    sweep = _usual_range(model)
    return sum(non_finite_outputs(model, sweep).values()) + len(beyond_a_tyre(model, sweep))


def _bad_with(params: Mapping[str, float | str], values: Mapping[str, float | str]) -> int:
    """:func:`_bad_outputs` with ``values`` replacing some coefficients (-1: the coefficients are refused then)."""
    try:
        return _bad_outputs(MagicFormula61({**params, **values}))
    except TirError:
        return -1


def overflowing(model: MagicFormula61, given: Iterable[str] = (),
                restore: Mapping[str, float | str] | None = None) -> list[str]:
    """The coefficients that make the model's outputs non-finite (:func:`non_finite_outputs`) or no tyre's
    (:func:`beyond_a_tyre`).

    A coefficient can be given back a sane value: one of ``restore`` its value there (what a --set replaced),
    any other of ``given`` (the keys of the file) the value of :data:`TYPICAL_TYRE`. Named: those that each
    alone make the outputs finite and a tyre's; else the fewest found greedily (each time the one that leaves
    the fewest outputs bad, at most :data:`_MOST_NAMED`) that together do. Empty when none do.
    """
    params = model.params
    left = _bad_outputs(model)
    typical = MagicFormula61.from_tir(bundled_tir(TYPICAL_TYRE)).params
    sane = dict(restore or {})
    sane.update((key, typical[key]) for key in given if key not in sane and isinstance(params.get(key), float)
                and isinstance(typical.get(key), float) and typical[key] != params[key])
    chosen: dict[str, float | str] = {}
    while left and len(chosen) < _MOST_NAMED:
        trials = {key: _bad_with(params, {**chosen, key: value}) for key, value in sane.items()
                  if key not in chosen}
        trials = {key: n for key, n in trials.items() if 0 <= n < left}
        if not chosen and 0 in trials.values():
            return [key for key, n in trials.items() if n == 0]
        if not trials:
            return []
        best = min(trials, key=trials.__getitem__)
        chosen[best], left = sane[best], trials[best]
    if left:
        return []
    for key in list(chosen):  # one that the later ones made unnecessary
        rest = {k: v for k, v in chosen.items() if k != key}
        if _bad_with(params, rest) == 0:
            chosen = rest
    return [key for key in sane if key in chosen]  # (--set ones first, then in the file's order)


def overflow_message(model: MagicFormula61, what: str, given: Iterable[str] = (),
                     restore: Mapping[str, float | str] | None = None, *, beyond: bool = False) -> str:
    """One line: the model (its source) overflows, ``what`` is not finite (``beyond``: ``what`` is no tyre's),
    and the coefficient(s) that cause it (:func:`overflowing`), or which to check when no coefficient alone or
    few together do."""
    keys = overflowing(model, given, restore)
    where = model.source
    if len(keys) == 1 and isinstance(given, TirFile) and keys[0] in given.lines:
        where = given.where(keys[0])
    head = f"{where}: the Magic Formula " + (f"gives {what}, beyond any tyre" if beyond else
                                             f"overflows ({what} not finite)")
    if keys:
        values = ", ".join(f"{key} = {model.params[key]:g}" for key in keys)
        return f"{head}: {values}; give {'it a value' if len(keys) == 1 else 'them values'} of a tyre's size"
    return f"{head}; check {'the --set coefficients ' + ', '.join(restore) if restore else 'its coefficients'}"


def overflow_problem(model: MagicFormula61, given: Iterable[str] = (),
                     restore: Mapping[str, float | str] | None = None) -> str | None:
    """:func:`overflow_message` when some output is not finite in the tyre's usual range, or is no tyre's
    (:func:`beyond_a_tyre`), else None."""
    where = "at 0.5-1.5 FNOMIN, 0.9-1.1 INFLPRES"
    sweep = _usual_range(model)
    bad = non_finite_outputs(model, sweep)
    if bad:
        return overflow_message(model, f"{', '.join(bad)} {where}", given, restore)
    beyond = beyond_a_tyre(model, sweep)
    if not beyond:
        return None
    radius = model._p["UNLOADED_RADIUS"]
    parts = [f"{name} up to {v:.3g} times the load (over {FORCE_RATIO_LIMIT:g})" if name in ("Fx", "Fy") else
             f"{name} with a lever of {v:.3g} m (over the unloaded radius, {radius:g} m)" for name, v in beyond.items()]
    return overflow_message(model, f"{', '.join(parts)} {where}", given, restore, beyond=True)


class _PressureTerms:
    """Inflation-pressure factors of MF 6.1 for one pressure (float) or per element (array)."""

    __slots__ = ("key", "dpi", "mux", "kxk", "kya", "pky2", "kyg", "muy", "dt", "dr", "my", "cx",
                 "cy", "cz")

    def __init__(self, p: Mapping[str, float], pressure: FloatArray | float) -> None:
        dpi = (pressure - p["NOMPRES"]) / p["NOMPRES"]  # (4.E2b)
        self.key = pressure if isinstance(pressure, float) else None
        self.dpi = dpi
        self.mux = 1.0 + p["PPX3"] * dpi + p["PPX4"] * dpi * dpi  # (4.E13)
        self.kxk = 1.0 + p["PPX1"] * dpi + p["PPX2"] * dpi * dpi  # (4.E15)
        self.kya = 1.0 + p["PPY1"] * dpi  # (4.E25)
        self.pky2 = 1.0 + p["PPY2"] * dpi  # (4.E25)
        self.kyg = 1.0 + p["PPY5"] * dpi  # (4.E30)
        self.muy = 1.0 + p["PPY3"] * dpi + p["PPY4"] * dpi * dpi  # (4.E23)
        self.dt = 1.0 - p["PPZ1"] * dpi  # (A60): PPZ1 > 0 -> higher pressure, shorter trail
        self.dr = 1.0 + p["PPZ2"] * dpi  # (4.E47)
        self.my = np.power(pressure / p["NOMPRES"], p["QSY8"]) if isinstance(pressure, np.ndarray) \
            else _pow(pressure / p["NOMPRES"], p["QSY8"])  # (A48)
        self.cx = 1.0 + p["PCFX3"] * dpi  # Besselink 2010 eq. 17
        self.cy = 1.0 + p["PCFY3"] * dpi  # eq. 18
        self.cz = 1.0 + p["PFZ1"] * dpi  # eq. 5


def _as_float(x: ArrayLike) -> FloatArray | float:
    """Python float for scalars (cheap arithmetic), float64 array otherwise."""
    if isinstance(x, float):
        return x
    if isinstance(x, int | np.floating | np.integer):
        return float(x)
    arr = np.asarray(x, dtype=np.float64)
    return float(arr) if arr.ndim == 0 else arr


def _pow(x: float, y: float) -> float:
    """x ** y of two floats, inf when it overflows (as numpy's power, under the caller's np.errstate): Python's
    float power raises OverflowError instead, which would escape as a crash rather than a non-finite output."""
    return float(np.power(np.float64(x), y))


def _f64(x: ArrayLike) -> FloatArray:
    return x if isinstance(x, np.ndarray) and x.dtype == np.float64 else np.asarray(x, dtype=np.float64)


def _flat(x: FloatArray, shape: tuple[int, ...]) -> FloatArray:
    """1-D float64 copy-free view of ``x`` broadcast to ``shape`` when possible."""
    if x.shape != shape:
        x = np.broadcast_to(x, shape)
    return x.reshape(-1)


def _clip(x: FloatArray, lo: float, hi: float) -> FloatArray:
    if lo > -math.inf:
        x = np.maximum(x, lo)
    if hi < math.inf:
        x = np.minimum(x, hi)
    return x
