"""Helpers shared by tests that simulate: a short table of recorded driver inputs (``simulate recorded``), the
cheapest run the command line makes when the manoeuvre itself does not matter to the test."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from virtsensor.recordings.canlog import write_csv
from virtsensor.signals import INPUTS, OUTPUTS, TABLE_TICK_S


def recorded_inputs(directory: Path, speed_mps, n: int = 80) -> Path:
    """``directory/inputs.csv``: a gentle steer (0.3 rad at 0.5 Hz) at the given speed per row (m/s), 20 Hz,
    ``n`` rows (80: 4 s)."""
    t = np.arange(n) * TABLE_TICK_S
    table = {"time_s": t, **{s: np.zeros(n) for s in INPUTS}, **{s: np.zeros(n) for s in OUTPUTS}}
    table["steer_angle_rad"] = 0.3 * np.sin(2 * np.pi * 0.5 * t)
    table["vx_mps"] = np.broadcast_to(speed_mps, (n,)).astype(float)
    path = directory / "inputs.csv"
    write_csv(path, table)
    return path
