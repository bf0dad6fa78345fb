"""MDF4 files (``.mf4``, ``.mdf``) as 20 Hz tables; needs the ``mdf`` extra (asammdf).

Channels named by a catalogue name or a DBC signal name are sampled and held at
the 20 Hz ticks ``t0 + k * 0.05 s`` (k = 1, 2...; ``t0`` the first sample of any
channel), as the CAN front-end samples frames; the table's ``time_s`` counts
from ``t0``. A channel's unit, when the file gives one, must be the catalogue's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError

TICK_S = 1.0 / cat.TABLE_RATE_HZ


def read_mdf(path: Path) -> dict[str, np.ndarray]:
    """A 20 Hz table from an MDF4 file: each channel named by its catalogue name or
    its DBC signal name is sampled and held at the ticks, as the CAN front-end does."""
    try:
        from asammdf import MDF
    except ImportError:
        raise UserError(f"{path}: reading MDF4 needs asammdf: pip install 'virtsensor[mdf]'") from None
    by_dbc = {s.dbc_signal: s.name for s in cat.SIGNALS.values() if s.dbc_signal}
    try:
        mdf = MDF(str(path))
    except Exception as exc:  # asammdf raises many kinds on a bad file
        raise UserError(f"{path}: not a readable MDF file ({type(exc).__name__}: {exc})") from None
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
