"""argparse ``type=`` helpers shared by every subcommand: a mistake is caught while parsing, before any work.

Each helper returns a callable for ``add_argument(type=...)``. It converts the text or raises
``argparse.ArgumentTypeError`` with one line naming what is wrong (argparse prefixes the option, and
the CLI exits 2). Paths are checked for their *kind* (existing file, existing directory, writable
output file or directory) and never read beyond what the check needs; messages name the path and
never quote a file's content.

Each callable carries ``fuzz_valid`` and ``fuzz_invalid``: example argument texts that it must
accept and refuse (``{tmp}`` stands for a scratch directory prepared by the command-line fuzz test,
holding ``file.txt``, ``binary.bin``, ``dir/`` and ``ro/``), so the fuzz test draws values from each
option's own type and its neighbours.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")
ArgType = Callable[[str], Any]

#: Upper bound of seeds: numpy's legacy seeding and many tools take 32-bit unsigned seeds.
SEED_MAX = 2**32 - 1
#: Bytes a text-file check reads (the whole file when smaller).
TEXT_PROBE_BYTES = 1 << 20

_NONFINITE = ("nan", "inf", "-inf", "1e999")
_NOT_NUMBER = ("", "x", "1..2", "0x")


def _tag(fn: Callable[[str], T], name: str, valid: Sequence[str], invalid: Sequence[str]) -> Callable[[str], T]:
    fn.__name__ = name  # argparse names the type in some of its own messages
    fn.fuzz_valid = tuple(valid)  # type: ignore[attr-defined]
    fn.fuzz_invalid = tuple(invalid)  # type: ignore[attr-defined]
    return fn


def _bounds(lo: int | None, hi: int | None) -> str:
    if lo is not None and hi is not None:
        return f"{lo} to {hi}"
    return f">= {lo}" if lo is not None else f"<= {hi}"


# ---------------------------------------------------------------------------------------------------------------
# numbers
# ---------------------------------------------------------------------------------------------------------------
def int_range(lo: int | None = None, hi: int | None = None, *, also: Sequence[int] = ()) -> ArgType:
    """An integer in ``[lo, hi]`` (either bound may be open-ended), or one of ``also`` (e.g. -1 = all cores)."""
    extra = f" (or {', '.join(map(str, also))})" if also else ""

    def parse(text: str) -> int:
        try:
            v = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if v in also or ((lo is None or v >= lo) and (hi is None or v <= hi)):
            return v
        raise argparse.ArgumentTypeError(f"{v} is out of range: {_bounds(lo, hi)}{extra}")

    valid = [str(x) for x in (lo, hi, *also) if x is not None] or ["0"]
    invalid = [*_NOT_NUMBER, "1.5", "nan", "1e3"]
    invalid += [str(lo - 1), str(-(10**40))] if lo is not None and lo - 1 not in also else []
    invalid += [str(min(also) - 1)] if also else []
    invalid += [str(hi + 1), str(10**40)] if hi is not None else []
    return _tag(parse, "integer", valid, invalid)


def positive_int(hi: int | None = None) -> ArgType:
    """An integer >= 1 (and <= ``hi``)."""
    return int_range(1, hi)


def non_negative_int(hi: int | None = None) -> ArgType:
    """An integer >= 0 (and <= ``hi``)."""
    return int_range(0, hi)


def seed() -> ArgType:
    """A random seed: an integer 0 to 2**32-1."""
    return int_range(0, SEED_MAX)


def jobs(hi: int = 1024) -> ArgType:
    """Parallel workers: -1 (all cores) or 1 to ``hi``."""
    return int_range(1, hi, also=(-1,))


def float_range(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                hi_open: bool = False) -> ArgType:
    """A finite number in ``[lo, hi]`` (``lo_open``/``hi_open`` exclude the bound); NaN and infinities refused."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        ok = math.isfinite(v)
        if ok and lo is not None:
            ok = v > lo if lo_open else v >= lo
        if ok and hi is not None:
            ok = v < hi if hi_open else v <= hi
        if not ok:
            lo_s = "" if lo is None else f"{'>' if lo_open else '>='} {lo:g}"
            hi_s = "" if hi is None else f"{'<' if hi_open else '<='} {hi:g}"
            raise argparse.ArgumentTypeError(f"{text} is out of range: a finite number "
                                              f"{' and '.join(s for s in (lo_s, hi_s) if s)}".rstrip())
        return v

    valid = [repr(float(x)) for x in (lo, hi) if x is not None
             and not ((x == lo and lo_open) or (x == hi and hi_open))] or ["1.0"]
    if lo is not None and hi is not None:
        valid.append(repr((lo + hi) / 2))
    invalid = [*_NOT_NUMBER, *_NONFINITE]
    invalid += [repr(lo)] if lo is not None and lo_open else []
    invalid += [repr(lo - max(1.0, abs(lo))), "-1e300"] if lo is not None else []
    invalid += [repr(hi)] if hi is not None and hi_open else []
    invalid += [repr(hi + max(1.0, abs(hi))), "1e300"] if hi is not None else []
    return _tag(parse, "number", valid, invalid)


