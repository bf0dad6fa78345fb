"""Physical parameters of the simulated car: defaults, overrides, validation.

The defaults live in ``sim/data/car_c_segment.toml``. A run may override any
leaf with ``section.name=value`` strings (the CLI's ``--set``) or with a TOML
file of the same shape. Overrides are validated against the defaults: an
unknown key, a value of the wrong type or a non-finite number raises
:class:`ParamError` naming the key (and the file, for TOML files).
"""

from __future__ import annotations

import copy
import difflib
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

try:  # Python >= 3.11
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore[no-redef]

DATA_DIR = Path(__file__).resolve().parent / "data"
DEFAULT_CAR = DATA_DIR / "car_c_segment.toml"


class ParamError(ValueError):
    """A parameter override or file that cannot be used (message names key/file)."""


def resolve_data_file(name: str | Path) -> Path:
    """A data file named in the parameters: absolute, relative to the working
    directory if it exists there, else relative to the bundled ``sim/data``."""
    path = Path(name)
    if path.is_absolute() or path.exists():
        return path
    return DATA_DIR / path


def load_defaults(path: Path | str = DEFAULT_CAR) -> dict[str, Any]:
    """Read a car parameter TOML file into a nested dict."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except OSError as exc:
        raise ParamError(f"{path}: cannot read parameter file ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ParamError(f"{path}: not valid TOML ({exc})") from None


def _leaves(tree: Mapping[str, Any], prefix: str = "") -> Iterable[tuple[str, Any]]:
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            yield from _leaves(value, name + ".")
        else:
            yield name, value


def leaf_keys(tree: Mapping[str, Any]) -> list[str]:
    """All dotted leaf keys of a parameter tree (``section.name``)."""
    return [k for k, _ in _leaves(tree)]


def _coerce(key: str, default: Any, value: Any, where: str) -> Any:
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
    elif isinstance(default, (int, float)):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(float(value)):
                raise ParamError(f"{where}{key}: value must be finite, got {value!r}")
            return float(value)
    elif isinstance(default, str):
        if isinstance(value, str):
            return value
    elif isinstance(default, list):
        if isinstance(value, list) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v)) for v in value
        ):
            return [float(v) for v in value]
    raise ParamError(
        f"{where}{key}: expected {type(default).__name__} like {default!r}, got {value!r}"
    )


def _set(tree: dict[str, Any], key: str, value: Any, where: str = "") -> None:
    parts = key.split(".")
    node: Any = tree
    for i, part in enumerate(parts):
        if not isinstance(node, dict) or part not in node:
            close = difflib.get_close_matches(key, leaf_keys(tree), n=3, cutoff=0.85)
            hint = f" (did you mean {', '.join(close)}?)" if close else ""
            raise ParamError(f"{where}unknown parameter {key!r}{hint}")
        if i == len(parts) - 1:
            if isinstance(node[part], dict):
                raise ParamError(f"{where}{key!r} is a section, not a parameter; set one of its keys")
            node[part] = _coerce(key, node[part], value, where)
        else:
            node = node[part]


def parse_assignment(text: str) -> tuple[str, Any]:
    """Parse ``section.name=value`` (value in TOML syntax; bare words are strings)."""
    if "=" not in text:
        raise ParamError(f"--set {text!r}: expected section.name=value")
    key, raw = (s.strip() for s in text.split("=", 1))
    if not key:
        raise ParamError(f"--set {text!r}: empty parameter name")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw  # a bare word, e.g. a file name
    return key, value


def apply_overrides(
    base: Mapping[str, Any],
    assignments: Iterable[str] | Mapping[str, Any] = (),
    files: Iterable[Path | str] = (),
) -> dict[str, Any]:
    """Return a copy of ``base`` with TOML files, then assignments, applied.

    Args:
        base: the default parameter tree.
        assignments: ``["section.name=value", ...]`` or ``{"section.name": value}``.
        files: TOML files with the same shape as the defaults (any subset).
    """
    tree = copy.deepcopy(dict(base))
    for f in files:
        patch = load_defaults(f)
        for key, value in _leaves(patch):
            _set(tree, key, value, where=f"{f}: ")
    items = assignments.items() if isinstance(assignments, Mapping) else map(parse_assignment, assignments)
    for key, value in items:
        _set(tree, key, value)
    return tree


def car_parameters(
    assignments: Iterable[str] | Mapping[str, Any] = (),
    files: Iterable[Path | str] = (),
    defaults: Path | str = DEFAULT_CAR,
) -> dict[str, Any]:
    """The default car with overrides applied (the usual entry point)."""
    return apply_overrides(load_defaults(defaults), assignments, files)
