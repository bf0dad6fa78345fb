"""MDF4 files (``.mf4``, ``.mdf``) as 20 Hz tables; needs the ``mdf`` extra (asammdf).

Channels named by a catalogue name or a DBC signal name are sampled and held at
the 20 Hz ticks ``t0 + k * TICK_S`` (k = 1, 2...; ``t0`` the first sample of any
channel), as the CAN front-end samples frames; the table's ``time_s`` counts
from ``t0``. A channel's unit, when the file gives one, must be the catalogue's.

Such a channel must be readable as one run's: present once, with at least one
sample, one number per sample (not text), finite timestamps that never go back;
and all of them together must keep the time rule of CAN logs
(:func:`virtsensor.frontend.time_problem`: no jump of more than a minute
between consecutive samples of any channels, at most 12 hours from first to
last), so that a channel group stamped in Unix time among groups counted from 0
is refused, naming the time of the jump, before any tick grid is built.

An MDF4 file cut by the end of the file (a block that starts or ends past it,
found by walking every link from the header block) or never finalized by its
logger is refused, with the last timestamp that can still be read, if any.
"""

from __future__ import annotations

import gc
import math
import struct
import sys
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.frontend import MAX_GAP_S, largest_step, time_problem

TICK_S = cat.TABLE_TICK_S


def read_mdf(path: Path) -> dict[str, np.ndarray]:
    """A 20 Hz table from an MDF4 file: each channel named by its catalogue name or
    its DBC signal name is sampled and held at the ticks, as the CAN front-end does.

    Raises:
        UserError: naming the file: asammdf missing, a cut or unreadable file, no
            channel named like a signal, or such a channel that is empty, not one
            number per sample, in another unit, named twice or stamped out of order
            (:func:`_channel`), or a time that is not one run's (:func:`_check_time`).
    """
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
    channels: dict[str, str] = {}  # catalogue name -> the channel read for it
    with mdf:
        for ch, where in list(mdf.channels_db.items()):
            name = ch if ch in cat.SIGNALS else by_dbc.get(ch)
            if name is None or name == "time_s" or name in series:
                continue
            series[name] = _channel(path, mdf, ch, where, cat.SIGNALS[name])
            channels[name] = ch
    if not series:
        raise UserError(f"{path}: no channel named like a catalogue or DBC signal")
    t0 = min(ts[0] for ts, _ in series.values())
    t1 = max(ts[-1] for ts, _ in series.values())
    _check_time(path, series, channels, t0, t1)
    ticks = t0 + TICK_S * np.arange(1, int(np.floor((t1 - t0) / TICK_S + 1e-9)) + 1)
    table = {"time_s": ticks - t0}
    for name, (ts, ys) in series.items():
        i = np.searchsorted(ts, ticks + 1e-9, side="right") - 1
        col = np.where(i >= 0, ys[np.maximum(i, 0)], np.nan)
        table[name] = col
    return table


#: What a channel holds instead of numbers, by numpy dtype kind, for messages.
_NOT_NUMBERS = {"S": "text", "U": "text", "O": "objects (text or byte strings)", "V": "structures",
                "c": "complex numbers", "M": "dates", "m": "durations"}


def _channel(path: Path, mdf: Any, ch: str, where: tuple, signal: cat.Signal) -> tuple[np.ndarray, np.ndarray]:
    """The timestamps (s, finite, never decreasing) and float samples of channel ``ch`` (read for catalogue
    ``signal``; ``where``: its ``(group, index)`` occurrences in the file).

    Raises:
        UserError: naming the file and the channel: it occurs more than once (which is the run's is not
            known), asammdf cannot read it, it has no sample, it holds something other than one number per
            sample (text, say), its unit is not the catalogue's, or a timestamp is not finite or goes back.
    """
    at = f"{path}: channel {ch!r}"
    if len(where) != 1:
        groups = ", ".join(str(g) for g, _ in where)
        raise UserError(f"{at} occurs {len(where)} times (channel groups {groups}): which one is the run's "
                        f"{signal.name} is not known")
    group, index = where[0]
    try:
        sig = mdf.get(ch, group=group, index=index)
    except Exception as exc:  # noqa: BLE001 - asammdf raises many kinds on a bad channel
        raise UserError(f"{at}: cannot be read ({type(exc).__name__}: {exc})") from None
    ts, ys = np.asarray(sig.timestamps), np.asarray(sig.samples)
    if len(ts) == 0 or ys.size == 0:
        raise UserError(f"{at} has no samples (the catalogue's {signal.name} needs at least one)")
    if ys.dtype.kind not in "biuf" or ts.dtype.kind not in "iuf":
        what = _NOT_NUMBERS.get(ys.dtype.kind, f"values of type {ys.dtype}") if ys.dtype.kind not in "biuf" \
            else f"timestamps of type {ts.dtype}"
        raise UserError(f"{at} holds {what}, not numbers (the catalogue's {signal.name} is a number in "
                        f"{signal.unit!r})")
    if ys.ndim != 1:
        raise UserError(f"{at} holds an array of shape {ys.shape[1:]} per sample, not one number")
    if ys.shape != ts.shape:
        raise UserError(f"{at} has {ys.size} samples for {len(ts)} timestamps")
    unit = (sig.unit or "").strip()
    if unit and unit != signal.unit:
        raise UserError(f"{at} is in {unit!r}, the catalogue's {signal.name} is in {signal.unit!r}")
    ts = ts.astype(float)
    bad = np.flatnonzero(~np.isfinite(ts))
    if bad.size:
        raise UserError(f"{at}: the timestamp of sample {int(bad[0])} is {ts[bad[0]]}, not a finite time")
    back = np.flatnonzero(np.diff(ts) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise UserError(f"{at}: time goes back at sample {i}, from {ts[i - 1]:.6f} s to {ts[i]:.6f} s")
    return ts, ys.astype(float)


def _check_time(path: Path, series: dict[str, tuple[np.ndarray, np.ndarray]], channels: dict[str, str],
                t0: float, t1: float) -> None:
    """Refuse a file whose channels' time is not one run's (:func:`virtsensor.frontend.time_problem`, the
    rule of CAN logs: every channel's samples together, in time order, are its frames), naming the time of
    the jump and the channels that start there (a channel group on another clock, typically)."""
    jump = (math.nan, math.nan)
    if t1 - t0 > MAX_GAP_S:  # otherwise no gap can exceed it
        jump = largest_step(np.sort(np.concatenate([ts for ts, _ in series.values()])))
    why = time_problem(t0, t1, jump, what="samples")
    if why is None:
        return
    starts = [channels[n] for n, (ts, _) in series.items() if ts[0] == jump[1]]
    if len(starts) == 1:
        why += f"; channel {starts[0]!r} starts there"
    elif starts:
        why += f"; {len(starts)} channels start there, {starts[0]!r} first"
    raise UserError(f"{path}: {why}")


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
