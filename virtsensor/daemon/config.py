"""Settings of ``virtsensor run``: a checked :class:`RuntimeConfig` from a TOML file and overrides.

CLI options and TOML keys share the field names (``-`` or ``_``); an unknown key or a bad value raises
:class:`~virtsensor.errors.UserError` naming the file (or the option) and the key.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from virtsensor import assets
from virtsensor.daemon.jsonlog import LOG_LEVELS
from virtsensor.errors import UserError
from virtsensor.fileio import read_user_text
from virtsensor.signals import INPUT_TIMEOUT_CYCLES

__all__ = ["DURATION_MAX_S", "INT_RANGES", "TIMEOUT_CYCLES_RANGE", "RuntimeConfig", "load_config",
           "read_config_file"]

#: the integer settings' inclusive ranges: the CLI's options and the config file's keys share them
INT_RANGES: dict[str, tuple[int, int]] = {"bitrate": (1000, 20_000_000), "sync_every": (1, 1000), "cpu": (0, 4095),
                                          "rt_priority": (1, 99), "model_id": (0, 255),
                                          "cpu_latency_us": (0, 2_000_000_000)}
#: ``duration`` is in (0, DURATION_MAX_S] seconds; ``timeout_cycles`` in this inclusive range: a value is VALID
#: only while fresh, and at 10 cycles a 10 ms message's value may be two ticks old, a 20 ms one's four
DURATION_MAX_S = 1e9
TIMEOUT_CYCLES_RANGE = (1.0, 10.0)
#: the file kind of each path setting
_PATH_SUFFIX = {"model": ".onnx", "dbc": ".dbc"}


@dataclass
class RuntimeConfig:
    """Settings of ``virtsensor run`` (CLI options and TOML keys share these names, ``-`` or ``_``).

    Attributes:
        model: ONNX file (its card beside it; None: the shipped model). dbc: DBC file (None: bundled).
        interface, channel, bitrate: python-can bus.
        sync_id: CAN id whose frames trigger the ticks (None: free-running 20 Hz).
        sync_every: tick on every n-th sync frame (e.g. 5 for a 100 Hz frame), counted from the first.
        cpu: pin the daemon to this CPU. realtime: ask for SCHED_FIFO at ``rt_priority``.
        cpu_latency_us: hold a Linux PM QoS CPU-latency request of this many microseconds while running (0: no
            idle state with any exit latency; None: leave the machine's idle policy alone); see
            :mod:`virtsensor.daemon.pmqos`.
        duration: stop after this many seconds (None: until SIGTERM/SIGINT).
        log_level: debug, info, warning or error.
        timeout_cycles: an input message is stale after this many of its cycles without a usable frame.
        model_id: the VS_ModelId byte (None: the card's ``model_id``, else the first byte of its sha256).
    """

    model: str | None = None
    dbc: str | None = None
    interface: str | None = None
    channel: str | None = None
    bitrate: int | None = None
    sync_id: int | None = None
    sync_every: int = 1
    cpu: int | None = None
    realtime: bool = False
    rt_priority: int = 50
    cpu_latency_us: int | None = None
    duration: float | None = None
    log_level: str = "info"
    timeout_cycles: float = INPUT_TIMEOUT_CYCLES
    model_id: int | None = None
    #: where each setting given came from, for messages: key -> ``"<file>: <key>"`` or ``"--<option>"``
    origin: dict[str, str] = field(default_factory=dict, compare=False, repr=False)

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        del out["origin"]
        return out

    def where(self, key: str) -> str:
        """Where ``key`` was set (its config file and key, or its option), for a message about its value."""
        return self.origin.get(key, f"--{key.replace('_', '-')}")


_PATH_KEYS = ("model", "dbc")


def _coerce(key: str, value: Any, where: str) -> Any:
    """Check and convert one setting; ``where`` names its source in errors."""
    def bad(expect: str) -> UserError:
        return UserError(f"{where}: {key} must be {expect}, got {value!r}")

    if value is None:
        return None
    if key in ("model", "dbc", "interface", "channel", "log_level"):
        if not isinstance(value, (str, os.PathLike)) or not str(value):
            raise bad("a non-empty string")
        value = str(value)
        if key == "log_level" and value.lower() not in LOG_LEVELS:
            raise bad(f"one of {', '.join(LOG_LEVELS)}")
        if key == "interface":
            import can

            if value not in can.interfaces.VALID_INTERFACES:
                raise bad(f"one of python-can's interfaces ({', '.join(sorted(can.interfaces.VALID_INTERFACES))})")
        return value.lower() if key == "log_level" else value
    if key == "sync_id":
        try:
            v = int(value, 0) if isinstance(value, str) else value
        except ValueError:
            raise bad("a CAN id such as 0x7F0") from None
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 0x7FF:
            raise bad("an 11-bit CAN id 0x000..0x7FF")
        return v
    if key in ("bitrate", "sync_every", "cpu", "rt_priority", "model_id", "cpu_latency_us"):
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        lo, hi = INT_RANGES[key]
        if not lo <= value <= hi:
            raise bad(f"in {lo}..{hi}")
        if key == "cpu" and hasattr(os, "sched_getaffinity") and value not in (cpus := os.sched_getaffinity(0)):
            raise bad(f"one of the CPUs this process may run on ({', '.join(map(str, sorted(cpus)))})")
        return value
    if key == "realtime":
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if key in ("duration", "timeout_cycles"):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise bad("a positive number")
        if key == "duration" and value > DURATION_MAX_S:
            raise bad(f"at most {DURATION_MAX_S:g} s")
        if key == "timeout_cycles" and not TIMEOUT_CYCLES_RANGE[0] <= value <= TIMEOUT_CYCLES_RANGE[1]:
            raise bad(f"in {TIMEOUT_CYCLES_RANGE[0]:g}..{TIMEOUT_CYCLES_RANGE[1]:g}")
        return float(value)
    raise UserError(f"{where}: unknown setting {key!r}")  # pragma: no cover - keys are checked first


_KEYS = tuple(f.name for f in fields(RuntimeConfig) if f.name != "origin")


def _check_path(key: str, value: Path, where: Path) -> None:
    """The config file ``where``'s ``model``/``dbc`` ``value`` names an existing file of its kind, as the
    options' own check; a UserError naming the file and the key if not."""
    suffix = _PATH_SUFFIX[key]
    if not value.exists():
        raise UserError(f"{where}: {key} {value}: no such file")
    if value.is_dir():
        raise UserError(f"{where}: {key} {value} is a directory, not a {suffix} file")
    if value.suffix.lower() != suffix:
        raise UserError(f"{where}: {key} {value}: expected a {suffix} file")
    if not os.access(value, os.R_OK):
        raise UserError(f"{where}: {key} {value}: not readable")


def read_config_file(path: str | os.PathLike) -> dict[str, Any]:
    """The settings of a TOML config file (keys checked, paths relative to the file made absolute).

    Raises:
        UserError: unreadable file, invalid TOML, unknown key (named with the file) or a bad value.
    """
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]

    path = Path(path)
    text = read_user_text(path, "config file")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"config file {path} is not valid TOML: {exc}") from None
    out: dict[str, Any] = {}
    for raw_key, value in data.items():
        key = raw_key.replace("-", "_")
        if key not in _KEYS:
            raise UserError(f"{path}: unknown key {raw_key!r} (known: {', '.join(_KEYS)})")
        if key in out:
            raise UserError(f"{path}: key {raw_key!r} given twice")
        value = _coerce(key, value, str(path))
        if key in _PATH_KEYS and value is not None and not Path(value).is_absolute():
            value = str((path.parent / value).resolve())
        out[key] = value
    return out


