"""A campaign directory: its manifest, written last, and its in-progress marker.

A campaign (``virtsensor campaign``) writes, in this order:

1. the marker :data:`MARKER` (hidden), saying a campaign is under way, how many
   runs it plans and in which format;
2. each run under a hidden ``.partial-*`` name, renamed to its final name by the
   campaign's own process once every run is complete;
3. its provenance :data:`PROVENANCE` (hidden: written by a campaign, which
   preset, how many runs), then the manifest :data:`MANIFEST` (atomically),
   listing every run with its file name, its number of table rows and the
   sha256 of its bytes;
4. then it removes the marker.

So a directory with a marker and no manifest holds a campaign that did not
complete (stopped, killed, crashed); a directory with a manifest holds exactly
the manifest's runs, each of which can be checked, and its manifest agrees with
the campaign's own totals (its ``samples``, the provenance's run count: a run
removed from it by hand is seen); a directory with the provenance and no
manifest holds a campaign whose manifest was lost, whose runs cannot be
checked (:func:`unverifiable_campaign`). A directory with none
of these files is a plain directory of recordings. Readers apply these rules
through :func:`listed_runs` and :func:`check_rows`; every violation is a
:class:`~virtsensor.errors.UserError` naming the file.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from virtsensor.errors import UserError

MANIFEST = "manifest.json"
MARKER = ".campaign-incomplete.json"
#: hidden file a complete campaign leaves beside its manifest: the directory was written by a campaign
PROVENANCE = ".campaign.json"
#: keys every run entry of a manifest carries (besides its metadata)
ENTRY_KEYS = ("file", "rows", "sha256")


def is_hidden(path: Path) -> bool:
    """Hidden files (``.name``, so also every ``.partial-*`` file) are never recordings."""
    return path.name.startswith(".")


def file_sha256(path: Path) -> str:
    """sha256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def start_marker(directory: Path, info: Mapping[str, Any]) -> Path:
    """Write the in-progress marker of a campaign starting in ``directory`` (``info``:
    preset, planned run count, format...)."""
    path = Path(directory) / MARKER
    path.write_text(json.dumps({**info, "pid": os.getpid()}))
    return path


def write_manifest(directory: Path, manifest: Mapping[str, Any]) -> Path:
    """Write a campaign's manifest atomically, then remove the marker: the campaign
    is complete. ``manifest["runs"]`` entries must carry :data:`ENTRY_KEYS`."""
    directory = Path(directory)
    for entry in manifest["runs"]:
        missing = [k for k in ENTRY_KEYS if k not in entry]
        if missing:
            raise ValueError(f"manifest entry {entry.get('file')!r} lacks {', '.join(missing)}")
    (directory / PROVENANCE).write_text(json.dumps({
        "written_by": "virtsensor campaign", "preset": manifest.get("preset"), "runs": len(manifest["runs"]),
        "manifest": MANIFEST}, indent=1) + "\n")
    path = directory / MANIFEST
    tmp = directory / f".partial-{MANIFEST}"
    try:
        tmp.write_text(json.dumps(manifest, indent=1))
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    (directory / MARKER).unlink(missing_ok=True)
    return path


def _visible_files(directory: Path) -> list[Path]:
    return sorted(f for f in directory.iterdir() if not is_hidden(f) and f.is_file())


def incomplete_campaign(directory: Path) -> str | None:
    """Why ``directory`` holds an unfinished campaign (marker, no manifest), or None."""
    directory = Path(directory)
    marker = directory / MARKER
    if not marker.exists() or (directory / MANIFEST).exists():
        return None
    from virtsensor.fileio import read_json  # (here: fileio imports numpy, which listing recordings need not)

    try:  # (what the marker says only details the refusal: a marker that says nothing readable details none)
        info = read_json(marker, "campaign marker")
        planned = f" of {int(info['runs'])}"
        preset = f" {info['preset']!r}"
    except (UserError, ValueError, KeyError, TypeError, OverflowError):
        planned, preset = "", ""
    done = len(_visible_files(directory))
    return (f"{directory}: campaign{preset} did not complete: no {MANIFEST}, {done}{planned} runs written "
            f"(it was stopped or killed); delete the directory and run the campaign again")


def unverifiable_campaign(directory: Path) -> str | None:
    """Why ``directory`` holds a campaign's runs that cannot be checked (its provenance, no manifest), or None."""
    directory = Path(directory)
    if not (directory / PROVENANCE).exists() or (directory / MANIFEST).exists():
        return None
    return (f"{directory}: written by a campaign ({PROVENANCE}) but its {MANIFEST} is missing, so its runs "
            f"cannot be verified (rows, sha256); restore the manifest or run the campaign again")


