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

    def slots(text: str) -> list[tuple[Path, str]]:  # an input when it names a file (not a bundled tyre)
        name = text.partition("=")[2] if axles and "=" in text else text
        return [(Path(name), "")] if Path(name).is_file() else []

    _with_role(parse, INPUT, slots)
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

    _with_role(parse, INPUT, lambda text: [(Path(text), "")] if Path(text).is_file() else [])
    return _tag(parse, "circuit", ["zandvoort", "random:3"],
                ["", "{tmp}/secret.txt", "/no/such/track.csv", "nowhere", "random:x"])


# ---------------------------------------------------------------------------------------------------------------
# paths
#
# A path's *kind* (exists, is a file or a directory, is writable) is checked after parsing, before the
# command runs (:func:`check_paths`, called by :func:`virtsensor.cli.main`), then its suffix: at parse
# time only that it is not empty, so that a documented command line parses on a machine without its files.
# ---------------------------------------------------------------------------------------------------------------
def _path_tag(check: Callable[[str], str], name: str, valid: Sequence[str], invalid: Sequence[str], *,
              role: str, slots: Slots | None = None, is_dir: bool = False,
              implicit: Callable[[], Path] | None = None) -> ArgType:
    """A path type: ``check`` is its kind (run by :func:`check_paths`); ``role`` is :data:`INPUT` or :data:`OUTPUT`;
    ``slots`` lists the files a value stands for (default: the path itself); ``is_dir``: an output directory;
    ``implicit``: the file the command reads when the option is not given (e.g. the shipped model)."""
    def parse(text: str) -> str:
        if not text:
            raise argparse.ArgumentTypeError(f"empty {name} name")
        return text

    parse.check_path = check  # type: ignore[attr-defined]
    _with_role(parse, role, slots or _plain_slots, is_dir=is_dir, implicit=implicit)
    return _tag(parse, name, valid, invalid)


# ---------------------------------------------------------------------------------------------------------------
# inputs and outputs
#
# Every path argument is an input (read by the command) or an output (written by it). After the kinds,
# :func:`check_paths` compares the resolved files of both sides, the files that come with each included (a
# model's card, a recording's metadata sidecar, what an output writes beside itself): an output must not be an
# input, lie inside an input directory, be the file of another output or lie inside an output directory.
# ---------------------------------------------------------------------------------------------------------------
#: roles of a path argument
INPUT, OUTPUT = "input", "output"
#: ``text -> [(file, label)]``: the files one argument value stands for; the label names a file that is not
#: the value itself (e.g. ``"the model card of"``), "" for the value itself
Slots = Callable[[str], list[tuple[Path, str]]]


def _with_role(fn: Callable[[str], Any], role: str, slots: Slots, *, is_dir: bool = False,
               implicit: Callable[[], Path] | None = None) -> None:
    fn.path_role = role  # type: ignore[attr-defined]
    fn.path_slots = slots  # type: ignore[attr-defined]
    fn.path_is_dir = is_dir  # type: ignore[attr-defined]
    fn.path_implicit = implicit  # type: ignore[attr-defined]


def _plain_slots(text: str) -> list[tuple[Path, str]]:
    return [(Path(text), "")]


def input_slots(text: str) -> list[tuple[Path, str]]:
    """The files an input path is read with: itself; for a model (``.onnx``) its card
    (:func:`virtsensor.model.card_path_for`); for a recording file its metadata sidecar ``<stem>.json`` when
    there is one (read by ``demo`` and ``diagnose``): a JSON object whose ``file`` names the recording, as
    ``simulate`` writes it (:attr:`virtsensor.recordings.sidecar.Sidecar.matches`, the one test of whose a
    ``<stem>.json`` is). Any other ``<stem>.json`` (say the output of an earlier ``score --json``) is no
    input, so running a command twice is not refused."""
    from virtsensor.recordings.files import SUFFIXES
    from virtsensor.recordings.sidecar import sidecar_of, sidecar_path

    p = Path(text)
    out = [(p, "")]
    suffix = p.suffix.lower()
    if suffix == ".onnx":
        out.append((_card_path(p), "the model card of"))
    elif suffix in SUFFIXES and sidecar_of(p).matches:
        out.append((sidecar_path(p), "the metadata of"))
    return out


