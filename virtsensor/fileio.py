"""Writing files safely and JSON the way every command writes it.

Contracts:
* :func:`atomic_write` / :func:`atomic_write_bytes`: a reader sees the old file or the new one, never half
  of one; on any failure no partial file is left (the temporary name starts with ``.partial-``, which no
  reader of recordings ever takes for a run). The file is made readable by all (0644) and the rename is
  made durable (``fsync`` of the file and its folder, POSIX).
* :func:`staged_files`: a command's several output files written all or none: each into a ``.partial-``
  file beside it, renamed into place only when every one is written; on a failure or an interrupt while
  writing no target is touched (a rename that fails part way, rarer, leaves the ones renamed so far).
* :func:`staged_dir`: the files of a directory written all or none: into a ``.partial-`` directory beside
  it, moved into place only when every one is written; on a failure or an interrupt while writing the target is
  as it was (a move that fails part way, rarer, leaves the files moved so far).
* :func:`json_safe`: the same object with non-finite floats as ``None`` (JSON has no NaN/inf), numpy
  scalars and arrays as Python numbers and lists, paths as strings, sets as sorted lists, mapping keys as
  strings.
* :func:`read_json`: the JSON value in a file the program reads (a manifest, a marker, a run's metadata, a
  conditions file), every way it can fail (unreadable, not UTF-8, not JSON, nested too deeply, a number too
  long) one :class:`~virtsensor.errors.UserError` naming the file, never quoting its content.
* :func:`json_default`: the ``default=`` hook of ``json.dumps`` for writers that refuse non-finite floats
  instead (``allow_nan=False``): the same conversions, ``TypeError`` for any other type.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import uuid
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import interrupt
from virtsensor.errors import UserError

__all__ = ["PARTIAL_PREFIX", "atomic_write", "atomic_write_bytes", "check_writable", "dumps", "json_default",
           "json_safe", "name_the_file", "read_json", "read_user_text", "staged_dir", "staged_files", "write_json",
           "write_texts"]

#: Prefix of the temporary file of an atomic write (readers of recordings skip such files).
PARTIAL_PREFIX = ".partial-"


def read_user_text(path: str | os.PathLike[str], what: str) -> str:
    """The UTF-8 text of a file the user names (``what``: e.g. ``"config file"``, ``"model card"``).

    Raises:
        UserError: ``cannot read {what} {path}: {reason}`` (missing, a directory, no permission...) or
            ``{what} {path} is not UTF-8 text``; the message never quotes the file's content.
    """
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise UserError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise UserError(f"{what} {path} is not UTF-8 text") from None


def read_json(path: str | os.PathLike[str], what: str) -> Any:
    """The JSON value in the file ``path`` (``what``: e.g. ``"campaign manifest"``), whatever the value is (the
    caller checks its shape).

    Raises:
        UserError: the only error, naming ``path`` and never quoting its content: the file cannot be read or is
            not UTF-8 (:func:`read_user_text`), ``{path}:{line}: {what} is not valid JSON: ...``,
            ``{path}: {what} is nested too deeply`` (``RecursionError`` of the parser), or ``{path}: {what} is
            not JSON that can be read: ...`` (any other ``ValueError`` of the parser, e.g. an integer longer than
            Python reads).
    """
    text = read_user_text(path, what)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}:{exc.lineno}: {what} is not valid JSON: {exc.msg}") from None
    except RecursionError:
        raise UserError(f"{path}: {what} is nested too deeply") from None
    except ValueError as exc:  # (e.g. an integer of more digits than int() converts)
        raise UserError(f"{path}: {what} is not JSON that can be read: {exc}") from None


def json_safe(obj: Any) -> Any:
    """``obj`` made JSON-serialisable without loss of meaning (see the module contract)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        return json_safe(obj.item())
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (set, frozenset)):
        return [json_safe(v) for v in sorted(obj)]
    return obj


def json_default(obj: Any) -> Any:
    """``default=`` of ``json.dumps``: numpy arrays and scalars, paths and sets as JSON values (no NaN check:
    pair it with ``allow_nan=False``). Raises ``TypeError`` naming any other type."""
    if isinstance(obj, (np.ndarray, np.generic)):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"a value of type {type(obj).__name__} is not JSON-serialisable")