def _read_manifest(path: Path) -> list[dict[str, Any]]:
    """The run entries of the manifest ``path``, each checked (:data:`ENTRY_KEYS`, types, plain unique names),
    and the manifest checked against the campaign's other records (:func:`_check_records`)."""
    from virtsensor.fileio import read_json  # (here: see incomplete_campaign)

    doc = read_json(path, "campaign manifest")
    runs = doc.get("runs") if isinstance(doc, dict) else None
    if not isinstance(runs, list) or not all(isinstance(r, dict) for r in runs):
        raise UserError(f"{path}: not a campaign manifest (a JSON object whose 'runs' is a list of objects)")
    seen: set[str] = set()
    for i, r in enumerate(runs):
        missing = [k for k in ENTRY_KEYS if k not in r]
        if missing:
            raise UserError(f"{path}: run {i} ({r.get('file', '?')}) lacks {', '.join(missing)} (a manifest of an "
                            f"older version or written by hand); run the campaign again")
        if not isinstance(r["rows"], int) or isinstance(r["rows"], bool) or r["rows"] < 0:
            raise UserError(f"{path}: run {i} ({r['file']}): rows {r['rows']!r} is not a count of rows")
        if not isinstance(r["sha256"], str):
            raise UserError(f"{path}: run {i} ({r['file']}): sha256 {r['sha256']!r} is not a hex digest")
        name = r["file"]
        if not isinstance(name, str) or Path(name).name != name or name.startswith("."):
            raise UserError(f"{path}: run {i}: {name!r} is not a plain, visible file name")
        if name in seen:
            raise UserError(f"{path}: run {name} is listed twice")
        seen.add(name)
    _check_records(path, doc, runs)
    return runs


def _check_records(path: Path, doc: Mapping[str, Any], runs: Sequence[Mapping[str, Any]]) -> None:
    """Refuse a manifest (``path``, its object ``doc``, its checked ``runs``) that the campaign's own records
    contradict, as a run removed from it by hand leaves it:

    * its ``"samples"`` must be the sum of its entries' ``rows`` (every campaign that writes ``rows`` writes
      it; a manifest without it, written by another tool, is not checked for it);
    * the provenance :data:`PROVENANCE` beside it, when there is one, must be a JSON object whose ``"runs"``
      is the number of its entries (campaigns older than the provenance leave none: not checked).

    Raises:
        UserError: one line naming the directory (or the provenance) and the disagreement.
    """
    directory = path.parent
    rows = sum(int(r["rows"]) for r in runs)
    if "samples" in doc:
        samples = doc["samples"]
        if not isinstance(samples, int) or isinstance(samples, bool):
            raise UserError(f"{path}: samples is not a count of rows (a {type(samples).__name__})")
        if samples != rows:
            raise UserError(f"{directory}: {MANIFEST} says {samples} samples but its {len(runs)} runs list {rows} "
                            f"rows: it was changed after the campaign wrote it; run the campaign again")
    provenance = directory / PROVENANCE
    if not provenance.exists():
        return
    from virtsensor.fileio import read_json  # (here: see incomplete_campaign)

    info = read_json(provenance, "campaign provenance")
    planned = info.get("runs") if isinstance(info, dict) else None
    if not isinstance(planned, int) or isinstance(planned, bool):
        raise UserError(f"{provenance}: not a campaign provenance (a JSON object whose 'runs' counts the runs)")
    if planned != len(runs):
        raise UserError(f"{directory}: {MANIFEST} lists {len(runs)} runs but {PROVENANCE} says the campaign "
                        f"wrote {planned}: the manifest was changed after the campaign wrote it; run the "
                        f"campaign again")


def listed_runs(directory: Path, only: Sequence[Path] | None = None) -> list[tuple[Path, dict[str, Any]]]:
    """The runs of a campaign directory, each with its manifest entry, after checking
    that the directory holds exactly them and that every file's sha256 matches.

    Args:
        directory: holds :data:`MANIFEST`.
        only: check and return just these files of the directory (each must be listed).

    Raises:
        UserError: a listed run missing, a file not listed, a sha256 mismatch, a
            malformed manifest, a manifest its campaign's totals contradict
            (:func:`_check_records`); the message names the file.
    """
    directory = Path(directory)
    manifest = directory / MANIFEST
    entries = {r["file"]: r for r in _read_manifest(manifest)}
    if only is None:
        for f in _visible_files(directory):
            if f.name != MANIFEST and f.name not in entries:
                raise UserError(f"{f}: not listed in {manifest}; a campaign directory holds exactly its "
                                f"manifest's runs (move the file elsewhere)")
        names = list(entries)
    else:
        names = [Path(f).name for f in only]
        for name in names:
            if name not in entries:
                raise UserError(f"{directory / name}: not listed in {manifest}, which lists this directory's runs")
    out = []
    for name in names:
        path, entry = directory / name, entries[name]
        if not path.is_file():
            raise UserError(f"{path}: listed in {manifest} but missing")
        digest = file_sha256(path)
        if digest != entry["sha256"]:
            raise UserError(f"{path}: sha256 {digest[:16]}... differs from the {entry['sha256'][:16]}... in "
                            f"{manifest}: the file changed after the campaign wrote it")
        out.append((path, entry))
    return out


def check_rows(path: Path, entry: Mapping[str, Any], rows: int) -> None:
    """Refuse a run whose table does not have the rows its manifest entry lists."""
    if int(entry["rows"]) != rows:
        raise UserError(f"{path}: {rows} rows read, its manifest lists {int(entry['rows'])}")
