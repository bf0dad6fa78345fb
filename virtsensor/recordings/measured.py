"""Measured data as a test vehicle records it, checked before anyone trusts it.

Accepted: CAN logs (.blf, .asc, .log, .trc) decoded through the DBC by the
runtime's front-end, MDF4 files (.mf4, .mdf; needs the ``mdf`` extra, asammdf)
with channels named by catalogue name or DBC signal name, and the canonical
20 Hz CSV table. Every run must carry the 12 estimator inputs and the reference
SATs (wheel-force transducers); anything else the car had (TPMS pressures, rear
wheel speeds...) is kept.

Files are listed and read by :mod:`virtsensor.recordings.files` (hidden and
``.partial-*`` files are never runs; a campaign directory is checked against its
manifest). Checks, each a one-line :class:`UserError` naming the file:

* a needed signal missing;
* the shared input check :func:`virtsensor.recordings.check.check_table` with
  gaps allowed: 20 Hz rows (logs and MDF files are sampled at 20 Hz by the
  front-end, whatever their message rates), strictly increasing time, every
  signal inside its catalogue range or SNA (a test day's log has dropouts: unlike
  ``train`` and ``score``, which refuse missing rows and a non-finite reference
  SAT, the diagnosis keeps them as gaps);
* a unit scaling that contradicts the car's kinematics (speed in km/h, angles in
  degrees, accelerations in g, pressures in bar...), found by cross-checking
  signals that physics ties together;
* no moving sample (``vx_mps`` never above :data:`MOVING_MPS`: a car standing
  still has nothing to re-simulate).

Gaps (non-finite samples of a needed signal, the reference SATs included, or
missing ticks in a CSV table) are kept as gaps: the run is cut into segments at
them, never interpolated across; each segment in which the car moves is
re-simulated on its own and the gaps are listed in the report.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.recordings.check import check_table
from virtsensor.recordings.files import read_table, recording_files
from virtsensor.recordings.identity import refuse_repeats, table_digest
from virtsensor.recordings.manifest import check_rows

RATE_HZ = cat.TABLE_RATE_HZ
TICK_S = cat.TABLE_TICK_S
#: signals a measured run must carry: the 12 inputs and the reference SATs (the canonical table but time_s)
NEEDED: tuple[str, ...] = cat.TABLE_COLUMNS[1:]
#: shortest segment between gaps worth re-simulating (s)
MIN_SEGMENT_S = 4.0
#: a run or segment whose forward speed never exceeds this (m/s, walking pace) has the car standing still
MOVING_MPS = 1.0


@dataclass
class Segment:
    """A stretch of a measured run without gaps: rows ``start:stop`` of the table."""

    start: int
    stop: int

    @property
    def n(self) -> int:
        return self.stop - self.start


@dataclass
class MeasuredRun:
    """One measured run: its 20 Hz table (``time_s`` from the first tick), where it
    came from, its segments and gaps."""

    name: str
    path: Path
    table: dict[str, np.ndarray]
    segments: list[Segment]
    gaps: list[tuple[float, float]] = field(default_factory=list)  # (start, end) s
    notes: list[str] = field(default_factory=list)
    #: the digest of the table as read (:func:`~virtsensor.recordings.identity.table_digest`): the same run in
    #: another file or format has the same
    digest: str = ""

    @property
    def duration_s(self) -> float:
        t = self.table["time_s"]
        return float(t[-1] - t[0]) if len(t) else 0.0

    def segment_table(self, seg: Segment) -> dict[str, np.ndarray]:
        return {k: v[seg.start:seg.stop] for k, v in self.table.items()}


def _rms_ratio(y: np.ndarray, x: np.ndarray) -> float | None:
    """RMS of ``y`` over RMS of ``x`` (same rows; None where ``x`` is all zero): an amplitude ratio, blind to a lag."""
    xx = float(np.sum(x ** 2))
    return float(np.sqrt(np.sum(y ** 2) / xx)) if xx > 0 else None


def _kinematic_checks(table: Mapping[str, np.ndarray]) -> list[tuple[str, float]]:
    """Amplitude ratios (RMS over RMS) of a signal to what kinematics predicts from others (about 1 when the
    units are right): speed against the front wheel speeds times a passenger-car rolling radius (0.30 m,
    within 15 %), lateral acceleration against yaw rate x speed. Amplitudes, not a least-squares fit: a signal
    that lags the others (a sensor delay, what ``diagnose`` looks for) keeps its amplitude, while its
    least-squares ratio falls with the phase (0.31 for a 0.1 s lag in a 2 Hz slalom, near km/h's 1/3.6)."""
    def ratio(y: np.ndarray, x: np.ndarray, min_ref: float) -> float | None:
        ok = np.isfinite(y) & np.isfinite(x)
        if ok.sum() < 20 or np.max(np.abs(x[ok])) < min_ref:
            return None  # not excited enough to tell
        return _rms_ratio(y[ok], x[ok])

    out = []
    wheels = 0.5 * (table["wheel_speed_fl_radps"] + table["wheel_speed_fr_radps"])
    vx, yaw, ay = table["vx_mps"], table["yaw_rate_radps"], table["ay_mps2"]
    for name, k in (("vx_mps", ratio(vx, wheels * 0.30, 5.0)), ("ay_mps2", ratio(ay, yaw * vx, 1.5))):
        if k is not None:
            out.append((name, k))
    return out


_NAMED_SCALES = {3.6: "km/h instead of m/s", 1 / 3.6: "m/s against wheel speeds in km/h",
                 2.237: "mph instead of m/s", 1 / 9.81: "g instead of m/s^2", 9.81: "m/s^2 against g",
                 57.2958: "degrees instead of radians", 1 / 57.2958: "radians against degrees",
                 100.0: "a factor 100", 0.01: "a factor 1/100", 1000.0: "a factor 1000", 0.001: "a factor 1/1000"}


def _check_units(path: Path, table: Mapping[str, np.ndarray]) -> None:
    """Gross unit errors the catalogue ranges let through: kinematic cross-checks."""
    # a car at its limit (sideslip, wheelspin) departs from the kinematics by tens of
    # per cent: only a ratio near a unit factor is a unit error
    for name, k in _kinematic_checks(table):
        if k <= 0 or not np.isfinite(k):
            continue
        nearest = min(_NAMED_SCALES, key=lambda s: abs(np.log(k / s)))
        if not 0.6 < k < 1.6 and abs(np.log(k / nearest)) < 0.2:
            raise UserError(f"{path}: {name} is {k:.3g} x what the kinematics give from the other signals "
                            f"(about x{nearest:.4g}: {_NAMED_SCALES[nearest]}?); expected {cat.SIGNALS[name].unit}")
    # steering-wheel angle in degrees: lock-to-lock is about +-8 rad; in degrees a
    # moderate manoeuvre already exceeds 13 (caught by the range), a gentle one does not:
    sw, yaw, vx = table["steer_angle_rad"], table["yaw_rate_radps"], table["vx_mps"]
    ok = np.isfinite(sw) & np.isfinite(yaw) & np.isfinite(vx) & (vx > 5.0)
    if ok.sum() > 40 and np.nanmax(np.abs(yaw[ok])) > 0.05:
        # kinematic yaw rate of a car with a 14-18 steering ratio and a 2.4-3.0 m wheelbase
        k_lo = 1.0 / (18.0 * 3.0)
        big = ok & (np.abs(sw) > 0.3 * np.nanmax(np.abs(sw[ok])))
        if big.sum() > 10:
            # amplitudes, as in _kinematic_checks: a least-squares gain falls with a lag between the two (a yaw
            # rate delayed 0.15 s in a 2 Hz sine gives a negative one), and a sensor delay is what diagnose seeks
            gain = _rms_ratio(yaw[big], sw[big] * vx[big])
            if gain is not None and gain < 0.1 * k_lo:
                raise UserError(f"{path}: steer_angle_rad is far too large for the yaw rate it gives "
                                f"(steering ratio {1.0 / (gain * 2.7):.0f}:1); degrees instead of radians?")


def _moving(table: Mapping[str, np.ndarray], start: int, stop: int) -> bool:
    """Whether the car moves in rows ``start:stop`` (``vx_mps`` above :data:`MOVING_MPS`; no speed: assumed)."""
    vx = table.get("vx_mps")
    return vx is None or bool(np.any(np.abs(vx[start:stop]) > MOVING_MPS))


def _segments(path: Path, table: dict[str, np.ndarray], needed: Sequence[str]
              ) -> tuple[dict[str, np.ndarray], list[Segment], list[tuple[float, float]], list[str]]:
    """Put the run on a regular tick grid (missing ticks become NaN rows), find gaps
    (any needed signal non-finite), cut segments between them (none: no stretch
    long enough to re-simulate, the caller decides)."""
    t = table["time_s"]
    k = np.round((t - t[0]) / TICK_S).astype(np.int64)
    if np.any(np.diff(k) <= 0):
        raise UserError(f"{path}: time_s is not on a {TICK_S:g} s grid (two samples in one tick)")
    n = int(k[-1]) + 1
    full = {"time_s": t[0] + TICK_S * np.arange(n)}
    for name, col in table.items():
        if name == "time_s":
            continue
        c = np.full(n, np.nan)
        c[k] = col
        full[name] = c
    good = np.ones(n, dtype=bool)
    for name in needed:
        good &= np.isfinite(full[name])
    notes = []
    gaps: list[tuple[float, float]] = []
    segs: list[Segment] = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], good.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if (b - a) * TICK_S < MIN_SEGMENT_S:
            notes.append(f"a {(b - a) * TICK_S:.2f} s stretch at {full['time_s'][a]:.2f} s between gaps is too "
                         f"short to re-simulate (< {MIN_SEGMENT_S:g} s)")
        elif not _moving(full, a, b):
            notes.append(f"in the {(b - a) * TICK_S:.2f} s stretch at {full['time_s'][a]:.2f} s the car stands "
                         f"still (vx_mps never above {MOVING_MPS:g} m/s): not re-simulated")
        else:
            segs.append(Segment(int(a), int(b)))
    bad_edges = np.flatnonzero(np.diff(np.concatenate([[0], (~good).astype(np.int8), [0]])))
    for a, b in zip(bad_edges[::2], bad_edges[1::2], strict=True):
        gaps.append((float(full["time_s"][a]), float(full["time_s"][b - 1] + TICK_S)))
    return full, segs, gaps, notes