def positive_float(hi: float | None = None) -> ArgType:
    """A finite number > 0 (and <= ``hi``)."""
    return float_range(0.0, hi, lo_open=True)


def rate(lo: float = 1e-3, hi: float = 1e3) -> ArgType:
    """A playback speed factor in ``[lo, hi]`` (1.0 = real time) or ``max``: returns a float or ``"max"``."""
    number = float_range(lo, hi)

    def parse(text: str) -> float | str:
        if text.strip().lower() == "max":
            return "max"
        try:
            return number(text)
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"{text!r} is not 'max' nor a speed factor from {lo:g} to {hi:g}") \
                from None

    return _tag(parse, "rate", ["max", "1.0", repr(lo), repr(hi)],
                ["0", "-1", "1e-300", "1e300", *_NONFINITE, "", "fast"])


def can_id() -> ArgType:
    """An 11-bit CAN identifier, decimal or 0x-hex: 0 to 0x7FF."""

    def parse(text: str) -> int:
        try:
            v = int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a CAN id: {text!r} (e.g. 0x7F0)") from None
        if not 0 <= v <= 0x7FF:
            raise argparse.ArgumentTypeError(f"{text} is not an 11-bit CAN id (0x000..0x7FF)")
        return v

    return _tag(parse, "CAN id", ["0x7F0", "0", "2047"], ["0x800", "-1", "x", "", "1e3", str(10**40)])


def tyre_spec(*, axles: bool = True) -> ArgType:
    """``[front=|rear=]TYRE`` (``axles``) or ``TYRE``: a tyre file or a bundled tyre's name.

    Only the form is checked here (an axle prefix, a non-empty name); the file itself is read and
    validated before any work starts (:func:`virtsensor.tyres.check_tyre_file`)."""

    def parse(text: str) -> str:
        axle, sep, name = text.partition("=") if axles else ("", "", text)
        if sep and axle not in ("front", "rear"):
            raise argparse.ArgumentTypeError(f"{text!r}: the axle before '=' is front or rear")
        if not (name if sep else text).strip():
            raise argparse.ArgumentTypeError(f"{text!r}: no tyre file or name given")
        return text

    if not axles:
        return _tag(parse, "tyre", ["mf61_255_55R20"], ["", "/no/such/tyre.tir", "{tmp}/secret.txt"])
    return _tag(parse, "tyre", ["mf61_255_55R20", "front=mf61_255_55R20", "rear=c_segment_205_55R16"],
                ["", "front=", "left=x.tir", "/no/such/tyre.tir", "rear=/no/such.tir"])


def track_spec() -> ArgType:
    """A circuit: a bundled circuit's name, ``random:SEED``, or a centreline file (.csv/.geojson).

    Only the form is checked here (a name, or a path with one of those suffixes); the circuit itself is
    loaded and checked before any work starts (:func:`sim.track.load_track`)."""

    def parse(text: str) -> str:
        if not text.strip():
            raise argparse.ArgumentTypeError("no circuit given")
        suffix = Path(text).suffix.lower()
        if suffix and suffix not in (".csv", ".geojson", ".json"):
            raise argparse.ArgumentTypeError(f"{text}: a circuit is a name or a .csv/.geojson centreline")
        return text

    return _tag(parse, "circuit", ["zandvoort", "random:3"],
                ["", "{tmp}/secret.txt", "/no/such/track.csv", "nowhere", "random:x"])


