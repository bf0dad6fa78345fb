"""What makes two recordings the same run, whatever their file: the digest of the 20 Hz table the CAN bus carries.

A run copied, renamed, or written once as a table (``.csv``) and once as a CAN log (``.blf``, ``.asc``...) has
other bytes but the same signals: its files' sha256 differ, its :func:`table_digest` does not. A set of runs that
holds one run twice would weigh it twice in training, and a run on both sides of a split (training and held out)
would score the model on what it learned; :func:`refuse_repeats` refuses both.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError

__all__ = ["table_digest", "refuse_repeats"]

#: what a non-finite value counts as in the digest (SNA, a gap): apart from every finite one and from each other
_NAN, _POS_INF, _NEG_INF = 2.0**60, 2.0**61, -(2.0**61)


def table_digest(table: Mapping[str, Any]) -> str:
    """sha256 of a run's table as its CAN frames carry it: ``time_s`` from its first row (to the microsecond), then
    every catalogue signal with a DBC mapping the table holds (sorted by name), each in steps of its CAN resolution
    (NaN and infinities as three values no finite one takes). Columns the bus does not carry (the simulator's truth:
    forces, slip angles, road friction) do not count, so a table and a CAN log of one run agree; so do the same
    values written with more decimals. ``time_s`` must hold at least one row."""
    h = hashlib.sha256()
    t = np.asarray(table["time_s"], dtype=float)
    h.update(np.round((t - t[0]) * 1e6).tobytes())
    for name in sorted(k for k in table if k in cat.SIGNALS and cat.SIGNALS[k].message):
        x = np.asarray(table[name], dtype=float)
        steps = np.round(x / (cat.SIGNALS[name].resolution or 1e-9))
        steps[np.isnan(x)], steps[np.isposinf(x)], steps[np.isneginf(x)] = _NAN, _POS_INF, _NEG_INF
        h.update(name.encode())
        h.update(np.ascontiguousarray(steps, dtype=np.float64).tobytes())
    return h.hexdigest()


def refuse_repeats(runs: Iterable[tuple[str | Path, str]], what: str = "a run must count once") -> None:
    """Refuse a run given twice: ``runs`` are ``(file, table digest)``; the second file whose digest an earlier one
    has is refused.

    Raises:
        UserError: ``<file>: the same run as <earlier file> (the same signals, tick for tick); <what>``.
    """
    seen: dict[str, str | Path] = {}
    for path, digest in runs:
        if digest in seen:
            raise UserError(f"{path}: the same run as {seen[digest]} (the same signals, tick for tick); {what}")
        seen[digest] = path
