"""Write a simulation campaign into a directory that readers can trust.

The order of writes is the contract of :mod:`virtsensor.recordings.manifest`:
marker, runs under ``.partial-*`` names (written by the workers), renames (by
the campaign's own process, once every run is complete), manifest, marker
removed. A campaign that is interrupted (KeyboardInterrupt, or SIGTERM turned
into one by the command) removes what it wrote; one that is killed leaves its
marker, so readers refuse the directory.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

from virtsensor.errors import UserError
from virtsensor.extras import require
from virtsensor.fileio import name_the_file
from virtsensor.recordings.files import WRITE_FORMATS
from virtsensor.recordings.manifest import (
    MANIFEST,
    MARKER,
    PROVENANCE,
    file_sha256,
    incomplete_campaign,
    start_marker,
    write_manifest,
)
from virtsensor.recordings.simulated import metadata_entry, partial_name, write_run_file

#: file formats of a campaign's runs (suffix without the dot)
FORMATS = WRITE_FORMATS
#: joblib backends of a cluster -> the optional extra that provides them
CLUSTER_EXTRAS = {"ray": "distributed", "dask": "dask"}


def run_name(request: Any, fmt: str) -> str:
    """File name of a campaign run (a :class:`sim.api.Request`) in format ``fmt``."""
    r = request
    where = f"-{str(r.track).replace(':', '')}" if getattr(r, "track", None) else ""
    return f"{r.manoeuvre}{where}_{r.speed_kmh:g}kmh_mu{r.mu:g}_{r.seed}.{fmt}"


def write_partial_run(sim_run: Any, out_dir: Path, fmt: str) -> dict[str, Any]:
    """Worker side: write one finished run under its ``.partial-*`` name and return
    its manifest entry (final file name, request, rows, sha256, duration...)."""
    final = Path(out_dir) / run_name(sim_run.request, fmt)
    tmp = partial_name(final)
    try:
        table = write_run_file(sim_run, tmp)
    except OSError as exc:
        name_the_file(exc, final)  # (a full disk names no file: the parent's one line says which)
        raise
    entry = metadata_entry(sim_run, final, table)
    entry.update(rows=len(table["time_s"]), sha256=file_sha256(tmp))
    return entry


def _check_out(out_dir: Path) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--out {out_dir}: is a file, not a directory")
    why = incomplete_campaign(out_dir) if out_dir.is_dir() else None
    if why:
        raise UserError(why)
    if out_dir.is_dir() and any(out_dir.iterdir()):
        raise UserError(f"--out {out_dir}: directory is not empty (refusing to mix campaigns)")


def _remove(out_dir: Path, names: Sequence[str], created: bool) -> None:
    """Undo an interrupted campaign: its files, then the directory if it made it."""
    for name in (*names, MANIFEST):
        (out_dir / name).unlink(missing_ok=True)
        partial_name(out_dir / name).unlink(missing_ok=True)
    (out_dir / PROVENANCE).unlink(missing_ok=True)
    (out_dir / MARKER).unlink(missing_ok=True)
    if created:
        try:
            out_dir.rmdir()
        except OSError:
            pass


def write_campaign(requests: Sequence[Any], params: Mapping[str, Any], out_dir: Path | str, *, fmt: str = "csv",
                   info: Mapping[str, Any] | None = None, n_jobs: int = -1, batch_size: int = 25,
                   backend: str | None = None, progress: bool = True) -> dict[str, Any]:
    """Simulate ``requests`` with the car ``params`` into the empty (or new) directory
    ``out_dir``, one file per run in format ``fmt``; returns the manifest written.

    ``info`` (preset, seed, car overrides...) goes into the marker and the manifest.
    On any exception or interrupt the files written so far are removed (workers
    first stopped by :func:`sim.campaign.run_campaign`) and it propagates.

    Raises:
        UserError: ``out_dir`` not empty, a file, or an unfinished campaign; an unknown ``fmt``; ``backend``
            ``ray`` or ``dask`` without its optional extra (:data:`CLUSTER_EXTRAS`).
    """
    from sim.campaign import run_campaign

    if fmt not in FORMATS:
        raise UserError(f"--format {fmt!r}: one of {', '.join(FORMATS)}")
    if backend in CLUSTER_EXTRAS:
        require(CLUSTER_EXTRAS[backend], f"--backend {backend}")
    out_dir = Path(out_dir)
    _check_out(out_dir)
    info = dict(info or {})
    names = [run_name(r, fmt) for r in requests]
    if len(set(names)) != len(names):
        raise UserError("two runs of the campaign would share a file name (same manoeuvre, speed, mu and seed)")
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        start_marker(out_dir, {**info, "runs": len(requests), "format": fmt})
        t0 = time.perf_counter()
        entries = run_campaign(requests, params, n_jobs=n_jobs, batch_size=batch_size,
                               writer=partial(write_partial_run, out_dir=out_dir, fmt=fmt),
                               progress=progress, backend=backend)
        for e in entries:
            partial_name(out_dir / e["file"]).replace(out_dir / e["file"])
        manifest = {**info, "format": fmt, "runs": entries, "samples": sum(e["rows"] for e in entries),
                    "simulated_s": sum(e["duration_s"] for e in entries), "wall_s": time.perf_counter() - t0}
        write_manifest(out_dir, manifest)
    except BaseException:
        _remove(out_dir, names, created)
        raise
    return manifest
