"""Training and evaluation data: recordings -> per-run 20 Hz tables -> feature matrices.

A *recording* is a canonical CSV table, a CAN log (.blf, .asc, .log, .trc) or an
MDF4 file (:mod:`virtsensor.recordings.files`). Logs are decoded through the DBC
and sampled by the same front-end the runtime uses
(:func:`virtsensor.recordings.canlog.read_log`); simulated CSV tables were made by that
same path. A directory of recordings may hold the ``manifest.json`` a campaign
writes last; the directory must then hold exactly its runs, each as listed, and
their metadata (manoeuvre, speed, friction, seed) travel with each run.

Rows whose features or targets are not finite (NaN: a signal not available at
that tick, the first ticks of a run without history) are dropped by
:func:`build_dataset` and counted, never trained on; a file whose reference SATs
are not finite in every row is refused by :func:`load_runs` before that.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.features import FeatureSpec
from virtsensor.recordings.check import check_table
from virtsensor.recordings.files import read_table, recording_files
from virtsensor.recordings.identity import find_overlap, find_repeat, refuse_repeats, table_digest
from virtsensor.recordings.manifest import check_rows, file_sha256


@dataclass
class Run:
    """One recording: its name, canonical table and metadata."""

    name: str
    table: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None
    #: the digest of its table as the CAN bus carries it (:func:`~virtsensor.recordings.identity.table_digest`;
    #: empty: not computed)
    digest: str = ""


def load_runs(paths: Iterable[Path | str], needed: Sequence[str] = ()) -> list[Run]:
    """Read recordings (files or directories of them) into runs, each checked.

    Files are listed by :func:`virtsensor.recordings.files.recording_files`
    (hidden and ``.partial-*`` files never count; a campaign directory must be
    complete and hold exactly its manifest's runs, each with its listed sha256 and
    rows) and every table passes the shared input check
    :func:`virtsensor.recordings.check.check_table` (20 Hz, no missing rows,
    strictly increasing time, signals in their catalogue ranges or SNA; the
    reference SATs among ``needed`` finite in every row).

    Args:
        paths: recording files, or directories holding them.
        needed: catalogue signals every run must carry; a run without one is
            refused with a one-line error naming the signal and the file. The TPMS
            pressures are the exception: a run without them (a car or a recording
            without TPMS) gets NaN columns (pressure unknown, not nominal) and
            ``meta["pressure_unknown"] = True``.

    Raises:
        UserError: the first file that fails, naming it (and column and row); a run given twice (another file of
            the same signals tick for tick: a copy, or the run as a table and as a CAN log;
            :func:`~virtsensor.recordings.identity.refuse_repeats`).
    """
    targets = [s for s in needed if s in cat.OUTPUTS]
    runs = []
    for source in recording_files(paths):
        f = source.path
        table = read_table(f)
        digest = table_digest(table) if len(table.get("time_s", ())) else ""
        unknown = [s for s in needed if s in cat.TPMS_SIGNALS and s not in table]
        for s in unknown:  # a recording without TPMS: its pressures are unknown (NaN), never taken as nominal
            table[s] = np.full(len(table["time_s"]) if "time_s" in table else 0, np.nan)
        missing = [s for s in needed if s not in table]
        if missing:
            raise UserError(f"{f}: recording lacks the needed signal(s) {', '.join(missing)}")
        meta: dict[str, Any] = {}
        check_table(f, table, targets=targets)  # (first: it refuses a table without time_s)
        if source.entry is not None:
            check_rows(f, source.entry, len(table["time_s"]))
            meta = {k: v for k, v in source.entry.items() if k != "file"}
        if unknown:
            meta["pressure_unknown"] = True
        runs.append(Run(f.stem, table, meta, f, digest))
    refuse_repeats((r.path or r.name, r.digest, r.table) for r in runs)  # (a copy, one run as a table and a log)
    return runs


def run_digest(run: Run) -> str | None:
    """sha256 of the run's file: its campaign manifest's when listed there (checked on loading), else of the
    file's bytes; None for a run without a file."""
    listed = run.meta.get("sha256")
    if isinstance(listed, str):
        return listed
    return file_sha256(run.path) if run.path is not None else None


def _identity(run: Run) -> list[object]:
    """What makes two runs the same: their resolved file, their file's sha256, their table's digest (the same
    signals in another file or format)."""
    keys: list[object] = [] if run.path is None else [run.path.resolve()]
    if run.digest:
        keys.append(("table", run.digest))
    digest = run_digest(run)
    return keys if digest is None else [*keys, ("sha256", digest)]