def _card_path(p: Path) -> Path:
    from virtsensor.model.card import card_path_for

    return card_path_for(p)


def output_slots(companions: Callable[[Path], Sequence[Path]] | None = None, *, model: bool = False) -> Slots:
    """The files an output path is written as: itself, the model card beside a model (``model``), and
    ``companions(path)`` (e.g. a simulated run's metadata)."""
    def slots(text: str) -> list[tuple[Path, str]]:
        if text == "-":  # standard output
            return []
        p = Path(text)
        out = [(p, "")]
        if model:
            out.append((_card_path(p), "the model card of"))
        out += [(c, "written with") for c in (companions(p) if companions is not None else ())]
        return out

    return slots


class _Slot:
    """One file an argument stands for: its resolved path, whether it is a directory, and how to name it."""

    def __init__(self, option: str, text: str, path: Path, label: str, is_dir: bool) -> None:
        self.path = Path(os.path.realpath(path))
        self.is_dir = is_dir
        #: written beside the argument's own file (a model card, a run's metadata), not named by the user
        self.companion = bool(label)
        self.name = f"{option} {text}" if not label else f"{path} ({label} {option} {text})"

    def same(self, other: _Slot) -> bool:
        if self.path == other.path:
            return True
        try:
            return self.path.exists() and other.path.exists() and os.path.samefile(self.path, other.path)
        except OSError:
            return False

    def inside(self, other: _Slot) -> bool:
        return other.is_dir and other.path in self.path.parents


def _slots(action: argparse.Action, values: Sequence[str]) -> list[_Slot]:
    """The files the values of a path argument stand for (the implicit default when none is given)."""
    from virtsensor.errors import UserError

    t = action.type
    option = "/".join(action.option_strings) or action.metavar or action.dest
    if not values and getattr(t, "path_implicit", None) is not None:
        try:
            values, option = [str(t.path_implicit())], f"{option} (default)"  # type: ignore[union-attr]
        except UserError:  # a broken install: the command says so itself
            return []
    out = []
    for v in values:
        for path, label in t.path_slots(v):  # type: ignore[union-attr]
            is_dir = t.path_is_dir if not label else False  # type: ignore[union-attr]
            out.append(_Slot(option, v, path, label, is_dir or (not label and Path(v).is_dir())))
    return out


def path_clash(inputs: Sequence[_Slot], outputs: Sequence[_Slot]) -> str | None:
    """Why these outputs cannot be written (one line), or None: an output is an input, lies inside an input
    directory, is another output's file or lies inside an output directory."""
    for k, o in enumerate(outputs):
        for i in inputs:
            if o.same(i):
                return f"{o.name} would overwrite {i.name}, an input of this command"
            if o.inside(i):
                return f"{o.name} lies inside {i.name}, an input directory of this command"
        for other in outputs[:k]:
            if o.same(other):
                return f"{o.name} and {other.name} are the same file: each output needs its own"
            if o.inside(other) or other.inside(o):
                inner, outer = (o, other) if o.inside(other) else (other, o)
                return f"{inner.name} lies inside {outer.name}, an output directory of this command"
    return None