def load_config(file: str | os.PathLike | None = None, overrides: Mapping[str, Any] | None = None) -> RuntimeConfig:
    """Merge a TOML file and overrides (e.g. CLI options; None values are ignored) into a checked config.

    Raises:
        UserError: see :func:`read_config_file`; a missing ``model``, ``interface`` or ``channel``; a
            ``sync_every`` other than 1 without a ``sync_id``.
    """
    merged: dict[str, Any] = read_config_file(file) if file is not None else {}
    origin = {k: f"{file}: {k}" for k in merged}
    from_file = {k for k in _PATH_KEYS if merged.get(k) is not None}
    for key, value in (overrides or {}).items():
        k = key.replace("-", "_")
        if k not in _KEYS:
            raise UserError(f"unknown setting {key!r}")
        if value is not None:
            merged[k] = _coerce(k, value, f"--{k.replace('_', '-')}")
            origin.pop(k, None)
            from_file.discard(k)
    for k in sorted(from_file):  # a path the file gives and no option overrides: checked as the option's own
        _check_path(k, Path(merged[k]), Path(str(file)))
    if merged.get("model") is None:  # the shipped model, whatever the working directory
        merged["model"] = str(assets.model_path())
    cfg = RuntimeConfig(**merged, origin=origin)
    if cfg.sync_every != 1 and cfg.sync_id is None:
        raise UserError(f"sync_every {cfg.sync_every} goes with sync_id (sync mode: a tick every n-th sync frame); "
                        "free-running, the daemon ticks on its own 20 Hz clock: give --sync-id or drop --sync-every")
    missing = [k for k in ("interface", "channel") if getattr(cfg, k) is None]
    if missing:
        src = f" (not in {file} either)" if file is not None else ""
        raise UserError(f"missing setting(s) {', '.join('--' + k for k in missing)}{src}")
    return cfg