def trained_digests(runs: Sequence[Run]) -> list[str]:
    """The table digests of the runs a model is trained on, sorted: a card records them
    (``training_data.run_digests``) so that :func:`trained_on` can tell a run the model has seen."""
    return sorted({r.digest for r in runs if r.digest})


def trained_on(card: Mapping[str, Any], runs: Sequence[Run]) -> list[Run]:
    """The ``runs`` the card's model was trained on (their table digest among its ``training_data.run_digests``);
    none for a card that records no digests (the shipped models, trained before cards carried them)."""
    digests = set((card.get("training_data") or {}).get("run_digests") or ())
    return [r for r in runs if r.digest and r.digest in digests]


def refuse_trained_on(card: Mapping[str, Any], named: Sequence[tuple[str, Sequence[Run]]], model: str,
                      why: str) -> None:
    """Refuse a run of ``named`` (``(option, runs)``) that the card's model was trained on (:func:`trained_on`).

    Raises:
        UserError: ``<file>: <model> was trained on this run (its card lists it), given as <option>; <why>``.
    """
    for option, runs in named:
        seen = trained_on(card, runs)
        if seen:
            r = seen[0]
            raise UserError(f"{r.path or r.name}: {model} was trained on this run (its card lists it), given as "
                            f"{option}; {why}")


def check_disjoint(named: Sequence[tuple[str, Sequence[Run]]], why: str) -> None:
    """Refuse a run that is in two of the ``named`` sets (``(option, runs)``): the same file, or another file
    with the same content (:func:`run_digest`) or the same run in another file or format (its table's digest), e.g.
    held-out runs also given on the training side.

    Raises:
        UserError: ``<file>: given both as <option> and as <option> [(<other file>, the same content)]; <why>``, or
            ``(<other file>, the same signals written with other decimals)`` (:func:`~virtsensor.recordings.identity.
            find_repeat`).
    """
    seen: dict[object, tuple[str, Run]] = {}
    for option, runs in named:
        identities = [(r, _identity(r)) for r in runs]
        for r, keys in identities:
            hit = next((seen[k] for k in keys if k in seen), None)
            if hit is not None:
                other_option, other = hit
                same_file = r.path is not None and other.path is not None and r.path.resolve() == other.path.resolve()
                also = "" if same_file else f" ({other.path or other.name}, the same content)"
                raise UserError(f"{r.path or r.name}: given both as {other_option} and as {option}{also}; {why}")
        for r, keys in identities:
            for k in keys:
                seen.setdefault(k, (option, r))
    flat = [(k, option, r) for k, (option, runs) in enumerate(named) for r in runs if len(r.table.get("time_s", ()))]
    pair = find_repeat([r.table for _, _, r in flat], [k for k, _, _ in flat])
    if pair is not None:
        (_, first, a), (_, second, b) = flat[pair[0]], flat[pair[1]]
        raise UserError(f"{b.path or b.name}: given both as {first} and as {second} ({a.path or a.name}, the same "
                        f"signals written with other decimals); {why}")
    cut = find_overlap([r.table for _, _, r in flat], [k for k, _, _ in flat])
    if cut is not None:
        (_, first, a), (_, second, b) = flat[cut[0]], flat[cut[1]]
        raise UserError(f"{b.path or b.name}: given both as {first} and as {second} ({cut[2]} of its rows are "
                        f"{a.path or a.name}'s, tick for tick: one run, cut otherwise); {why}")


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


def build_dataset(runs: Sequence[Run], spec: FeatureSpec, targets: Sequence[str] = cat.OUTPUTS,
                  optional: Sequence[str] = ()) -> Dataset:
    """Feature vectors of every run (history never crosses a run boundary).

    ``optional``: names of features that may be non-finite in a kept row (the TPMS pressures of a model with a
    pressure-free fallback: such a row is estimated by the fallback); every other feature and target must be."""
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
        must = [j for j, name in enumerate(spec.names) if name not in optional]
        ok = np.isfinite(x[:, must]).all(axis=1) & np.isfinite(y).all(axis=1)
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

    Raises:
        UserError: the run's metadata (its campaign manifest's entry, or its own ``<stem>.json``) names another
            manoeuvre (a recording without one, e.g. measured, is taken as given).
    """
    from virtsensor.recordings.sidecar import sidecar_of

    what = run.meta.get("manoeuvre")
    if what is None and run.path is not None:
        own = sidecar_of(run.path)
        what = own.doc.get("manoeuvre") if own.matches and own.doc is not None else None
    if what is not None and what != "magny-cours":
        raise UserError(f"{run.path or run.name}: a {what} run (its metadata), not a Magny-Cours recording "
                        "(the dry lap, then the wet one: virtsensor simulate magny-cours)")
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