def check_paths(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Check every path argument of ``parser`` parsed into ``args`` (defaults included): its kind (the type's
    ``check_path``), then that no output (with what it writes beside itself) is an input (with the card or
    metadata read with it), lies inside an input directory, is another output's file or lies inside an output
    directory (:func:`path_clash`). Nothing is read beyond what these checks need; nothing is written.

    Raises:
        UserError: ``argument --opt: <path>: <what is wrong>`` for the first wrong kind, else one line naming
            the two arguments that clash.
    """
    from virtsensor.errors import UserError

    inputs: list[_Slot] = []
    outputs: list[_Slot] = []
    for action in parser._actions:
        value = getattr(args, action.dest, None)
        values = [] if value is None else value if isinstance(value, list) else [value]
        check = getattr(action.type, "check_path", None)
        for v in values if check is not None else ():
            try:
                check(v)
            except argparse.ArgumentTypeError as exc:
                name = "/".join(action.option_strings) or action.metavar or action.dest
                raise UserError(f"argument {name}: {exc}") from None
        role = getattr(action.type, "path_role", None)
        if role is not None:
            (inputs if role == INPUT else outputs).extend(_slots(action, values))
    problem = path_clash(inputs, outputs) or next(filter(None, map(_companion_problem, outputs)), None)
    if problem:
        raise UserError(problem)


def _companion_problem(slot: _Slot) -> str | None:
    """Why a file an output writes beside itself (a model card, a run's metadata) cannot be written there, or None:
    checked with the output's own file, before any work, so that neither is touched when the other cannot be."""
    p = slot.path
    if not slot.companion or not p.exists():
        return None
    if p.is_dir():
        return f"{slot.name} is a directory: the file cannot be written there; move it or choose another output name"
    if not p.is_file():
        return f"{slot.name} exists and is not a regular file"
    if not os.access(p, os.W_OK):
        return f"{slot.name} exists and is not writable"
    return None


def _suffix_ok(p: Path, suffixes: Sequence[str]) -> None:
    if suffixes and p.suffix.lower() not in suffixes:
        raise argparse.ArgumentTypeError(f"{p}: expected a {' or '.join(suffixes)} file")


def existing_file(*suffixes: str, what: str = "file", implicit: Callable[[], Path] | None = None) -> ArgType:
    """An input: a path to an existing regular file (with one of ``suffixes`` when given); returns the text.

    ``what`` names the kind in the messages, e.g. ``log file``: ``x.blf: no such log file``. ``implicit``: the
    file the command reads when the option is not given (outputs must not overwrite it either).
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
    return _path_tag(check, "file", valid, invalid, role=INPUT, slots=input_slots, implicit=implicit)


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
    return _path_tag(check, "text file", valid, [*base.fuzz_invalid, "{tmp}/binary.bin"],  # type: ignore[attr-defined]
                     role=INPUT, slots=input_slots)


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

    return _path_tag(check, "directory", ["{tmp}/dir"], ["{tmp}/missing", "{tmp}/file.txt", ""], role=INPUT)


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

    return _path_tag(check, "path", ["{tmp}/dir"], ["{tmp}/missing", "", "{tmp}/file.txt/x"], role=INPUT,
                     slots=input_slots)


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


def output_file(*suffixes: str, mkdirs: bool = False,
                companions: Callable[[Path], Sequence[Path]] | None = None) -> ArgType:
    """An output: a file the command will write: not a directory, an existing file must be writable, and its
    directory must exist and be writable (``mkdirs``: the nearest existing ancestor instead, the
    command creating the rest). Nothing is created here. A model (``.onnx`` among ``suffixes``) is written
    with its card; ``companions(path)``: the other files the command writes beside it."""

    def check(text: str) -> str:
        p = Path(text)
        if not text:
            raise argparse.ArgumentTypeError("empty file name")
        if text == "-":  # (the usual spelling of standard output: never a file named '-' by surprise)
            raise argparse.ArgumentTypeError("'-' (standard output) is not taken here: give a file name")
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
               f"{{tmp}}/file.txt/{name}", "", "-"]
    if not mkdirs:
        invalid.append(f"{{tmp}}/missing/{name}")
    if suffixes:
        invalid.append("{tmp}/out.wrongsuffix")
    return _path_tag(check, "output file", [f"{{tmp}}/{name}"], invalid, role=OUTPUT,
                     slots=output_slots(companions, model=".onnx" in suffixes))


def output_file_or_stdout(*suffixes: str) -> ArgType:
    """``-`` (standard output) or an :func:`output_file`."""
    inner = output_file(*suffixes)

    def check(text: str) -> str:
        return text if text == "-" else inner.check_path(text)  # type: ignore[attr-defined]

    return _path_tag(check, "output file or -", ["-", *inner.fuzz_valid],  # type: ignore[attr-defined]
                     [v for v in inner.fuzz_invalid if v != "-"],  # type: ignore[attr-defined]
                     role=OUTPUT, slots=output_slots())


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
                     ["{tmp}/file.txt", "{tmp}/ro", "{tmp}/ro/sub", "{tmp}/file.txt/sub", ""], role=OUTPUT, is_dir=True)
