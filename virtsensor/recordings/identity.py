"""What makes two recordings the same run, whatever their file: the digest of the 20 Hz table the CAN bus carries.

A run copied, renamed, or written once as a table (``.csv``) and once as a CAN log (``.blf``, ``.asc``...) has
other bytes but the same signals: its files' sha256 differ, its :func:`table_digest` does not. A set of runs that
holds one run twice would weigh it twice in training, and a run on both sides of a split (training and held out)
would score the model on what it learned; :func:`refuse_repeats` refuses both.

The digest is exact: one value written with fewer decimals (a table re-saved by another tool) changes it.
:func:`same_run` compares two tables with that tolerance, and :func:`find_repeat` finds such a pair among many.

Nor does either see a run cut otherwise: an export that starts one row later, or a stretch of a run saved as a
run of its own, has other rows and another digest, yet the same rows tick for tick. :func:`find_overlap` finds two
tables that share a stretch of :data:`OVERLAP_ROWS` rows or more (or half the shorter table), row for row in the
same order, on the bus signals both carry in steps of their CAN resolution.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError

__all__ = ["OVERLAP_ROWS", "TIME_TOL_S", "table_digest", "same_run", "find_overlap", "find_repeat",
           "refuse_repeats"]

#: what a non-finite value counts as in the digest (SNA, a gap): apart from every finite one and from each other
_NAN, _POS_INF, _NEG_INF = 2.0**60, 2.0**61, -(2.0**61)
#: two tables of one run have their rows' times (s, from their first row) this close
TIME_TOL_S = 1e-3
#: relative slack on a tolerance (floating-point rounding of the values compared)
_SLACK = 1e-6
#: rows two tables share, one after the other at one offset, that make them one run cut otherwise (10 s at 20 Hz;
#: or half the shorter table, if less); rows that repeat within a table (a car at rest) never count
OVERLAP_ROWS = 200


def table_digest(table: Mapping[str, Any]) -> str:
    """sha256 of a run's table as its CAN frames carry it: ``time_s`` from its first row (to the microsecond), then
    every catalogue signal with a DBC mapping the table holds (sorted by name), each in steps of its CAN resolution
    (NaN and infinities as three values no finite one takes). Columns the bus does not carry (the simulator's truth:
    forces, slip angles, road friction) do not count, so a table and a CAN log of one run agree; so do the same
    values written with more decimals. ``time_s`` must hold at least one row."""
    with np.errstate(over="ignore", invalid="ignore"):  # (a huge value is the input check's to name, in one line)
        return _digest(table)


def _digest(table: Mapping[str, Any]) -> str:
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


def _bus_signals(table: Mapping[str, Any]) -> set[str]:
    return {k for k in table if k in cat.SIGNALS and cat.SIGNALS[k].message}


def _decimal_step(x: np.ndarray) -> float:
    """The decimal step a column's finite values are whole multiples of: ``10**-d`` for the least ``d`` (0..9); 0 when
    there is none (full precision); inf without a finite value."""
    f = x[np.isfinite(x)]
    if not len(f):
        return np.inf
    for d in range(10):
        s = f * 10.0**d
        if np.all(np.abs(s - np.round(s)) <= _SLACK * np.maximum(1.0, np.abs(s))):
            return 10.0**-d
    return 0.0


def _written_step(table: Mapping[str, Any], names: Iterable[str]) -> float:
    """The decimal step a table was written in: the finest of its columns' ``names`` (a column that happens to hold
    whole numbers, or a constant, tells nothing by itself); 0 at full precision."""
    steps = [_decimal_step(np.asarray(table[n], dtype=float)) for n in names]
    finest = min(steps, default=np.inf)
    return 0.0 if not np.isfinite(finest) else finest


def same_run(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    """Whether two tables hold one run, written twice with other decimals or through other tools: as many rows, the
    rows' times (from the first row) within :data:`TIME_TOL_S`, and at least one catalogue signal with a DBC mapping
    in both, each such signal non-finite at the same rows and elsewhere apart by at most the larger of its CAN
    resolution and half the sum of the decimal steps the two tables were written in (a value rounded to ``d``
    decimals moves by at most half of ``10**-d``; a table's step is the finest of its bus signals'). Columns the bus
    does not carry do not count."""
    return _same(a, b, {})


def _same(a: Mapping[str, Any], b: Mapping[str, Any], steps: dict[int, float]) -> bool:
    """:func:`same_run`, with the tables' written steps kept in ``steps`` (by ``id``) for the next pair."""
    ta, tb = np.asarray(a["time_s"], dtype=float), np.asarray(b["time_s"], dtype=float)
    if len(ta) != len(tb) or not len(ta) or np.max(np.abs((ta - ta[0]) - (tb - tb[0]))) > TIME_TOL_S:
        return False
    names = sorted(_bus_signals(a) & _bus_signals(b))
    worst_over = 0.0  # the largest gap beyond a signal's resolution
    for name in names:
        xa, xb = np.asarray(a[name], dtype=float), np.asarray(b[name], dtype=float)
        fa = np.isfinite(xa)
        if not np.array_equal(fa, np.isfinite(xb)):
            return False
        worst = float(np.max(np.abs(xa[fa] - xb[fa]))) if fa.any() else 0.0
        if worst > (cat.SIGNALS[name].resolution or 0.0) * (1 + _SLACK):
            if worst > 1.0 + _SLACK:  # (beyond any rounding: a written step is at most 1)
                return False
            worst_over = max(worst_over, worst)
    if worst_over > 0.0:
        for t in (a, b):
            if id(t) not in steps:
                steps[id(t)] = _written_step(t, _bus_signals(t))
        if worst_over > 0.5 * (steps[id(a)] + steps[id(b)]) * (1 + _SLACK):
            return False
    return bool(names)


