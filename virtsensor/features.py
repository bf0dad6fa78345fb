"""Feature vectors of the estimator, built the same way offline and on the bus.

A :class:`FeatureSpec` is an ordered list of :class:`Feature` definitions over
the catalogue's input signals, sampled at the canonical 20 Hz ticks:

* ``value``: the latest value at the tick (the paper's 12 inputs are 12 of these);
* ``rate``:  first difference over one tick divided by the tick period (unit/s),
  e.g. the steering-wheel rate of the paper's eq. (1);
* ``accel``: second difference over two ticks divided by the period squared
  (unit/s^2), e.g. the steering-wheel acceleration of eq. (1);
* ``lag``:   the value ``lag`` ticks earlier.

:meth:`FeatureSpec.transform` builds the vectors of a whole table (training,
evaluation); :class:`FeatureBuilder` builds one vector per tick from a ring
buffer (the runtime daemon): the two give identical numbers (tested), so the
model is trained on what it will see. The spec travels in the model card as
JSON, so the runtime knows its inputs from the card, not from code.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np

from virtsensor import signals as cat

Op = Literal["value", "rate", "accel", "lag"]
TICK_S = cat.TABLE_TICK_S


@dataclass(frozen=True)
class Feature:
    """One feature: an operation on one catalogue signal.

    Attributes:
        signal: catalogue input name.
        op: ``value``, ``rate``, ``accel`` or ``lag`` (see module docstring).
        lag: ticks back, for ``lag``.
    """

    signal: str
    op: Op = "value"
    lag: int = 0

    @property
    def name(self) -> str:
        if self.op == "value":
            return self.signal
        if self.op == "lag":
            return f"{self.signal}@lag{self.lag}"
        return f"{self.signal}@{self.op}"

    @property
    def unit(self) -> str:
        base = cat.SIGNALS[self.signal].unit
        return {"value": base, "lag": base, "rate": f"{base}/s", "accel": f"{base}/s^2"}[self.op]

    @property
    def history(self) -> int:
        """Ticks of history this feature needs beyond the present one."""
        return {"value": 0, "rate": 1, "accel": 2, "lag": self.lag}[self.op]


@dataclass(frozen=True)
class FeatureSpec:
    """An ordered feature list with a name (``paper``, ``history``...)."""

    name: str
    features: tuple[Feature, ...]

    def __post_init__(self) -> None:
        for f in self.features:
            if f.signal not in cat.SIGNALS or cat.SIGNALS[f.signal].role not in ("input", "aux"):
                raise ValueError(f"feature {f.name}: {f.signal!r} is not a catalogue input signal")
            if f.op not in ("value", "rate", "accel", "lag") or f.lag < 0 or (f.op == "lag") != (f.lag > 0):
                raise ValueError(f"feature {f.name}: bad operation {f.op!r} / lag {f.lag}")
        names = [f.name for f in self.features]
        if len(set(names)) != len(names):
            raise ValueError(f"feature spec {self.name!r} repeats a feature")

    # ---- description ----------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.features)

    @property
    def signals(self) -> tuple[str, ...]:
        """The catalogue signals the features read, in first-use order."""
        return tuple(dict.fromkeys(f.signal for f in self.features))

    @property
    def history(self) -> int:
        """Ticks of history needed before the first complete vector."""
        return max((f.history for f in self.features), default=0)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "tick_s": TICK_S, "features": [asdict(f) for f in self.features]}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> FeatureSpec:
        if abs(float(data.get("tick_s", TICK_S)) - TICK_S) > 1e-12:
            raise ValueError(f"feature spec made for a tick of {data['tick_s']} s, this build uses {TICK_S} s")
        return cls(str(data["name"]), tuple(Feature(**f) for f in data["features"]))

    # ---- offline: a whole table -----------------------------------------------------------
    def transform(self, table: Mapping[str, np.ndarray]) -> np.ndarray:
        """Feature matrix (n, d) of one run's 20 Hz table (rows in time order).

        The first :attr:`history` rows lack history and are NaN, as are rows whose
        inputs are not finite: callers drop non-finite rows and count them.
        """
        missing = [s for s in self.signals if s not in table]
        if missing:
            raise KeyError(", ".join(missing))
        n = len(np.asarray(table[self.signals[0]])) if self.signals else 0
        out = np.full((n, len(self.features)), np.nan)
        for j, f in enumerate(self.features):
            x = np.asarray(table[f.signal], dtype=np.float64)
            h = f.history
            if h >= n:
                continue
            if f.op == "value":
                out[:, j] = x
            elif f.op == "lag":
                out[h:, j] = x[:-h]
            elif f.op == "rate":
                out[1:, j] = (x[1:] - x[:-1]) / TICK_S
            else:  # accel
                out[2:, j] = (x[2:] - 2.0 * x[1:-1] + x[:-2]) / (TICK_S * TICK_S)
        return out


class FeatureBuilder:
    """The online path of a :class:`FeatureSpec`: one vector per tick, no array allocation.

    ``push(values)`` takes the latest values of :attr:`FeatureSpec.signals` (in that order; a list of
    floats or a 1-D array; items after them, such as the daemon's check references, are kept in the history
    rows and never read) at a tick and returns the feature vector as a list of Python floats (the
    daemon's tick then calls numpy only to hand it to the model), or None until enough history exists.

    The history is ``depth`` Python lists, newest first, rotated per push; the vector is built by a
    function generated once from the spec (one list display), with the arithmetic of
    :meth:`FeatureSpec.transform` in the same order, so the two agree to the bit.
    """

    def __init__(self, spec: FeatureSpec):
        self.spec = spec
        self.depth = spec.history + 1
        n = len(spec.signals)
        self._rows: list[list[float]] = [[math.nan] * n for _ in range(self.depth)]
        self._count = 0
        self._build = _compile_builder(spec, self.depth)

    def reset(self) -> None:
        """Forget the history (after a gap in the inputs)."""
        for row in self._rows:
            row[:] = [math.nan] * len(row)
        self._count = 0

    @property
    def ready(self) -> bool:
        return self._count >= self.depth

    def push(self, values: Sequence[float] | np.ndarray) -> list[float] | None:
        rows = self._rows
        row = rows.pop()  # the oldest row becomes the newest
        row[:] = values
        rows.insert(0, row)
        self._count += 1
        if self._count < self.depth:
            return None
        return self._build(rows)  # type: ignore[no-any-return]


def _compile_builder(spec: FeatureSpec, depth: int) -> Any:
    """``build(rows) -> list`` of the feature values, ``rows[k]`` the signal values ``k`` ticks back."""
    col = {s: i for i, s in enumerate(spec.signals)}
    terms = []
    for f in spec.features:
        c = col[f.signal]
        if f.op == "value":
            terms.append(f"r0[{c}]")
        elif f.op == "lag":
            terms.append(f"rows[{f.lag}][{c}]")
        elif f.op == "rate":
            terms.append(f"(r0[{c}] - r1[{c}]) / TICK_S")
        else:
            terms.append(f"(r0[{c}] - 2.0 * r1[{c}] + r2[{c}]) / TICK_S2")
    heads = "".join(f"    r{k} = rows[{k}]\n" for k in range(min(depth, 3)))
    src = f"def build(rows):\n{heads}    return [{', '.join(terms)}]\n"
    env: dict[str, Any] = {"TICK_S": TICK_S, "TICK_S2": TICK_S * TICK_S}
    exec(compile(src, f"<features {spec.name}>", "exec"), env)  # noqa: S102 - generated from the spec only
    return env["build"]


def _values(names: Sequence[str]) -> tuple[Feature, ...]:
    return tuple(Feature(n) for n in names)


#: The paper's estimator: the 12 inputs of Table II as they are at the tick.
PAPER = FeatureSpec("paper", _values(cat.INPUTS))

#: Beyond the paper: eq. (1) has the steering rate and acceleration, which a static
#: MLP cannot see; the torques' and the body motion's rates give the dynamic state.
HISTORY = FeatureSpec(
    "history",
    _values(cat.INPUTS)
    + (
        Feature("steer_angle_rad", "rate"),
        Feature("steer_angle_rad", "accel"),
        Feature("steer_torque_nm", "rate"),
        Feature("assist_torque_nm", "rate"),
        Feature("ay_mps2", "rate"),
        Feature("yaw_rate_radps", "rate"),
        Feature("susp_defl_fl_m", "rate"),
        Feature("susp_defl_fr_m", "rate"),
        Feature("steer_angle_rad", "lag", 2),
        Feature("assist_torque_nm", "lag", 2),
    ),
)

#: The TPMS estimator: the history features, then the two front tyres' pressures (Pa, gauge) last, so that the
#: first features are exactly those of HISTORY and a pressure-free model on them is its fallback when the
#: pressures are unknown (no TPMS frame, a sensor missing).
TPMS = FeatureSpec("history+tpms", HISTORY.features + _values(cat.TPMS_FRONT))

SPECS: dict[str, FeatureSpec] = {s.name: s for s in (PAPER, HISTORY, TPMS)}
