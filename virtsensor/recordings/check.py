"""The one input check of a recording's 20 Hz table, shared by every command that reads data.

:func:`check_table` refuses, with a :class:`~virtsensor.errors.UserError` in one
format, ``<file>: column <name>, row <k>: expected <what>, got <what>``:

* ``time_s`` missing, not finite, or not strictly increasing;
* a time that is not one run's, the rule of CAN logs and MDF files
  (:func:`virtsensor.frontend.time_problem`): a step between rows of more than
  :data:`~virtsensor.frontend.MAX_GAP_S` (where gaps are allowed: a reader that
  fills them with rows would otherwise build billions of rows for a clock that
  jumped), or more than :data:`~virtsensor.frontend.MAX_SPAN_S` from the first
  row to the last;
* a rate other than the canonical 20 Hz: every step between rows must be one
  tick (:data:`~virtsensor.signals.TABLE_TICK_S`) within :data:`STEP_TOLERANCE` of a tick, or, where gaps are
  allowed (a caller that cuts tables into segments at missing rows), a whole number of ticks;
* a signal a car carries (catalogue roles input, output, aux) outside its
  catalogue range; NaN is SNA (signal not available) and passes; +-inf never
  does. The simulator's truth columns describe its state, not a sensor's
  reading, and are not range-checked (a spinning wheel's slip ratio exceeds 1),
  but must be finite or SNA too;
* a target (reference SAT to train or score on) that is not finite, where the
  caller names targets.

Rows are numbered from 1, the first data row; in a CSV table row ``k`` is
line ``k + 1`` (the header is line 1) and the message says so.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.frontend import MAX_GAP_S, MAX_SPAN_S

RATE_HZ = cat.TABLE_RATE_HZ
TICK_S = cat.TABLE_TICK_S
#: largest departure of a step between rows from a whole number of ticks, as a fraction of a tick
STEP_TOLERANCE = 0.05
#: Fewest rows a table must have (a rate needs two ticks): every reader refuses fewer.
MIN_ROWS = 2
#: catalogue roles whose values must lie in their catalogue range (or be SNA)
_RANGE_CHECKED = ("input", "output", "aux")


def is_can_csv(path: Path) -> bool:
    """Whether a ``.csv`` file is python-can's CSV CAN log (header ``timestamp,arbitration_id,...``), not a table."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            head = f.readline(4096)
    except OSError:
        return False  # (the table reader names what is wrong)
    return [c.strip() for c in head.split(",")[:2]] == ["timestamp", "arbitration_id"]


def table_error(path: Path | str, column: str, row: int | None, expected: str, got: str) -> UserError:
    """The one message format of a bad value: file, column, row (1-based; None: the
    column as a whole), what was expected and what was found; a CSV table's row also as its line (not a CSV CAN
    log's: its rows are the 20 Hz ticks decoded from it)."""
    path = Path(path)
    where = f"column {column}"
    if row is not None:
        where += f", row {row}"
        if path.suffix.lower() == ".csv" and not is_can_csv(path):
            where += f" (line {row + 1})"
    return UserError(f"{path}: {where}: expected {expected}, got {got}")