def dumps(obj: Any, *, indent: int | None = 2, compact: bool = False) -> str:
    """``json.dumps`` of :func:`json_safe` (``compact``: no spaces, one line, for logs)."""
    if compact:
        return json.dumps(json_safe(obj), separators=(",", ":"), allow_nan=False)
    return json.dumps(json_safe(obj), indent=indent, allow_nan=False)


def _fsync_dir(folder: Path) -> None:
    if hasattr(os, "O_DIRECTORY"):
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write(path: str | os.PathLike[str], write: Callable[[Path], object]) -> None:
    """Call ``write(tmp)`` to fill a temporary file beside ``path`` (same suffix), then rename it over ``path``.

    The temporary file keeps ``path``'s suffix, so writers that choose the format by suffix (python-can's
    loggers) write the right one. Raises whatever ``write`` or the file system raises (an ``OSError`` without a
    file name, a full disk say, or naming the temporary file, as one naming ``path``); nothing is left behind.
    One output of :func:`staged_files`.
    """
    with staged_files(path) as (tmp,):
        assert tmp is not None
        write(tmp)


#: the longest file name (bytes) the temporary files are made to fit (Linux, macOS, Windows file systems)
NAME_MAX = 255


def _temp_beside(target: Path) -> Path:
    """A new empty file beside ``target``: ``.partial-<stem>.<8 random characters><suffix>``, the stem shortened
    so that the name fits :data:`NAME_MAX` (a target whose own name fits can always be staged).

    Raises:
        OSError: it cannot be created (no such folder, no permission, a full disk), naming ``target``.
    """
    room = NAME_MAX - len(PARTIAL_PREFIX) - len(os.fsencode(target.suffix)) - 9  # (".", the 8 random characters)
    stem = os.fsencode(target.stem)[:max(room, 0)].decode("utf-8", "ignore")
    try:
        fd, name = tempfile.mkstemp(dir=target.parent, prefix=f"{PARTIAL_PREFIX}{stem}.", suffix=target.suffix)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(target)) from exc
    os.close(fd)
    return Path(name)


