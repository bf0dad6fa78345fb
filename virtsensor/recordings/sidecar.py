"""A recording's metadata sidecar: the JSON ``<stem>.json`` beside it, and whose it is.

``simulate`` writes each run with its metadata beside it (:func:`virtsensor.recordings.simulated.write_metadata`):
a JSON object whose ``file`` is the run's file name, with its conditions (``mu``...) and its ``samples`` (rows of
its 20 Hz table). Other JSON files may share a run's stem: a test engineer's conditions (``{"mu": 0.5}``, no
``file``, :mod:`virtsensor.diagnose.conditions`), the bundled demo recordings' descriptions (no ``file``), the
output of an earlier ``score --json``, or the metadata of *another* run copied or renamed beside this one.

Every reader decides whose a ``<stem>.json`` is through :func:`sidecar_of`, by its ``file`` field alone:

* it names the recording (:attr:`Sidecar.matches`): the run's own metadata. Its ``samples`` is the run's row
  count, checked by :func:`check_samples` wherever the run's table is read
  (:func:`virtsensor.recordings.files.read_table`): a run file cut at a line boundary (CSV, ``.log``, ``.trc``
  have no trailer to show it) is refused; a symbolic link is checked against its target's own metadata too;
* it names another file (:attr:`Sidecar.foreign`): the metadata of another run. It is **ignored**, never
  refused: every command that reads it (``demo``, ``diagnose``) also works on a run without metadata (a
  measured run has none), so it works on this run as on one without, and says in its output and its JSON that it
  ignored that file (:attr:`Sidecar.note`); nothing from it (conditions, description, row count) is used;
* it names no file (an object without ``file``): no run's metadata, nor another run's; readers that take
  conditions or a description from such a file (``diagnose``, ``demo``) keep doing so, no row count is checked.

A file that is absent, not a regular file, larger than :data:`MAX_BYTES`, unreadable, not UTF-8, not JSON (or
nested too deep to parse) or not a JSON object is no sidecar (:attr:`Sidecar.doc` is None), with one exception:
one whose text names the recording as its ``"file"`` is the run's own metadata, cut or damaged, and
:func:`check_samples` refuses the run (its rows cannot be checked). Otherwise this module never raises for it (a
reader that needs the file, such as ``diagnose``'s conditions, reports it itself).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from virtsensor.errors import UserError

#: A sidecar larger than this is not read (a run's metadata is a few hundred bytes).
MAX_BYTES = 1 << 20


def sidecar_path(recording: Path | str) -> Path:
    """Where the metadata of ``recording`` is: ``<stem>.json`` beside it."""
    return Path(recording).with_suffix(".json")


def read_json_object(path: Path) -> dict[str, Any] | None:
    """The JSON object in ``path`` (read by :func:`virtsensor.fileio.read_json`), or None when it is not one
    (see the module docstring); never raises."""
    from virtsensor.fileio import read_json

    try:
        if not path.is_file() or path.stat().st_size > MAX_BYTES:
            return None
        doc = read_json(path, "metadata")
    except (OSError, UserError):  # (unreadable, not UTF-8, not JSON, nested too deeply: no sidecar)
        return None
    return doc if isinstance(doc, dict) else None


@dataclass(frozen=True)
class Sidecar:
    """The ``<stem>.json`` beside a recording and whose it is (see the module docstring).

    Attributes:
        recording: the recording file.
        path: the sidecar's path (``<stem>.json``; it may not exist).
        doc: its JSON object, None when there is none (absent, unreadable, not an object).
    """

    recording: Path
    path: Path
    doc: dict[str, Any] | None

    @property
    def matches(self) -> bool:
        """Whether it is the recording's own metadata: its ``file`` is the recording's name."""
        return self.doc is not None and self.doc.get("file") == self.recording.name

    @property
    def foreign(self) -> bool:
        """Whether it is the metadata of another file: it has a ``file`` that is not the recording's name."""
        return self.doc is not None and "file" in self.doc and not self.matches

    @property
    def usable(self) -> dict[str, Any] | None:
        """What a reader may take from it: its object unless it is :attr:`foreign` (None then, and when none)."""
        return None if self.doc is None or self.foreign else self.doc

    @property
    def note(self) -> str | None:
        """One line saying it was ignored, when :attr:`foreign` (the line the commands print and write), else
        None."""
        if not self.foreign or self.doc is None:
            return None
        return (f"{self.path} ignored: its \"file\" is {self.doc.get('file')!r}, not {self.recording.name}, so it is "
                f"the metadata of another run")


