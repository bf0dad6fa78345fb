"""Reader for TNO ``.tir`` tyre property files (MF-Tyre / Magic Formula 6.x).

File format (as written by MF-Tyre, MFeval, Adams and most fitting tools)::

    $ a comment line                  (also lines starting with ``!``)
    [SECTION_NAME]
    KEY = 1.234        $ trailing comment
    NAME = 'a string'  $ strings are quoted with ' or "
    [SHAPE]            $ sections may hold a table instead of KEY = value lines
    {radial width}     $ ... announced by a ``{column names}`` line
     1.0    0.0

Keys are case-insensitive and returned upper-case. Numbers may use a Fortran
``D`` exponent (``1.0D-3``). Values of the ``[UNITS]`` section are kept apart in
:attr:`TirFile.units` (they would collide with e.g. ``[INERTIA] MASS``); only SI
files (meter, newton, radian, kg, second) are accepted, because the tyre model
does not convert units.

Every problem raises :class:`TirError` (a :class:`ValueError`) whose message
starts with ``<path>:<line>:`` so that it can be printed as is, e.g.
``tyre.tir:37: cannot parse value 'abc' for QDZ1``.

This module only reads the file; which coefficients a model needs, and the
defaults of the optional ones, are decided by the model (:mod:`sim.tyre`).
"""

from __future__ import annotations

import importlib.resources
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

__all__ = ["TirError", "TirFile", "read_tir", "parse_tir", "bundled_tir", "bundled_tyres", "require_keys",
           "standard_section"]

#: Sub-directory of the ``sim`` package that holds the bundled property files.
_BUNDLED_DIR = ("data", "tyres")

#: Keys whose value is a string even when the file leaves it unquoted.
_STRING_KEYS = frozenset(
    {
        "FILE_TYPE",
        "FILE_FORMAT",
        "TYRESIDE",
        "PROPERTY_FILE_FORMAT",
        "FUNCTION_NAME",
        "LENGTH",
        "FORCE",
        "ANGLE",
        "MASS",
        "TIME",
        "COMMENT",
    }
)

#: Accepted spellings of the SI units in ``[UNITS]`` (lower-case).
_SI_UNITS: dict[str, frozenset[str]] = {
    "LENGTH": frozenset({"meter", "meters", "metre", "metres", "m"}),
    "FORCE": frozenset({"newton", "newtons", "n"}),
    "ANGLE": frozenset({"radian", "radians", "rad"}),
    "MASS": frozenset({"kg", "kilogram", "kilograms"}),
    "TIME": frozenset({"second", "seconds", "sec", "s"}),
}

_KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_SECTION_RE = re.compile(r"^\[\s*([A-Za-z0-9_ ]+?)\s*\]$")
_FORTRAN_EXP_RE = re.compile(r"^([+-]?(?:\d+\.?\d*|\.\d+))[dD]([+-]?\d+)$")


class TirError(ValueError):
    """A ``.tir`` file (or a coefficient set) cannot be used.

    The message names the file, the line (when there is one) and what is wrong.
    """


class TirFile(dict[str, float | str]):
    """Content of a ``.tir`` file: a flat dict KEY (upper-case) -> float or str.

    All sections but ``[UNITS]`` are merged; when a key occurs in two different
    sections the later one wins. Extra attributes:

    * ``path``: the file that was read (``"<string>"`` for :func:`parse_tir` without a name);
    * ``sections``: KEY -> section it came from (upper-case, without brackets);
    * ``lines``: KEY -> 1-based line number it was read from;
    * ``units``: the ``[UNITS]`` entries (KEY -> str);
    * ``tables``: section -> rows of numbers, for table sections such as ``[SHAPE]``;
    * ``section_lines``: section -> 1-based line of its (first) header.
    """

    def __init__(
        self,
        path: str,
        params: Mapping[str, float | str],
        sections: Mapping[str, str] | None = None,
        lines: Mapping[str, int] | None = None,
        units: Mapping[str, str] | None = None,
        tables: Mapping[str, list[tuple[float, ...]]] | None = None,
        section_lines: Mapping[str, int] | None = None,
    ) -> None:
        super().__init__(params)
        self.path = path
        self.sections = dict(sections or {})
        self.lines = dict(lines or {})
        self.units = dict(units or {})
        self.tables = dict(tables or {})
        self.section_lines = dict(section_lines or {})

    @property
    def params(self) -> dict[str, float | str]:
        """The flat KEY -> value mapping (this object itself)."""
        return self

    def where(self, key: str) -> str:
        """``"<path>:<line>"`` of ``key`` (or just the path if the key is not in the file)."""
        line = self.lines.get(key.upper())
        return f"{self.path}:{line}" if line is not None else self.path


