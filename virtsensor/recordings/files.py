"""Which files are recordings, and reading one into its 20 Hz table whatever its format.

A recording is a canonical CSV table (``.csv``), a CAN log (``.blf``, ``.asc``,
``.log``, ``.trc``) or an MDF4 file (``.mf4``, ``.mdf``). Hidden files, and so
every ``.partial-*`` file (a write not yet complete), are never recordings.

A directory is read as follows:

* with a campaign's in-progress marker and no manifest: refused (the campaign
  did not complete);
* with a campaign's provenance and no manifest: refused (its runs cannot be
  checked);
* with a manifest: exactly the manifest's runs, each present, none extra, each
  file's sha256 as listed (:func:`virtsensor.recordings.manifest.listed_runs`);
* otherwise: its visible files with a recording suffix, in name order (an entry
  with such a suffix that is no regular file, a link to nothing say, is refused:
  a run it seems to hold and does not; so is a folder in it that holds recordings
  or a campaign's manifest: folders are not read, and its runs would be left out
  without a word).

A file given by name whose directory holds a manifest must be one of its runs,
with its listed sha256.

A symbolic link (given by name, or found in a directory) is judged also by
its target (``Path.resolve``): the target must not be hidden (so no
``.partial-*`` write), its directory must pass the checks above, and a target
in a campaign directory must be one of its manifest's runs with its listed
sha256. A link cannot make a run of an unfinished campaign, or of a staging
leftover, look like a plain recording.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from virtsensor.errors import UserError
from virtsensor.recordings.manifest import MANIFEST, incomplete_campaign, is_hidden, listed_runs, unverifiable_campaign

if TYPE_CHECKING:  # numpy only in annotations: the suffixes stay cheap to import (``--help``)
    import numpy as np

#: A recording with one of these suffixes is the canonical 20 Hz CSV table.
TABLE_SUFFIXES: tuple[str, ...] = (".csv",)
#: ... a CAN log (python-can's formats; read through the DBC, and written by ``simulate`` and ``campaign``).
LOG_SUFFIXES: tuple[str, ...] = (".blf", ".asc", ".log", ".trc")
#: ... an MDF4 file (the ``mdf`` extra).
MDF_SUFFIXES: tuple[str, ...] = (".mf4", ".mdf")
#: Every suffix a recording may have (lower case); a text CAN log may also be gzip-compressed (``.asc.gz``:
#: :func:`recording_kind`).
SUFFIXES = TABLE_SUFFIXES + LOG_SUFFIXES + MDF_SUFFIXES
#: CAN log formats that python-can reads gzip-compressed too (``<name>.asc.gz``), as ``replay`` and ``demo`` do
GZ_LOG_SUFFIXES: tuple[str, ...] = (".asc", ".log", ".trc", ".csv")
#: What ``simulate`` and ``campaign`` write a run as (suffix without the dot): the table or a CAN log.
WRITE_FORMATS: tuple[str, ...] = tuple(s[1:] for s in TABLE_SUFFIXES + LOG_SUFFIXES)


@dataclass(frozen=True)
class Source:
    """A recording file and, when it belongs to a campaign, its manifest entry."""

    path: Path
    entry: dict[str, Any] | None = None


def recording_kind(path: Path) -> str:
    """The suffix that says how a recording is read (lower case): its last one, or for a gzip-compressed text CAN
    log (``run.asc.gz``) the one before ``.gz``; ``""`` without one."""
    sfx = [x.lower() for x in Path(path).suffixes]
    if len(sfx) >= 2 and sfx[-1] == ".gz" and sfx[-2] in GZ_LOG_SUFFIXES:
        return sfx[-2]
    return sfx[-1] if sfx else ""


def _unsupported(path: Path) -> UserError:
    return UserError(f"{path}: unsupported file type {path.suffix or '(none)'!r} "
                     f"(a recording is one of {', '.join(SUFFIXES)}; {', '.join(GZ_LOG_SUFFIXES)} also "
                     "gzip-compressed, ending in .gz)")


def _check_campaign(d: Path) -> None:
    """Refuse a campaign directory that did not complete or lost its manifest."""
    why = incomplete_campaign(d) or unverifiable_campaign(d)
    if why:
        raise UserError(why)


def _hidden(p: Path) -> str:
    """What the hidden file ``p`` is, never a recording."""
    kind = "an unfinished write ('.partial-*')" if p.name.startswith(".partial-") else "a hidden file"
    return f"{kind}, never a recording"


def _as_campaign_run(p: Path) -> Source:
    """``p`` (not hidden, with a recording suffix) judged by its directory: refused when the directory is an
    incomplete or unverifiable campaign, with its manifest entry when the directory is a campaign's."""
    _check_campaign(p.parent)
    if (p.parent / MANIFEST).exists():
        ((_, entry),) = listed_runs(p.parent, only=[p])
        return Source(p, entry)
    return Source(p)