def sidecar_of(recording: Path | str, meta: Path | str | None = None) -> Sidecar:
    """The sidecar of ``recording``: ``meta``, default :func:`sidecar_path` (never the recording itself)."""
    recording = Path(recording)
    path = Path(meta) if meta is not None else sidecar_path(recording)
    return Sidecar(recording, path, None if path == recording else read_json_object(path))


def metadata_with_samples(recording: Path | str) -> list[Sidecar]:
    """The metadata that lists the rows of ``recording`` (:attr:`Sidecar.matches` and has ``samples``): its own
    and, when ``recording`` is a symbolic link, its target's own too (a link is judged by its target: a link to
    a cut run is the cut run)."""
    return [sc for sc in _own_and_target(Path(recording)) if _lists_samples(sc)]


def _own_and_target(recording: Path) -> list[Sidecar]:
    """The sidecars of ``recording`` and, when it is a symbolic link, of its target (each read once)."""
    files = [recording, recording.resolve()] if recording.is_symlink() else [recording]
    return [sidecar_of(f) for f in files]


def _lists_samples(sc: Sidecar) -> bool:
    return sc.matches and sc.doc is not None and "samples" in sc.doc


def check_samples(recording: Path | str, rows: int) -> None:
    """Refuse a run whose table has not the rows its own metadata lists (:func:`metadata_with_samples`, its
    ``samples``): the file was cut or changed after it was written. A run without its own metadata, or whose
    metadata lists no ``samples``, is not checked here.

    Raises:
        UserError: ``<file>: N rows read, its metadata <stem>.json lists M samples ...`` (a link's target's:
            ``<link> -> <target>: ...``), or the metadata's ``samples`` is not a count of rows.
    """
    recording = Path(recording)
    sidecars = _own_and_target(recording)
    if _damaged(sidecars[0]):
        raise UserError(f"{sidecars[0].path}: the metadata of {recording.name} is not a JSON object (cut or damaged), "
                        "so its rows cannot be checked; write it again (virtsensor simulate) or remove it")
    for sc in filter(_lists_samples, sidecars):
        listed = sc.doc["samples"] if sc.doc is not None else None
        if not isinstance(listed, int) or isinstance(listed, bool) or listed < 0:
            raise UserError(f"{sc.path}: samples {listed!r} is not a count of rows (the metadata of "
                            f"{sc.recording.name})")
        if listed != rows:
            shown = recording if sc.recording == recording else f"{recording} -> {sc.recording}"
            raise UserError(f"{shown}: {rows} rows read, its metadata {sc.path.name} lists {listed} samples: the "
                            f"file was cut or changed after it was written")


def _damaged(sc: Sidecar) -> bool:
    """Whether ``sc`` is the recording's own metadata, cut or damaged: a file that is no sidecar (:attr:`Sidecar.doc`
    None: not a JSON object) yet names the recording as its ``"file"`` in its text (the first field ``simulate``
    writes). A file nested deeper than Python parses is well-formed: not damaged. Read only when ``doc`` is None."""
    import json
    import re

    path = sc.path
    try:
        if sc.doc is not None or path == sc.recording or not path.is_file() or path.stat().st_size > MAX_BYTES:
            return False
        raw = path.read_bytes()
    except OSError:
        return False
    try:
        json.loads(raw.decode("utf-8"))
    except RecursionError:  # (well-formed, only nested deeper than Python parses: no sidecar)
        return False
    except ValueError:  # (JSONDecodeError, UnicodeDecodeError: cut or damaged)
        pass
    name = re.escape(json.dumps(sc.recording.name).encode("utf-8"))  # (as the metadata writer spells it)
    return re.search(rb'"file"\s*:\s*' + name, raw) is not None