# ---------------------------------------------------------------------------------------------------------------
# paths
#
# A path's *kind* (exists, is a file or a directory, is writable) is checked after parsing, before the
# command runs (:func:`check_paths`, called by :func:`virtsensor.cli.main`), then its suffix: at parse
# time only that it is not empty, so that a documented command line parses on a machine without its files.
# ---------------------------------------------------------------------------------------------------------------
def _path_tag(check: Callable[[str], str], name: str, valid: Sequence[str], invalid: Sequence[str]) -> ArgType:
    def parse(text: str) -> str:
        if not text:
            raise argparse.ArgumentTypeError(f"empty {name} name")
        return text

    parse.check_path = check  # type: ignore[attr-defined]
    return _tag(parse, name, valid, invalid)


def check_paths(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Check the kind of every path argument of ``parser`` parsed into ``args`` (defaults included).

    Raises:
        UserError: ``argument --opt: <path>: <what is wrong>`` for the first wrong one.
    """
    from virtsensor.errors import UserError

    for action in parser._actions:
        check = getattr(action.type, "check_path", None)
        value = getattr(args, action.dest, None)
        if check is None or value is None:
            continue
        for v in value if isinstance(value, list) else [value]:
            try:
                check(v)
            except argparse.ArgumentTypeError as exc:
                name = "/".join(action.option_strings) or action.metavar or action.dest
                raise UserError(f"argument {name}: {exc}") from None
def _suffix_ok(p: Path, suffixes: Sequence[str]) -> None:
    if suffixes and p.suffix.lower() not in suffixes:
        raise argparse.ArgumentTypeError(f"{p}: expected a {' or '.join(suffixes)} file")


def existing_file(*suffixes: str, what: str = "file") -> ArgType:
    """A path to an existing regular file (with one of ``suffixes`` when given); returns the text.

    ``what`` names the kind in the messages, e.g. ``log file``: ``x.blf: no such log file``.
    """

    def check(text: str) -> str:
        p = Path(text)
        if not text:
            raise argparse.ArgumentTypeError("empty file name")
        if p.is_dir():
            raise argparse.ArgumentTypeError(f"{p}: is a directory, a {what} is expected")
        if not p.exists():
            raise argparse.ArgumentTypeError(f"{p}: no such {what}")
        if not p.is_file():
            raise argparse.ArgumentTypeError(f"{p}: not a regular file")
        if not os.access(p, os.R_OK):
            raise argparse.ArgumentTypeError(f"{p}: not readable")
        _suffix_ok(p, suffixes)
        return text

    valid = [f"{{tmp}}/file{suffixes[0]}" if suffixes else "{tmp}/file.txt"]
    invalid = ["{tmp}/missing", "{tmp}/dir", "", "{tmp}/file.txt/x", f"{{tmp}}/dir{suffixes[0] if suffixes else ''}"]
    return _path_tag(check, "file", valid, invalid)


def text_file(*suffixes: str) -> ArgType:
    """An existing regular file holding UTF-8 text (no NUL byte in its first MiB): configuration files."""
    base = existing_file(*suffixes)

    def check(text: str) -> str:
        base.check_path(text)  # type: ignore[attr-defined]
        try:
            with open(text, "rb") as f:
                head = f.read(TEXT_PROBE_BYTES)
        except OSError as exc:
            raise argparse.ArgumentTypeError(f"{text}: cannot read it: {exc.strerror or exc}") from None
        try:
            head.decode("utf-8")
        except UnicodeDecodeError as exc:
            if exc.start < len(head) - 3:  # not merely a multi-byte character cut at the probe's end
                raise argparse.ArgumentTypeError(f"{text}: not a text file (not UTF-8)") from None
        if b"\0" in head:
            raise argparse.ArgumentTypeError(f"{text}: not a text file (binary content)")
        return text

    valid = base.fuzz_valid  # type: ignore[attr-defined]
    return _path_tag(check, "text file", valid, [*base.fuzz_invalid, "{tmp}/binary.bin"])  # type: ignore[attr-defined]


def existing_dir() -> ArgType:
    """A path to an existing, readable directory; returns the text."""

    def check(text: str) -> str:
        p = Path(text)
        if not text:
            raise argparse.ArgumentTypeError("empty directory name")
        if not p.exists():
            raise argparse.ArgumentTypeError(f"{p}: no such directory")
        if not p.is_dir():
            raise argparse.ArgumentTypeError(f"{p}: not a directory")
        if not os.access(p, os.R_OK | os.X_OK):
            raise argparse.ArgumentTypeError(f"{p}: directory not readable")
        return text

    return _path_tag(check, "directory", ["{tmp}/dir"], ["{tmp}/missing", "{tmp}/file.txt", ""])


def existing_path() -> ArgType:
    """An existing regular file or directory (inputs given as files or directories of them)."""

    def check(text: str) -> str:
        p = Path(text)
        if not text:
            raise argparse.ArgumentTypeError("empty path")
        if not p.exists():
            raise argparse.ArgumentTypeError(f"{p}: no such file or directory")
        if not (p.is_file() or p.is_dir()):
            raise argparse.ArgumentTypeError(f"{p}: neither a regular file nor a directory")
        if not os.access(p, os.R_OK):
            raise argparse.ArgumentTypeError(f"{p}: not readable")
        return text

    return _path_tag(check, "path", ["{tmp}/dir"], ["{tmp}/missing", "", "{tmp}/file.txt/x"])


def _writable_dir(d: Path, path: Path) -> None:
    """``d`` (``path`` itself or its directory) must be a writable directory; messages name ``path``."""
    same = d == path
    if not d.exists():
        raise argparse.ArgumentTypeError(f"{path}: directory {d} does not exist")
    if not d.is_dir():
        raise argparse.ArgumentTypeError(f"{path}: not a directory" if same else f"{path}: {d} is not a directory")
    if not os.access(d, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{path}: directory not writable" if same else
                                          f"{path}: directory {d} is not writable")


def _nearest_existing(p: Path) -> Path:
    p = p.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def output_file(*suffixes: str, mkdirs: bool = False) -> ArgType:
    """A file the command will write: not a directory, an existing file must be writable, and its
    directory must exist and be writable (``mkdirs``: the nearest existing ancestor instead, the
    command creating the rest). Nothing is created here."""

    def check(text: str) -> str:
        p = Path(text)
        if not text:
            raise argparse.ArgumentTypeError("empty file name")
        if p.is_dir():
            raise argparse.ArgumentTypeError(f"{p}: is a directory, an output file name is expected")
        if p.exists() and not p.is_file():
            raise argparse.ArgumentTypeError(f"{p}: exists and is not a regular file")
        if p.exists() and not os.access(p, os.W_OK):
            raise argparse.ArgumentTypeError(f"{p}: exists and is not writable")
        _suffix_ok(p, suffixes)
        _writable_dir(_nearest_existing(p.parent) if mkdirs else p.parent, p)
        return text

    name = f"out{suffixes[0] if suffixes else '.txt'}"
    invalid = ["{tmp}/dir", f"{{tmp}}/dir{suffixes[0] if suffixes else ''}", f"{{tmp}}/ro/{name}",
               f"{{tmp}}/file.txt/{name}", ""]
    if not mkdirs:
        invalid.append(f"{{tmp}}/missing/{name}")
    if suffixes:
        invalid.append("{tmp}/out.wrongsuffix")
    return _path_tag(check, "output file", [f"{{tmp}}/{name}"], invalid)


def output_file_or_stdout(*suffixes: str) -> ArgType:
    """``-`` (standard output) or an :func:`output_file`."""
    inner = output_file(*suffixes)

    def check(text: str) -> str:
        return text if text == "-" else inner.check_path(text)  # type: ignore[attr-defined]

    return _path_tag(check, "output file or -", ["-", *inner.fuzz_valid],  # type: ignore[attr-defined]
                     inner.fuzz_invalid)  # type: ignore[attr-defined]


def output_dir(*, empty: bool = False) -> ArgType:
    """A directory the command will write into: an existing one must be a writable directory (and
    empty when ``empty``); a new one needs a writable nearest existing ancestor. Nothing is created here."""

    def check(text: str) -> str:
        p = Path(text)
        if not text:
            raise argparse.ArgumentTypeError("empty directory name")
        if p.exists():
            _writable_dir(p, p)
            if empty and any(p.iterdir()):
                raise argparse.ArgumentTypeError(f"{p}: directory is not empty")
        else:
            _writable_dir(_nearest_existing(p), p)
        return text

    return _path_tag(check, "output directory", ["{tmp}/newdir"],
                ["{tmp}/file.txt", "{tmp}/ro", "{tmp}/ro/sub", "{tmp}/file.txt/sub", ""])
