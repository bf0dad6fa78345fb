"""MDF4 files (``.mf4``, ``.mdf``) as 20 Hz tables; needs the ``mdf`` extra (asammdf).

Channels named by a catalogue name or a DBC signal name are sampled and held at
the 20 Hz ticks ``t0 + k * TICK_S`` (k = 1, 2...; ``t0`` the first sample of any
channel), as the CAN front-end samples frames; the table's ``time_s`` counts
from ``t0``. A channel's unit, when the file gives one, must be the catalogue's.

An MDF4 file cut by the end of the file (a block that starts or ends past it,
found by walking every link from the header block) or never finalized by its
logger is refused, with the last timestamp that can still be read, if any.
"""

from __future__ import annotations

import gc
import struct
import sys
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError

TICK_S = cat.TABLE_TICK_S


def read_mdf(path: Path) -> dict[str, np.ndarray]:
    """A 20 Hz table from an MDF4 file: each channel named by its catalogue name or
    its DBC signal name is sampled and held at the ticks, as the CAN front-end does."""
    try:
        from asammdf import MDF
    except ImportError:
        raise UserError(f"{path}: reading MDF4 needs asammdf: pip install 'virtsensor[mdf]'") from None
    by_dbc = {s.dbc_signal: s.name for s in cat.SIGNALS.values() if s.dbc_signal}
    cut = mdf4_cut(path)
    if cut is not None:
        raise UserError(f"{path}: truncated: {cut}; {_last_good(MDF, path)}")
    mdf, error = _open(MDF, path)
    if mdf is None:
        raise UserError(f"{path}: not a readable MDF file ({error})")
    series: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    with mdf:
        for ch in list(mdf.channels_db):
            name = ch if ch in cat.SIGNALS else by_dbc.get(ch)
            if name is None or name == "time_s" or name in series:
                continue
            sig = mdf.get(ch)
            unit = (sig.unit or "").strip()
            want = cat.SIGNALS[name].unit
            if unit and unit != want:
                raise UserError(f"{path}: channel {ch!r} is in {unit!r}, the catalogue's {name} is in {want!r}")
            series[name] = (np.asarray(sig.timestamps, dtype=float), np.asarray(sig.samples, dtype=float))
    if not series:
        raise UserError(f"{path}: no channel named like a catalogue or DBC signal")
    t0 = min(ts[0] for ts, _ in series.values() if len(ts))
    t1 = max(ts[-1] for ts, _ in series.values() if len(ts))
    ticks = t0 + TICK_S * np.arange(1, int(np.floor((t1 - t0) / TICK_S + 1e-9)) + 1)
    table = {"time_s": ticks - t0}
    for name, (ts, ys) in series.items():
        i = np.searchsorted(ts, ticks + 1e-9, side="right") - 1
        col = np.where(i >= 0, ys[np.maximum(i, 0)], np.nan)
        table[name] = col
    return table


def _open(mdf_class: Any, path: Path) -> tuple[Any, str | None]:
    """``(mdf, None)``, or ``(None, error)`` if asammdf cannot open ``path``. A
    half-built asammdf object raises again in its ``__del__``; that echo of an
    error reported once already is collected here, silently."""
    hook = sys.unraisablehook
    sys.unraisablehook = lambda _: None
    try:
        try:
            return mdf_class(str(path)), None
        except Exception as exc:  # noqa: BLE001 - asammdf raises many kinds on a bad file
            error = f"{type(exc).__name__}: {exc}"
        gc.collect()  # the traceback is released: the half-built object goes now
        return None, error
    finally:
        sys.unraisablehook = hook


def mdf4_cut(path: Path) -> str | None:
    """Why an MDF4 file is cut (a block starting or ending past the end of the file,
    or a file its logger never finalized), or None. Not MDF4: None (the reader judges)."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        ident = f.read(64)
        if ident[:8] == b"UnFinMF ":
            return "the file was never finalized (its logger did not close it)"
        if ident[:8] != b"MDF     " or not ident[8:9] == b"4":
            return None
        stack, seen = [64], set()
        while stack:
            off = stack.pop()
            if off in seen:
                continue
            seen.add(off)
            if off + 24 > size:
                return f"a block at byte offset {off} lies past the end of the file ({size} bytes)"
            f.seek(off)
            head = f.read(24)
            if head[:2] != b"##":
                return None  # not a block: damaged, not cut; the reader says so
            length, n_links = struct.unpack("<QQ", head[8:24])
            if off + length > size:
                return (f"its {head[2:4].decode(errors='replace')} block at byte offset {off} ({length} bytes) "
                        f"ends past the end of the file ({size} bytes)")
            n_links = min(n_links, max(0, (length - 24) // 8))
            stack.extend(x for x in struct.unpack(f"<{n_links}Q", f.read(8 * n_links)) if x)
    return None


def _last_good(mdf_class, path: Path) -> str:
    """The last timestamp any channel group of a cut file still gives, for messages."""
    mdf, _ = _open(mdf_class, path)
    if mdf is None:
        return "no timestamp can be read (the channel directory is past the cut)"
    try:
        with mdf:
            last = max(float(mdf.get_master(i)[-1]) for i in range(len(mdf.groups)) if len(mdf.get_master(i)))
    except Exception:  # noqa: BLE001 - asammdf fails in many ways on a cut file
        return "no timestamp can be read"
    return f"the last good timestamp is {last:.6f} s"