def _check_time(path: Path, t: np.ndarray, gaps: bool) -> None:
    if t.size < MIN_ROWS:
        raise table_error(path, "time_s", None, f"at least {MIN_ROWS} rows at {RATE_HZ:g} Hz", f"{t.size}")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise table_error(path, "time_s", int(bad[0]) + 1, "a finite time in s", f"{t[bad[0]]}")
    dt = np.diff(t)
    back = np.flatnonzero(dt <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise table_error(path, "time_s", i + 1, f"time strictly increasing (row {i} is at {t[i - 1]:.6g} s)",
                          f"{t[i]:.6g} s")
    _check_one_run(path, t, dt)
    tol = STEP_TOLERANCE * TICK_S
    median = float(np.median(dt))
    if abs(median - TICK_S) > tol:
        i = int(np.flatnonzero(np.abs(dt - TICK_S) > tol)[0]) + 1
        raise table_error(path, "time_s", i + 1, f"{RATE_HZ:g} Hz rows (steps of {TICK_S:g} s)",
                          f"{1.0 / median:.4g} Hz (steps of {median:.4g} s); resample it on the {RATE_HZ:g} Hz "
                          f"bus tick or give the CAN log")
    ticks = np.maximum(np.round(dt / TICK_S), 1.0) if gaps else np.ones_like(dt)
    off = np.flatnonzero(np.abs(dt - ticks * TICK_S) > tol)
    if off.size:
        i = int(off[0]) + 1
        want = f"a whole number of {TICK_S:g} s ticks after row {i}" if gaps else \
            f"one {TICK_S:g} s tick after row {i} ({RATE_HZ:g} Hz, no missing rows)"
        raise table_error(path, "time_s", i + 1, want, f"a step of {dt[i - 1]:.6g} s")


def _check_one_run(path: Path, t: np.ndarray, dt: np.ndarray) -> None:
    """Refuse rows ``t`` (increasing, s; ``dt`` their steps) that are not one run's time: a step over
    :data:`~virtsensor.frontend.MAX_GAP_S` or a span over :data:`~virtsensor.frontend.MAX_SPAN_S`."""
    i = int(np.argmax(dt))
    if dt[i] > MAX_GAP_S:
        raise table_error(path, "time_s", i + 2, f"at most {MAX_GAP_S:g} s after row {i + 1} (at {t[i]:.6f} s; one "
                          f"run has no longer gap: two runs, or a clock that jumped?)",
                          f"{t[i + 1]:.6f} s, {dt[i]:.6g} s later")
    if t[-1] - t[0] > MAX_SPAN_S:
        raise table_error(path, "time_s", t.size, f"at most {MAX_SPAN_S / 3600:g} h after row 1 (at {t[0]:.6f} s; "
                          f"one run lasts no longer)", f"{t[-1]:.6f} s, {t[-1] - t[0]:.6g} s later")


def _check_ranges(path: Path, table: Mapping[str, np.ndarray]) -> None:
    for name, col in table.items():
        s = cat.SIGNALS.get(name)
        if s is None:
            continue
        col = np.asarray(col, dtype=np.float64)
        if s.role not in _RANGE_CHECKED:  # (a truth column: any finite value of the simulator's state, or SNA)
            inf = np.flatnonzero(np.isinf(col))
            if inf.size:
                i = int(inf[0])
                raise table_error(path, name, i + 1, f"a finite value in {s.unit} or SNA (the simulator's state)",
                                  f"{col[i]} ({inf.size} rows)")
            continue
        with np.errstate(invalid="ignore"):
            out = ~np.isnan(col) & ~((col >= s.minimum) & (col <= s.maximum))
        bad = np.flatnonzero(out)
        if bad.size:
            i = int(bad[0])
            worst = col[bad][np.argmax(np.abs(col[bad]))]
            raise table_error(path, name, i + 1, f"{s.minimum:g} to {s.maximum:g} {s.unit} or SNA",
                              f"{col[i]:.6g} (reaching {worst:.6g} in {bad.size} rows; wrong unit or scaling?)")


def check_table(path: Path | str, table: Mapping[str, np.ndarray], *, targets: Sequence[str] = (),
                gaps: bool = False) -> None:
    """Refuse a recording's table that is not fit to read as data (see the module docstring).

    Args:
        path: the file the table came from (named in messages).
        table: column name -> 1-D array (``time_s`` in s, catalogue units).
        targets: columns that must be finite in every row (absent ones are the
            caller's missing-signal check, not this one's).
        gaps: accept steps of several ticks (missing rows: gaps the caller cuts at).

    Raises:
        UserError: the first problem found, in the one message format.
    """
    path = Path(path)
    if "time_s" not in table:
        raise table_error(path, "time_s", None, "a time column (s)", "none")
    t = np.asarray(table["time_s"], dtype=np.float64)
    _check_time(path, t, gaps)
    for name, col in table.items():
        if np.shape(col) != t.shape:
            raise table_error(path, name, None, f"{t.size} rows like time_s", f"{np.shape(col)}")
    _check_ranges(path, table)
    for name in targets:
        if name not in table:
            continue
        col = np.asarray(table[name], dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(col))
        if bad.size:
            i = int(bad[0])
            raise table_error(path, name, i + 1, "a finite reference value in every row (a target)",
                              f"{col[i]} ({bad.size} rows without one)")