def find_repeat(tables: Sequence[Mapping[str, Any]], groups: Sequence[int] | None = None) -> tuple[int, int] | None:
    """The first pair ``(i, j)``, ``i < j``, of ``tables`` that are one run (:func:`same_run`), or None; with
    ``groups`` (one label per table), only pairs from different groups count. Tables are compared only with those of
    as many rows whose mean ``vx_mps`` is within 1 m/s (the most two copies of one run can differ by), so a large
    campaign costs about a sort."""
    steps: dict[int, float] = {}
    by_rows: dict[int, list[int]] = {}
    for i, t in enumerate(tables):
        by_rows.setdefault(len(t["time_s"]), []).append(i)
    for idx in by_rows.values():
        keyed = sorted((_mean_speed(tables[i]), i) for i in idx)
        for k, (vi, i) in enumerate(keyed):
            for vj, j in keyed[k + 1:]:
                if vj - vi > 1.0:  # (-inf, no speed: compared with each other only; -inf - -inf is nan)
                    break
                if (groups is None or groups[i] != groups[j]) and _same(tables[i], tables[j], steps):
                    return (min(i, j), max(i, j))
    return None


def find_overlap(tables: Sequence[Mapping[str, Any]], groups: Sequence[int] | None = None
                 ) -> tuple[int, int, int] | None:
    """The first pair of ``tables`` that share a stretch of rows (module docstring), as ``(i, j, rows)``: ``i < j``
    and how many rows they share; or None. With
    ``groups``, only pairs from different groups count. A row's key is its bus signals (those every table holds) in
    steps of their CAN resolution; rows whose key repeats within their table are left out; two tables overlap where
    :data:`OVERLAP_ROWS` of their rows (or half the shorter one's, at least 20) share keys at one offset between
    them. Cost: one hash per row and a sort of all rows."""
    names = sorted(set.intersection(*(_bus_signals(t) for t in tables))) if tables else []
    if not names:
        return None
    coeff = np.random.default_rng(20261128).integers(1, 2**63, size=len(names), dtype=np.int64).astype(np.uint64)
    keys, owner, rows = [], [], []
    for k, t in enumerate(tables):
        h = np.zeros(len(t["time_s"]), dtype=np.uint64)
        for c, name in zip(coeff, names, strict=True):
            x = np.asarray(t[name], dtype=float)
            steps = np.round(x / (cat.SIGNALS[name].resolution or 1e-9))
            steps[~np.isfinite(x)] = _NAN
            with np.errstate(over="ignore"):
                h = h * np.uint64(1099511628211) + steps.astype(np.int64).view(np.uint64) * c
        u, first, count = np.unique(h, return_index=True, return_counts=True)
        keys.append(u[count == 1])
        rows.append(first[count == 1])
        owner.append(np.full(int((count == 1).sum()), k))
    key, who, row = np.concatenate(keys), np.concatenate(owner), np.concatenate(rows)
    order = np.argsort(key, kind="stable")
    key, who, row = key[order], who[order], row[order]
    pair = np.flatnonzero((key[1:] == key[:-1]) & (who[1:] != who[:-1]))
    if groups is not None:
        g = np.asarray(groups)
        pair = pair[g[who[pair]] != g[who[pair + 1]]]
    if not len(pair):
        return None
    a, b = who[pair], who[pair + 1]
    i, j = np.minimum(a, b), np.maximum(a, b)
    ri, rj = np.where(a < b, row[pair], row[pair + 1]), np.where(a < b, row[pair + 1], row[pair])
    combos, count = np.unique(np.stack([i, j, rj - ri]), axis=1, return_counts=True)
    found = []
    for (ti, tj, _), n in zip(combos.T, count, strict=True):
        shorter = min(len(tables[ti]["time_s"]), len(tables[tj]["time_s"]))
        if n >= max(20, min(OVERLAP_ROWS, shorter // 2)):
            found.append((int(ti), int(tj), int(n)))
    return min(found) if found else None


def _mean_speed(table: Mapping[str, Any]) -> float:
    v = np.asarray(table.get("vx_mps", ()), dtype=float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if len(v) else -np.inf


def refuse_repeats(runs: Iterable[tuple[str | Path, str, Mapping[str, Any]]], what: str = "a run must count once"
                   ) -> None:
    """Refuse a run given twice: ``runs`` are ``(file, table digest, table)``. A file whose digest an earlier one
    has is refused, then a file whose table is an earlier one's written with other decimals (:func:`find_repeat`),
    then one that shares a stretch of rows with an earlier one (:func:`find_overlap`: one run cut otherwise).

    Raises:
        UserError: ``<file>: the same run as <earlier file> (the same signals, tick for tick[, written with other
            decimals]); <what>``, or ``<file>: <n> of its rows are <earlier file>'s, tick for tick ...``.
    """
    items = list(runs)
    seen: dict[str, str | Path] = {}
    for path, digest, _ in items:
        if digest in seen:
            raise UserError(f"{path}: the same run as {seen[digest]} (the same signals, tick for tick); {what}")
        seen[digest] = path
    pair = find_repeat([table for _, _, table in items])
    if pair is not None:
        i, j = pair
        raise UserError(f"{items[j][0]}: the same run as {items[i][0]} (the same signals, tick for tick, written with "
                        f"other decimals); {what}")
    cut = find_overlap([table for _, _, table in items])
    if cut is not None:
        i, j, n = cut
        raise UserError(f"{items[j][0]}: {n} of its rows are {items[i][0]}'s, tick for tick (one run, cut otherwise); "
                        f"{what}")