def _strip_comment(text: str) -> tuple[str, bool]:
    """Remove a trailing ``$``/``!`` comment outside quotes.

    Returns the text and whether every quote was closed.
    """
    quote: str | None = None
    for i, ch in enumerate(text):
        if quote is not None:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch in "$!":
            return text[:i], True
    return text, quote is None


def _parse_number(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        m = _FORTRAN_EXP_RE.match(text)
        if m:
            return float(f"{m.group(1)}e{m.group(2)}")
        return None


def parse_tir(text: str, path: str | Path = "<string>") -> TirFile:
    """Parse the text of a ``.tir`` file; ``path`` is only used in messages."""
    name = str(path)
    params: dict[str, float | str] = {}
    sections: dict[str, str] = {}
    lines: dict[str, int] = {}
    units: dict[str, str] = {}
    unit_lines: dict[str, int] = {}
    tables: dict[str, list[tuple[float, ...]]] = {}
    section_lines: dict[str, int] = {}
    seen_in_section: dict[tuple[str, str], int] = {}
    section = ""
    in_table = False

    for lineno, raw in enumerate(text.splitlines(), start=1):
        stripped = raw.strip()
        if not stripped or stripped[0] in "$!":
            continue
        body, closed = _strip_comment(stripped)
        body = body.strip()
        if not closed:
            raise TirError(f"{name}:{lineno}: unterminated quoted string")
        if not body:
            continue

        if body.startswith("["):
            m = _SECTION_RE.match(body)
            if m is None:
                raise TirError(f"{name}:{lineno}: malformed section header")
            section = m.group(1).upper().replace(" ", "_")
            section_lines.setdefault(section, lineno)
            in_table = False
            continue

        if body.startswith("{"):
            if not body.endswith("}"):
                raise TirError(f"{name}:{lineno}: malformed table header")
            in_table = True
            tables.setdefault(section, [])
            continue

        if "=" not in body:
            if in_table:
                row: list[float] = []
                for tok in body.split():
                    num = _parse_number(tok)
                    if num is None:
                        raise TirError(f"{name}:{lineno}: cannot parse a table value in [{section}]")
                    row.append(num)
                tables[section].append(tuple(row))
                continue
            raise TirError(f"{name}:{lineno}: expected 'KEY = value' (is this a tyre property file?)")

        key_text, _, value_text = body.partition("=")
        key = key_text.strip().upper()
        value_text = value_text.strip()
        if not _KEY_RE.match(key):
            raise TirError(f"{name}:{lineno}: invalid key name")
        if not value_text:
            raise TirError(f"{name}:{lineno}: missing value for {key}")

        value: float | str
        if value_text[0] in "'\"":
            q = value_text[0]
            if len(value_text) < 2 or value_text[-1] != q or q in value_text[1:-1]:
                raise TirError(f"{name}:{lineno}: cannot parse the value of {key}")
            value = value_text[1:-1]
        else:
            num = _parse_number(value_text)
            if num is not None:
                value = num
            elif (key in _STRING_KEYS or section in ("MDI_HEADER", "UNITS")) and " " not in value_text:
                value = value_text
            else:
                raise TirError(f"{name}:{lineno}: cannot parse the value of {key}")

        first = seen_in_section.get((section, key))
        if first is not None:
            raise TirError(f"{name}:{lineno}: duplicate key {key} in [{section}] (first on line {first})")
        seen_in_section[(section, key)] = lineno
        if section != "UNITS" and key in lines:
            raise TirError(f"{name}:{lineno}: key {key} in [{section}] is already set in [{sections[key]}] on line "
                           f"{lines[key]} (a coefficient has one value: which one is meant?)")

        if section == "UNITS":
            units[key] = str(value)
            unit_lines[key] = lineno
            continue
        params[key] = value
        sections[key] = section
        lines[key] = lineno

    for unit_key, value in units.items():
        allowed = _SI_UNITS.get(unit_key)
        if allowed is not None and value.strip().lower() not in allowed:
            raise TirError(
                f"{name}:{unit_lines[unit_key]}: unit {unit_key} is not supported "
                f"(only SI files: {', '.join(sorted(allowed))})"
            )

    return TirFile(path=name, params=params, sections=sections, lines=lines, units=units, tables=tables,
                   section_lines=section_lines)


def read_tir(path: str | Path) -> TirFile:
    """Read and parse a ``.tir`` file.

    Raises:
        TirError: the file cannot be read or is malformed (message names path and line).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError:
        text = p.read_text(encoding="latin-1")
    except OSError as exc:
        raise TirError(f"{p}: cannot read tyre property file: {exc.strerror or exc}") from exc
    return parse_tir(text, p)


def require_keys(
    params: TirFile | Mapping[str, object],
    keys: Iterable[str],
    source: str | None = None,
    what: str = "the tyre model",
) -> None:
    """Raise :class:`TirError` naming the missing ones of ``keys`` (and the file).

    For a :class:`TirFile` the message gives the line of the section the first
    missing key belongs in (MF-Tyre layout), when the file has that section.
    """
    values = params.params if isinstance(params, TirFile) else params
    if source is None:
        source = params.path if isinstance(params, TirFile) else "coefficient set"
    missing = [k for k in keys if k not in values]
    if missing:
        more = f" (also missing: {', '.join(missing[1:])})" if len(missing) > 1 else ""
        where, section = source, standard_section(missing[0])
        line = params.section_lines.get(section) if isinstance(params, TirFile) else None
        if line is not None:
            where = f"{source}:{line}"
            more = f" in [{section}]{more}"
        raise TirError(f"{where}: missing coefficient {missing[0]}{more}, needed by {what} (no default)")


#: Section of the MF-Tyre layout that holds a key (keys not listed: by their prefix, see standard_section).
_SECTION_OF: dict[str, str] = {
    "FITTYP": "MODEL", "LONGVL": "MODEL", "VXLOW": "MODEL", "UNLOADED_RADIUS": "DIMENSION",
    "INFLPRES": "OPERATING_CONDITIONS", "NOMPRES": "OPERATING_CONDITIONS", "FNOMIN": "VERTICAL",
    "VERTICAL_STIFFNESS": "VERTICAL", "LONGITUDINAL_STIFFNESS": "STRUCTURAL", "LATERAL_STIFFNESS": "STRUCTURAL",
}


def standard_section(key: str) -> str:
    """Section of an MF 6.1 file that holds ``key`` (e.g. ``PKY1`` -> ``LATERAL_COEFFICIENTS``); "" if unknown."""
    key = key.upper()
    if key in _SECTION_OF:
        return _SECTION_OF[key]
    if re.fullmatch(r"L[A-Z]+", key):
        return "SCALING_COEFFICIENTS"
    m = re.fullmatch(r"([PQRS])[A-Z]([XYZ])\d+", key)
    if m is None:
        return ""
    kind, axis = m.groups()
    if kind == "Q" and axis in "XY":
        return "OVERTURNING_COEFFICIENTS" if axis == "X" else "ROLLING_COEFFICIENTS"
    return {"X": "LONGITUDINAL_COEFFICIENTS", "Y": "LATERAL_COEFFICIENTS", "Z": "ALIGNING_COEFFICIENTS"}[axis]


def bundled_tyres() -> list[str]:
    """Names of the property files shipped in ``sim/data/tyres`` (sorted)."""
    folder = importlib.resources.files("sim").joinpath(*_BUNDLED_DIR)
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tir"))


def bundled_tir(name: str) -> Path:
    """Path of a property file shipped in ``sim/data/tyres`` (e.g. ``"mf61_255_55R20.tir"``)."""
    ref = importlib.resources.files("sim").joinpath(*_BUNDLED_DIR, name)
    path = Path(str(ref))
    if not path.is_file():
        raise TirError(f"{path}: no such bundled tyre property file")
    return path
