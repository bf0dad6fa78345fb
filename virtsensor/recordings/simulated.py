"""A simulated run as data: the canonical 20 Hz table and the file that holds it.

The table is what a receiver on the bus samples from the run's frames (inputs
and reference SATs, see :func:`virtsensor.recordings.canlog.simulated_recording`), with
the simulator's truth columns (slip angles, loads, forces...) at the same ticks.
A CSV file holds that table; a CAN log holds the frames, and reading it back
(:func:`virtsensor.recordings.canlog.read_log`) gives the same inputs and SATs at the
same ticks.

The simulator (package ``sim``) is imported only when a function here runs.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor.errors import UserError
from virtsensor.fileio import name_the_file, write_json
from virtsensor.recordings.check import MIN_ROWS
from virtsensor.recordings.files import LOG_SUFFIXES, TABLE_SUFFIXES


def run_table(sim_run: Any) -> dict[str, np.ndarray]:
    """The canonical 20 Hz table of a simulated run (a :class:`sim.api.SimRun`):
    ``time_s`` (s), the catalogue's inputs and reference SATs as a receiver decodes
    them from the run's frames, then the truth columns at the same ticks."""
    from sim.sensors import truth_at
    from virtsensor.recordings.canlog import simulated_recording

    streams = sim_run.streams
    rec = simulated_recording(streams["time_s"], {k: v for k, v in streams.items() if k != "time_s"})
    table = dict(rec.table)
    table.update(truth_at(sim_run.truth, table["time_s"]))
    return table


def check_usable(sim_run: Any, table: Mapping[str, np.ndarray], what: str) -> None:
    """Refuse a run whose table (:func:`run_table`) is too short for any use (fewer than
    :data:`~virtsensor.recordings.check.MIN_ROWS` rows, which every reader refuses): a run that
    ended early after a usable stretch passes (its outcome says it was cut short).

    Raises:
        UserError: ``<what>: the run STOPPED after N sample(s) ...: <why>; nothing written``, the why
            from the outcome and the car's truth (e.g. inputs that never move the car).
    """
    n = len(table["time_s"])
    if n >= MIN_ROWS:
        return
    from sim.engine import ABORT_SIDESLIP_RAD, ABORT_SPEED_MPS

    outcome = sim_run.outcome
    status = str(outcome.get("status", "completed"))
    vx = np.asarray(sim_run.truth.get("vx_true_mps", []), dtype=np.float64)
    top = float(np.nanmax(vx)) if vx.size else float("nan")
    why = {
        "stopped": f"the car never reached {ABORT_SPEED_MPS:g} m/s (at most {top:.1f} m/s): its inputs never move "
                   "it" if top < ABORT_SPEED_MPS else f"the car slowed below {ABORT_SPEED_MPS:g} m/s at once",
        "spun": f"the car spun at once (side-slip beyond {np.rad2deg(ABORT_SIDESLIP_RAD):.0f} deg)",
        "off-track": "the car left the track at once",
    }.get(status, "the run is shorter than one 20 Hz tick")
    span = f" ({outcome['at_s']:.2f} s of {outcome['planned_s']:.2f} s planned)" if "at_s" in outcome else ""
    raise UserError(f"{what}: the run {status.upper()} after {n} sample(s) at 20 Hz{span}: {why}; nothing written "
                    f"(a table needs at least {MIN_ROWS} rows)")


def write_run_file(sim_run: Any, path: Path, table: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Write a simulated run to ``path`` as it is, in the format of its suffix (not
    atomic: on failure the file may be partial; the caller owns the name). Returns
    the run's canonical table (``table``, when the caller has it from :func:`run_table`).

    Raises:
        ValueError: a suffix that is neither a table nor a CAN log.
    """
    from virtsensor.recordings.canlog import write_csv, write_log

    path = Path(path)
    fmt = path.suffix.lower()
    if fmt not in TABLE_SUFFIXES + LOG_SUFFIXES:
        raise ValueError(f"{path}: unknown format {fmt!r}; use one of {', '.join(TABLE_SUFFIXES + LOG_SUFFIXES)}")
    table = dict(table) if table is not None else run_table(sim_run)
    if fmt in TABLE_SUFFIXES:
        write_csv(path, table)
    else:
        streams = sim_run.streams
        write_log(path, streams["time_s"], {k: v for k, v in streams.items() if k != "time_s"})
    return table


def partial_name(out: Path) -> Path:
    """The temporary name ``out`` is written under before it is complete
    (``.partial-<name>`` beside it: hidden, never read as a recording)."""
    return out.with_name(f".partial-{out.name}")


def write_run(sim_run: Any, out: Path, table: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Write a simulated run to ``out`` (.csv table or CAN log, by suffix) atomically:
    it is written under :func:`partial_name` and renamed when complete; on any
    failure no file is left behind. Returns the run's canonical table (``table``, when the
    caller has it from :func:`run_table`)."""
    out = Path(out)
    tmp = partial_name(out)
    try:
        table = write_run_file(sim_run, tmp, table)
        tmp.replace(out)
    except OSError as exc:
        name_the_file(exc, out)  # (a full disk names no file: the line the command prints says which)
        raise
    finally:
        tmp.unlink(missing_ok=True)
    return table


def metadata_path(out: Path) -> Path:
    """Where :func:`write_metadata` writes the metadata of the run written to ``out``: ``<out stem>.json``."""
    return Path(out).with_suffix(".json")


def metadata_entry(sim_run: Any, out: Path, table: Mapping[str, Any]) -> dict[str, Any]:
    """The metadata of the run written to ``out`` (request, outcome, plan label, samples, duration): what
    :func:`write_metadata` writes."""
    from sim.campaign import manifest_entry

    t = table["time_s"]
    return manifest_entry(sim_run, out, samples=len(t), duration_s=float(t[-1] - t[0]) if len(t) else 0.0)


def write_metadata(sim_run: Any, out: Path, table: Mapping[str, Any]) -> None:
    """Write the run's metadata (:func:`metadata_entry`) as JSON beside it (:func:`metadata_path`), atomically.

    Raises:
        UserError: the file cannot be written (the run's file ``out`` is then removed too: no run without
            its metadata).
    """
    entry = metadata_entry(sim_run, out, table)
    meta = metadata_path(out)
    try:
        write_json(meta, entry)
    except OSError as exc:
        out.unlink(missing_ok=True)
        raise UserError(f"{meta}: cannot write the run's metadata: {exc.strerror or exc}") from None