def load_measured(paths: Iterable[str | Path], needed: Sequence[str] = NEEDED,
                  skipped: list[tuple[str, str]] | None = None) -> list[MeasuredRun]:
    """Read and check measured runs (files or directories of them).

    A run with no gap-free stretch long enough to re-simulate (a test stopped
    early, a spin) is refused; with ``skipped`` given, it is left out and listed
    there as ``(file, reason)`` instead, unless no run at all is left.
    """
    runs = []
    for source in recording_files(paths):
        path = source.path
        table = read_table(path)
        missing = [s for s in ("time_s", *needed) if s not in table]
        if missing:
            raise UserError(f"{path}: measured run lacks the needed signal(s) {', '.join(missing)}")
        if source.entry is not None:
            check_rows(path, source.entry, len(table["time_s"]))
        table = {k: np.asarray(v, dtype=float) for k, v in table.items()}
        check_table(path, table, gaps=True)
        digest = table_digest(table)
        _check_units(path, table)
        full, segs, gaps, notes = _segments(path, table, needed)
        if not _moving(table, 0, len(table["time_s"])):
            why = f"no moving sample (vx_mps never above {MOVING_MPS:g} m/s: the car stands still)"
            segs = []
        else:
            why = f"no stretch of at least {MIN_SEGMENT_S:g} s without gaps in the needed signals"
        if not segs:
            if skipped is None:
                raise UserError(f"{path}: {why}")
            skipped.append((str(path), why))
            continue
        full["time_s"] = full["time_s"] - full["time_s"][0]
        runs.append(MeasuredRun(path.stem, path, full, segs, gaps, notes, digest))
    refuse_repeats((r.path, r.digest, r.table) for r in runs)  # (a copy, or one run as a table and a CAN log)
    if not runs:
        raise UserError(f"no usable measured run: {'; '.join(f'{p}: {why}' for p, why in skipped or [])}")
    names = [r.name for r in runs]
    if len(set(names)) != len(names):
        raise UserError("two measured runs have the same file name stem; rename one")
    return runs
