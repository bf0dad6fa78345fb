"""Training and evaluation data: recordings -> per-run 20 Hz tables -> feature matrices.

A *recording* is a canonical CSV table or a CAN log (.blf, .asc, .log, ...). Logs
are decoded through the DBC and sampled by the same front-end the runtime uses
(:func:`virtsensor.recording.read_log`); simulated CSV tables were made by that
same path. A directory of recordings may hold the ``manifest.json`` a campaign
writes; its per-run metadata (manoeuvre, speed, friction, seed) then travel with
each run.

Rows whose features or targets are not finite (NaN, inf: a signal missing at
that tick, the first ticks of a run without history) are dropped and counted,
never trained on.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.features import FeatureSpec

TABLE_SUFFIXES = (".csv",)
LOG_SUFFIXES = (".blf", ".asc", ".log", ".trc")


@dataclass
class Run:
    """One recording: its name, canonical table and metadata."""

    name: str
    table: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None


def _recording_files(paths: Iterable[Path | str]) -> list[Path]:
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.suffix.lower() in TABLE_SUFFIXES + LOG_SUFFIXES)
            if not found:
                raise UserError(f"{p}: no recordings (.csv, .blf, .asc, .log) in this directory")
            files.extend(found)
        elif p.exists():
            files.append(p)
        else:
            raise UserError(f"{p}: no such file or directory")
    return files


def _manifests(files: Sequence[Path]) -> dict[Path, dict[str, Any]]:
    meta: dict[Path, dict[str, Any]] = {}
    for d in {f.parent for f in files}:
        m = d / "manifest.json"
        if m.exists():
            try:
                runs = json.loads(m.read_text())["runs"]
            except (ValueError, KeyError, TypeError) as exc:
                raise UserError(f"{m}: not a campaign manifest ({exc})") from None
            for r in runs:
                meta[d / r["file"]] = {k: v for k, v in r.items() if k != "file"}
    return meta


def load_runs(paths: Iterable[Path | str], needed: Sequence[str] = ()) -> list[Run]:
    """Read recordings (files or directories of them) into runs.

    Args:
        paths: recording files, or directories holding them.
        needed: catalogue signals every run must carry; a run without one is
            refused with a one-line error naming the signal and the file.
    """
    from virtsensor.recording import read_csv, read_log

    files = _recording_files(paths)
    meta = _manifests(files)
    runs = []
    for f in files:
        if f.suffix.lower() in TABLE_SUFFIXES:
            table = read_csv(f)
        else:
            table = read_log(f).table
        missing = [s for s in needed if s not in table]
        if missing:
            raise UserError(f"{f}: recording lacks the needed signal(s) {', '.join(missing)}")
        runs.append(Run(f.stem, table, dict(meta.get(f, {})), f))
    return runs


@dataclass
class Dataset:
    """Feature matrix, targets and run groups of a set of runs.

    Attributes:
        X: (n, d) features; Y: (n, k) targets (Nm); groups: (n,) run index.
        runs: the runs' names; meta: their metadata.
        feature_names, target_names: column names.
        dropped_nonfinite: rows dropped because a feature or target was NaN/inf.
        time_s: (n,) each row's time in its run.
    """

    X: np.ndarray
    Y: np.ndarray
    groups: np.ndarray
    runs: list[str]
    meta: list[dict[str, Any]]
    feature_names: tuple[str, ...]
    target_names: tuple[str, ...]
    dropped_nonfinite: int
    time_s: np.ndarray

    def subset(self, rows: np.ndarray) -> Dataset:
        """The rows ``rows`` (indices or mask), same runs list."""
        return Dataset(self.X[rows], self.Y[rows], self.groups[rows], self.runs, self.meta, self.feature_names,
                       self.target_names, 0, self.time_s[rows])

    def runs_where(self, **conditions: Any) -> np.ndarray:
        """Row mask of the runs whose metadata match all ``conditions``."""
        ok = np.array([all(m.get(k) == v for k, v in conditions.items()) for m in self.meta], dtype=bool)
        return ok[self.groups] if len(ok) else np.zeros(0, dtype=bool)

    def fingerprint(self) -> str:
        """sha256 of the feature and target bytes (identifies the training data)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.X, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(self.Y, dtype=np.float64).tobytes())
        h.update(json.dumps([self.feature_names, self.target_names]).encode())
        return h.hexdigest()


def build_dataset(runs: Sequence[Run], spec: FeatureSpec, targets: Sequence[str] = cat.OUTPUTS) -> Dataset:
    """Feature vectors of every run (history never crosses a run boundary)."""
    if not runs:
        raise UserError("no runs to build a data set from")
    xs, ys, gs, ts = [], [], [], []
    dropped = 0
    for i, run in enumerate(runs):
        missing = [s for s in (*spec.signals, *targets) if s not in run.table]
        if missing:
            where = run.path or run.name
            raise UserError(f"{where}: recording lacks the needed signal(s) {', '.join(missing)}")
        x = spec.transform(run.table)
        y = np.column_stack([np.asarray(run.table[t], dtype=np.float64) for t in targets])
        ok = np.isfinite(x).all(axis=1) & np.isfinite(y).all(axis=1)
        dropped += int((~ok).sum())
        xs.append(x[ok])
        ys.append(y[ok])
        gs.append(np.full(int(ok.sum()), i))
        ts.append(np.asarray(run.table["time_s"], dtype=np.float64)[ok])
    return Dataset(np.concatenate(xs), np.concatenate(ys), np.concatenate(gs), [r.name for r in runs],
                   [r.meta for r in runs], spec.names, tuple(targets), dropped, np.concatenate(ts))


def split_track_laps(run: Run) -> dict[str, Run]:
    """Split a Magny-Cours recording into its dry and wet laps.

    Uses the simulator's ``road_mu`` truth column where present (the second lap is
    the one with the lower friction); otherwise the two halves in time.
    """
    t = run.table
    n = len(t["time_s"])
    if "road_mu" in t:
        mu = np.asarray(t["road_mu"])
        wet = mu < mu.max() - 1e-6
    else:
        wet = np.arange(n) >= n // 2
    out = {}
    for name, mask in (("dry", ~wet), ("wet", wet)):
        if mask.any():
            out[name] = Run(f"{run.name}-{name}", {k: np.asarray(v)[mask] for k, v in t.items()},
                            {**run.meta, "lap": name}, run.path)
    return out

