"""The validity envelope of a model: the region of input space its training rows covered.

A model estimates well where it was trained and extrapolates elsewhere; the envelope says where that is,
in the card's ``envelope`` key, so the daemon (:mod:`virtsensor.daemon.validity`), ``score`` and ``explain``
can flag the rows outside it. It is fitted by the trainer from the training rows (:meth:`Envelope.fit`)
and has two parts, both cheap enough to check at every 20 Hz tick:

* **Per-signal ranges.** For every input signal the model reads as a plain value: ``[q_lo - m, q_hi + m]``,
  with ``q_lo``/``q_hi`` the :data:`QUANTILES` (0.1 and 99.9 %) of the training rows and ``m`` the
  :data:`MARGIN` share of ``q_hi - q_lo``. Percentiles, not min/max, so a few outlying training rows do not
  widen the envelope; rates and lags are not bounded (they follow from the values over time, and their
  noise would make the flag flicker).
* **Grip used per speed band.** The road friction is not an input, so "lateral acceleration over friction"
  cannot be computed on the bus; what can be bounded is how much grip the training rows used at each speed.
  The speed ``vx`` is cut into bands of :data:`BAND_WIDTH_MPS`; per band the card stores the ceiling of
  ``|ay|`` and of the horizontal acceleration ``hypot(ax, ay)`` (the friction circle's radius), each the
  :data:`QUANTILES` upper quantile of the band's rows times ``1 + MARGIN``. A band with fewer than
  :data:`MIN_BAND_ROWS` rows has no ceiling: every row in it is outside. This is a 1-D table lookup
  per tick (no hull, no search) and reads as "at 25-30 m/s the model saw at most 7.9 m/s^2 lateral".
  It needs the model to read ``vx_mps``, ``ay_mps2`` (and ``ax_mps2`` for the horizontal ceiling) as values;
  without them that part is left out.

A row is *outside* when any bounded signal lies outside its range, its speed lies in a band without
ceilings, or its ``|ay|`` or ``hypot(ax, ay)`` exceeds its band's ceiling. Cards without an ``envelope``
have no envelope check. This module needs numpy only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from virtsensor.errors import UserError

__all__ = ["BAND_WIDTH_MPS", "MARGIN", "MIN_BAND_ROWS", "QUANTILES", "Envelope"]

#: Percentiles (%) of the training rows that bound each signal (and the upper one, each band's ceilings).
QUANTILES = (0.1, 99.9)
#: Margin added on each side, as a share of a signal's quantile span (and of a band's ceiling).
MARGIN = 0.05
#: Width of the speed bands (m/s) of the grip ceilings.
BAND_WIDTH_MPS = 5.0
#: Fewest training rows a speed band needs to have ceilings.
MIN_BAND_ROWS = 20
#: Signals of the derived quantities: speed, lateral and longitudinal acceleration.
VX, AY, AX = "vx_mps", "ay_mps2", "ax_mps2"


@dataclass(frozen=True)
class Envelope:
    """A fitted envelope (see the module docstring). Immutable; arrays are float64.

    Attributes:
        signals: the bounded input signals (catalogue names). lo, hi: their ranges, same order (units of
            the catalogue).
        band_start: lower edge of the first speed band (m/s; nan: no speed bands). band_width: their width.
        ay_max, acc_max: per band, the ceiling of ``|ay|`` and of ``hypot(ax, ay)`` (m/s^2; nan: no rows
            enough in the band, so outside; ``acc_max`` all nan when the model does not read ``ax``).
    """

    signals: tuple[str, ...]
    lo: np.ndarray
    hi: np.ndarray
    band_start: float = math.nan
    band_width: float = BAND_WIDTH_MPS
    ay_max: np.ndarray = field(default_factory=lambda: np.zeros(0))
    acc_max: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def has_bands(self) -> bool:
        """Whether the envelope bounds the grip used per speed band."""
        return len(self.ay_max) > 0

    # -- fitting ----------------------------------------------------------------------------------------------
    @classmethod
    def fit(cls, X: np.ndarray, feature_names: Sequence[str]) -> Envelope:
        """The envelope of the training rows ``X`` (n, d), columns named ``feature_names`` (finite rows).

        Raises:
            ValueError: no rows, or ``X`` not (n, len(feature_names)).
        """
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[1] != len(feature_names) or len(X) == 0:
            raise ValueError(f"envelope: X {X.shape} must be (n >= 1, {len(feature_names)})")
        from virtsensor import signals as cat

        col = {n: X[:, i] for i, n in enumerate(feature_names) if n in cat.INPUTS}  # value features only
        names = tuple(col)
        q = np.array([np.percentile(col[n], QUANTILES) for n in names]).reshape(len(names), 2)
        span = q[:, 1] - q[:, 0]
        lo, hi = q[:, 0] - MARGIN * span, q[:, 1] + MARGIN * span
        if VX not in col or AY not in col:
            return cls(names, lo, hi)
        vx, ay = col[VX], np.abs(col[AY])
        acc = np.hypot(col[AX], col[AY]) if AX in col else None
        start = math.floor(float(vx.min()) / BAND_WIDTH_MPS) * BAND_WIDTH_MPS
        band = np.floor((vx - start) / BAND_WIDTH_MPS).astype(np.int64)
        n_bands = int(band.max()) + 1
        ay_max, acc_max = np.full(n_bands, np.nan), np.full(n_bands, np.nan)
        for k in range(n_bands):
            rows = band == k
            if rows.sum() >= MIN_BAND_ROWS:
                ay_max[k] = np.percentile(ay[rows], QUANTILES[1]) * (1.0 + MARGIN)
                if acc is not None:
                    acc_max[k] = np.percentile(acc[rows], QUANTILES[1]) * (1.0 + MARGIN)
        return cls(names, lo, hi, float(start), BAND_WIDTH_MPS, ay_max, acc_max)

    # -- checking ---------------------------------------------------------------------------------------------
    def outside_rows(self, X: np.ndarray, feature_names: Sequence[str]) -> np.ndarray:
        """Per row of ``X`` (columns ``feature_names``), whether it is outside the envelope (bool (n,)).

        Raises:
            ValueError: a bounded signal is not among ``feature_names``.
        """
        X = np.asarray(X, dtype=np.float64)
        idx = {n: i for i, n in enumerate(feature_names)}
        missing = [s for s in self.signals if s not in idx]
        if missing:
            raise ValueError(f"envelope bounds {', '.join(missing)}, which the rows lack")
        cols = X[:, [idx[s] for s in self.signals]]
        out: np.ndarray = np.asarray(((cols < self.lo) | (cols > self.hi)).any(axis=1), dtype=bool)
        if self.has_bands:
            vx, ay = X[:, idx[VX]], np.abs(X[:, idx[AY]])
            k = np.floor((vx - self.band_start) / self.band_width)
            ok_band = (k >= 0) & (k < len(self.ay_max))
            kk = np.where(ok_band, k, 0).astype(np.int64)
            ay_cap = np.where(ok_band, self.ay_max[kk], np.nan)
            out |= ~(ay <= ay_cap)  # nan ceiling: outside
            if AX in idx and not np.isnan(self.acc_max).all():
                acc_cap = np.where(ok_band, self.acc_max[kk], np.nan)
                out |= ~(np.hypot(X[:, idx[AX]], X[:, idx[AY]]) <= acc_cap)
        return out

    def reasons(self, values: Mapping[str, float]) -> list[str]:
        """What is outside for one row of signal values (for logs): ``"ay_mps2=9.1 > 8.3 at vx 25-30"``..."""
        out = []
        for s, lo, hi in zip(self.signals, self.lo, self.hi, strict=True):
            v = float(values.get(s, math.nan))
            if not lo <= v <= hi:
                out.append(f"{s}={v:.4g} not in [{lo:.4g}, {hi:.4g}]")
        if self.has_bands and VX in values and AY in values:
            vx, ay = float(values[VX]), float(values[AY])
            k = math.floor((vx - self.band_start) / self.band_width) if math.isfinite(vx) else -1
            lo_v = self.band_start + k * self.band_width
            where = f"vx {lo_v:g}-{lo_v + self.band_width:g} m/s"
            if not 0 <= k < len(self.ay_max) or math.isnan(self.ay_max[k]):
                out.append(f"no training rows at {where}")
            else:
                if not abs(ay) <= self.ay_max[k]:
                    out.append(f"|ay|={abs(ay):.3g} > {self.ay_max[k]:.3g} m/s^2 at {where}")
                acc = math.hypot(float(values.get(AX, 0.0)), ay)
                if AX in values and not acc <= self.acc_max[k]:
                    out.append(f"hypot(ax, ay)={acc:.3g} > {self.acc_max[k]:.3g} m/s^2 at {where}")
        return out

    # -- the card's JSON --------------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        """The card's ``envelope`` value (nan ceilings as null)."""
        doc: dict[str, Any] = {
            "method": "per-signal quantile ranges; |ay| and hypot(ax, ay) ceilings per speed band",
            "quantiles_pct": list(QUANTILES), "margin": MARGIN,
            "signals": {s: [float(a), float(b)] for s, a, b in zip(self.signals, self.lo, self.hi, strict=True)},
        }
        if self.has_bands:
            doc["speed_bands"] = {"signal": VX, "start_mps": self.band_start, "width_mps": self.band_width,
                                  "min_rows": MIN_BAND_ROWS, "ay_abs_max_mps2": _nulls(self.ay_max),
                                  "accel_max_mps2": _nulls(self.acc_max)}
        return doc

    @classmethod
    def from_json(cls, doc: Any, where: str = "model card") -> Envelope:
        """Parse a card's ``envelope`` value.

        Raises:
            UserError: not the structure :meth:`to_json` writes (message names ``where``).
        """
        from virtsensor import signals as cat

        def bad(what: str) -> UserError:
            return UserError(f"{where}: envelope: {what}")

        if not isinstance(doc, Mapping) or not isinstance(doc.get("signals"), Mapping):
            raise bad("must be an object with 'signals'")
        names, lo, hi = [], [], []
        for s, r in doc["signals"].items():
            if s not in cat.INPUTS or not (isinstance(r, list) and len(r) == 2 and all(_num(x) for x in r)
                                           and r[0] <= r[1]):
                raise bad(f"signal {s!r} must be a catalogue input with a range [lo, hi], lo <= hi")
            names.append(s)
            lo.append(float(r[0]))
            hi.append(float(r[1]))
        env = cls(tuple(names), np.array(lo, dtype=np.float64), np.array(hi, dtype=np.float64))
        bands = doc.get("speed_bands")
        if bands is None:
            return env
        if not isinstance(bands, Mapping) or bands.get("signal") != VX:
            raise bad("speed_bands must be an object over vx_mps")
        start: Any = bands.get("start_mps")
        width: Any = bands.get("width_mps")
        ay, acc = bands.get("ay_abs_max_mps2"), bands.get("accel_max_mps2")
        if not (_num(start) and _num(width) and width > 0 and isinstance(ay, list) and isinstance(acc, list)
                and len(ay) == len(acc) > 0 and all(x is None or (_num(x) and x >= 0) for x in ay + acc)):
            raise bad("speed_bands needs start_mps, width_mps > 0 and equally long lists of ceilings >= 0 or null")
        if VX not in names or AY not in names:
            raise bad("speed_bands need vx_mps and ay_mps2 among the bounded signals")
        return cls(env.signals, env.lo, env.hi, float(start), float(width), _floats(ay), _floats(acc))


def _num(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _nulls(a: np.ndarray) -> list[float | None]:
    return [None if math.isnan(v) else float(v) for v in a]


def _floats(a: list[Any]) -> np.ndarray:
    return np.array([math.nan if v is None else float(v) for v in a], dtype=np.float64)
