"""tools/naive_loop.py, the reference the daemon's CPU at 20 Hz is compared with: it runs the shipped model on the
bench's frames and publishes SAT_FRONT at 20 Hz (a loop that published nothing would cost nothing)."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

TOOL = Path(__file__).resolve().parents[1] / "tools" / "naive_loop.py"


def _tool():
    spec = importlib.util.spec_from_file_location("naive_loop", TOOL)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_naive_loop_publishes_sat_front_at_20_hz_and_costs_cpu() -> None:
    cpu, rate = _tool().naive_cpu(1.5)
    assert 10.0 <= rate <= 21.0, rate  # (20/s; a loaded machine may skip a late tick, never add one)
    assert math.isfinite(cpu) and cpu > 0.0, cpu