def _linked(link: Path, entry: dict[str, Any] | None) -> Source:
    """The recording a symbolic link names (which passed its own directory's checks, with ``entry`` when that
    is a campaign's), judged by its target too (module docstring). The source keeps the link's name (as the
    user gave it) and ``entry``, else the target's manifest entry.

    Raises:
        UserError: ``{link} -> {target}: {why}``: the target is hidden, or fails its directory's checks.
    """
    target = link.resolve()
    if is_hidden(target):
        raise UserError(f"{link} -> {target}: {_hidden(target)}")
    try:
        theirs = _as_campaign_run(target).entry
    except UserError as exc:
        raise UserError(f"{link} -> {target}: {exc}") from None
    return Source(link, entry if entry is not None else theirs)


def _directory(d: Path) -> list[Source]:
    _check_campaign(d)
    if (d / MANIFEST).exists():
        out = []
        for path, entry in listed_runs(d):
            if recording_kind(path) not in SUFFIXES:
                raise _unsupported(path)
            out.append(_linked(path, entry) if path.is_symlink() else Source(path, entry))
        if not out:
            raise UserError(f"{d / MANIFEST}: lists no runs")
        return out
    for sub in sorted(e for e in d.iterdir() if not is_hidden(e) and e.is_dir()):
        if _holds_recordings(sub):
            raise UserError(f"{sub}: a folder of recordings inside {d}, whose folders are not read: give it too, or "
                            "move it out")
    found = sorted(f for f in d.iterdir() if not is_hidden(f) and recording_kind(f) in SUFFIXES)
    for f in found:
        if not f.is_file():  # (a run the directory seems to hold and does not: never skipped without a word)
            what = (f"a link to nothing ({f.readlink()}): the run it named is gone" if f.is_symlink() and
                    not f.exists() else "not a regular file")
            raise UserError(f"{f}: {what}")
    if not found:
        raise UserError(f"{d}: no recordings ({', '.join(SUFFIXES)}) in this directory")
    return [_linked(f, None) if f.is_symlink() else Source(f) for f in found]


def _holds_recordings(folder: Path) -> bool:
    """Whether ``folder`` holds a campaign's manifest or a visible file with a recording suffix; a folder that
    cannot be read (a root-only ``lost+found`` on a data stick) holds none that could be read either."""
    try:
        return (folder / MANIFEST).exists() or any(
            not is_hidden(f) and recording_kind(f) in SUFFIXES for f in folder.iterdir())
    except OSError:
        return False


def _file(p: Path) -> Source:
    if is_hidden(p):
        raise UserError(f"{p}: {_hidden(p)}")
    if recording_kind(p) not in SUFFIXES:
        raise _unsupported(p)
    source = _as_campaign_run(p)
    return _linked(p, source.entry) if p.is_symlink() else source


def recording_files(paths: Iterable[Path | str]) -> list[Source]:
    """The recordings named by ``paths`` (files, or directories of them; see the module docstring).

    Raises:
        UserError: a missing path, an unsupported or hidden file, an incomplete or
            inconsistent campaign directory, or a file given twice.
    """
    out: list[Source] = []
    for p in map(Path, paths):
        if p.is_dir():
            out.extend(_directory(p))
        elif p.is_file():
            out.append(_file(p))
        else:
            raise UserError(f"{p}: no such file or directory")
    seen: set[Path] = set()
    for s in out:
        key = s.path.resolve()
        if key in seen:
            raise UserError(f"{s.path}: given twice (a run must count once)")
        seen.add(key)
    return out


def read_table(path: Path) -> dict[str, np.ndarray]:
    """A recording's 20 Hz table (``time_s`` in s, then catalogue columns), by suffix:
    CSV as written, a CAN log decoded through the DBC by the runtime's front-end,
    an MDF4 file sampled on the ticks (:func:`virtsensor.recordings.mdf.read_mdf`).

    A run read with its own metadata beside it (``<stem>.json`` whose ``file`` is its name, as ``simulate``
    writes it) must have the rows that metadata lists as ``samples``
    (:func:`virtsensor.recordings.sidecar.check_samples`): a CSV, ``.log`` or ``.trc`` cut at a line boundary
    shows no cut in itself. A run without such metadata (a measured run, a campaign's run: its manifest lists
    its rows) is read as it is.

    Raises:
        UserError: an unreadable, malformed or truncated file, or rows other than its metadata's samples,
            naming it.
    """
    from virtsensor.recordings.canlog import read_csv, read_log
    from virtsensor.recordings.check import is_can_csv
    from virtsensor.recordings.sidecar import check_samples

    path = Path(path)
    suffix = recording_kind(path)
    if suffix not in SUFFIXES:
        raise _unsupported(path)
    try:
        if path.suffix.lower() == ".gz" or (suffix in TABLE_SUFFIXES and is_can_csv(path)):  # (CAN logs)
            table = dict(read_log(path).table)
        elif suffix in TABLE_SUFFIXES:
            table = read_csv(path)
        elif suffix in MDF_SUFFIXES:
            from virtsensor.recordings.mdf import read_mdf

            table = read_mdf(path)
        else:
            table = dict(read_log(path).table)
    except PermissionError as exc:  # (a file of a directory given as --data: as one given itself, exit 2)
        raise UserError(f"{path}: not readable ({exc.strerror})") from None
    if "time_s" in table:  # (a table without time is the input check's to refuse, naming the column)
        check_samples(path, len(table["time_s"]))
    return table