def name_the_file(exc: BaseException, path: Path | str) -> None:
    """Raise an ``OSError`` that names no file (a full disk, an I/O error on write) again as one naming ``path``,
    so the one line the command prints says where; any other exception: return."""
    if isinstance(exc, OSError) and not exc.filename and exc.errno is not None:
        raise OSError(exc.errno, exc.strerror, str(path)) from exc


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_write`)."""
    atomic_write(path, lambda tmp: tmp.write_bytes(data))


def write_json(path: str | os.PathLike[str], obj: Any) -> None:
    """Write ``obj`` as indented JSON (:func:`json_safe`) with a final newline, atomically."""
    atomic_write_bytes(path, (dumps(obj) + "\n").encode())


@contextmanager
def staged_files(*paths: str | os.PathLike[str] | None) -> Iterator[list[Path | None]]:
    """Yield, per path (None stays None), a new empty temporary file beside it (``.partial-`` name, the same
    suffix: writers that choose the format by suffix write the right one) to write that output into; when the
    block ends without an error, every temporary file is made readable by all (0644), synced and renamed over
    its target, then the folders synced; a temporary file the block removed is not (that output is not written,
    its target untouched). On an exception or an interrupt in the block every temporary file is
    removed and no target is touched (an existing one keeps its content). A rename that fails part way leaves
    the outputs renamed so far in place.

    Raises:
        OSError: a temporary file cannot be created, synced or renamed; an ``OSError`` of the block that names a
            temporary file (or one a writer made beside it) is raised again naming its target, one naming no
            file (a full disk) naming the targets (whatever else the block raises passes through unchanged).
    """
    targets = [None if p is None else Path(p) for p in paths]
    temps: list[Path | None] = []
    try:
        for t in targets:
            if t is None:
                temps.append(None)
                continue
            temps.append(_temp_beside(t))
        yield temps
        interrupt.check()  # (a Ctrl-C some library swallowed: nothing is put in place after it)
        temps = [None if tmp is None or not tmp.exists() else tmp for tmp in temps]  # (removed: not written)
        for tmp in temps:
            if tmp is not None:
                with open(tmp, "rb+") as f:
                    os.fsync(f.fileno())
                os.chmod(tmp, 0o644)
        for tmp, t in zip(temps, targets, strict=True):
            if tmp is not None and t is not None:
                os.replace(tmp, t)
    except BaseException as exc:
        for tmp in temps:
            if tmp is not None:
                tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and isinstance(exc.filename, (str, bytes)) and exc.filename \
                and exc.errno is not None:  # (a file descriptor's error has a number for its file name)
            name = Path(os.fsdecode(exc.filename)).name
            for tmp, t in zip(temps, targets, strict=False):
                if tmp is not None and t is not None and tmp.stem in name:  # (the temporary file, or a writer's own)
                    raise OSError(exc.errno, exc.strerror, str(t)) from exc
        name_the_file(exc, ", ".join(str(t) for t in targets if t is not None))
        raise
    for folder in {t.parent for t in targets if t is not None}:
        _fsync_dir(folder)


def write_texts(*outputs: tuple[str | os.PathLike[str] | None, str]) -> None:
    """Write each ``(path, text)`` (UTF-8; a None path: skipped), all or none (:func:`staged_files`)."""
    with staged_files(*(p for p, _ in outputs)) as temps:
        for tmp, (_, text) in zip(temps, outputs, strict=True):
            if tmp is not None:
                tmp.write_text(text, encoding="utf-8")


def _staging_parent(out: Path) -> Path:
    """Where the staging directory of ``out`` goes: beside it (its nearest existing ancestor when its parent is
    to be created), or inside an existing ``out`` whose parent is not writable."""
    parent = next(a for a in (out.parent, *out.parent.parents) if a.exists())
    if out.is_dir() and not os.access(parent, os.W_OK | os.X_OK):
        return out
    return parent


@contextmanager
def staged_dir(out: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a new empty directory to write the files of ``out`` into; when the block ends without an error,
    move them into place: a new ``out`` (and its missing parents) is the staging directory renamed, an existing
    one receives each file under its name (replacing a file of that name; any other content untouched).

    The staging directory is ``.partial-<name>.<random>`` beside ``out`` (hidden: never read as a recording).
    On an exception or an interrupt (``BaseException``) in the block it is removed and ``out`` is left exactly as
    it was; so is an existing ``out`` where one of the new files' names is taken by a directory (checked before
    anything moves). A move that fails part way for another reason (the disk, permissions changed meanwhile)
    leaves the files moved so far in place.

    Raises:
        OSError: the staging directory cannot be created, a name in ``out`` is taken by a directory, or the move
            fails (whatever the block raises passes through unchanged).
    """
    out = Path(out)
    stage = _staging_parent(out) / f"{PARTIAL_PREFIX}{out.name}.{uuid.uuid4().hex[:12]}"
    stage.mkdir()  # the mode follows the umask, as a directory made by mkdir
    try:
        yield stage
        interrupt.check()
        if out.is_dir():
            entries = sorted(stage.iterdir())
            taken = [e.name for e in entries if (out / e.name).is_dir() and not (out / e.name).is_symlink()]
            if taken:
                raise IsADirectoryError(f"{out / taken[0]}: is a directory, cannot put the new file there")
            for entry in entries:
                os.replace(entry, out / entry.name)
            stage.rmdir()
        else:
            out.parent.mkdir(parents=True, exist_ok=True)
            stage.rename(out)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise


def check_writable(path: str | os.PathLike[str], option: str) -> None:
    """Refuse an output file that cannot be written, before any work is spent on it; leaves nothing behind.

    Missing folders are fine (the writer creates them) when the nearest existing one is a writable folder;
    an existing parent folder is tried with a temporary file (which is removed at once).

    Raises:
        UserError: ``"<option>: ..."``: ``path`` is a folder, or its folder is not one or is not writable.
    """
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{option}: {path} is a directory, give a file name")
    parent = path.parent
    folder = next(a for a in (parent, *parent.parents) if a.exists())  # "." or "/" at the latest
    if not folder.is_dir():
        raise UserError(f"{option}: cannot write {path}: {folder} is not a directory")
    try:
        if folder == parent:
            fd, tmp = tempfile.mkstemp(dir=parent, prefix=f"{PARTIAL_PREFIX}{path.stem}.", suffix=path.suffix)
            os.close(fd)
            os.unlink(tmp)
        elif not os.access(folder, os.W_OK | os.X_OK):
            raise PermissionError(13, f"{folder} is not writable")
    except OSError as exc:
        raise UserError(f"{option}: cannot write {path}: {exc.strerror or exc}") from None
