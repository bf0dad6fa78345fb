"""tools/paper_gap_study.py: its error anatomy, its report and its command line (no campaign is run)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from virtsensor.learning.dataset import Dataset

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("paper_gap_study", ROOT / "tools" / "paper_gap_study.py")
study = importlib.util.module_from_spec(_spec)
sys.modules["paper_gap_study"] = study
_spec.loader.exec_module(study)


def _dataset(n: int = 1000) -> tuple[Dataset, np.ndarray]:
    """Two runs (mu 1 and 0.3); the last 10 % of rows steer fast. Returns it and the test rows."""
    rng = np.random.default_rng(0)
    X = rng.normal(size=(n, 14))
    X[:, 12] = 0.5  # steering rate, rad/s: slow ...
    X[:, 13] = 2.0  # ... and acceleration, rad/s^2
    fast = np.arange(n) >= n - n // 10
    X[fast, 12] = np.radians(400.0)
    Y = rng.normal(scale=20.0, size=(n, 2))
    groups = (np.arange(n) >= n // 2).astype(int)
    meta = [{"mu": 1.0, "manoeuvre": "fishhook"}, {"mu": 0.3, "manoeuvre": "brake-accel"}]
    ds = Dataset(X, Y, groups, ["a", "b"], meta, tuple(f"x{i}" for i in range(14)), ("sat_fl_nm", "sat_fr_nm"), 0,
                 np.arange(n) * 0.05)
    return ds, np.arange(n)


def test_anatomy_splits_the_squared_error_where_it_was_put():
    ds, test = _dataset()
    E = np.ones_like(ds.Y)  # 1 Nm everywhere ...
    fast = ds.X[:, 12] >= study.FAST_RATE_RADPS
    E[fast] = 3.0  # ... 3 Nm on the fast-steering rows
    a = study._anatomy(ds, test, ds.Y + E)
    sse_fast = fast.sum() * 2 * 9.0
    sse_all = sse_fast + (~fast).sum() * 2 * 1.0
    assert a["fast_steering"]["row_share"] == pytest.approx(0.1)
    assert a["fast_steering"]["sse_share"] == pytest.approx(sse_fast / sse_all)
    assert a["fast_steering"]["mae_nm"] == pytest.approx(3.0)
    assert a["rest"]["mae_nm"] == pytest.approx(1.0)
    assert a["mae_nm"] == pytest.approx(0.9 * 1 + 0.1 * 3)
    assert a["rmse_over_mae"] == pytest.approx(np.sqrt(0.9 + 0.1 * 9) / 1.2)
    # the worst 1 % of rows are all fast ones, each with 1 / (fast rows) of the fast share
    assert a["worst_1pct_sse_share"] == pytest.approx(10 * 18.0 / sse_all)
    assert set(a["by_mu"]) == {"1", "0.3"} and a["by_mu"]["1"]["rows"] == 500
    assert a["by_manoeuvre"]["fishhook"]["sse_share"] == pytest.approx((500 * 2.0) / sse_all)


def test_markdown_lists_every_experiment_and_group():
    ds, test = _dataset()
    a = study._anatomy(ds, test, ds.Y + 1.0)
    fit = {"train": {"r2": 0.96}, "test": {"r2": 0.95, "mae_nm": 2.8}, "epochs": 300, "seconds": 30.0}
    res = {"seed": 0, "seeds": 1, "rows": 1000, "seconds": 60.0, "anatomy": a,
           "experiments": [{"label": "paper recipe", "inputs": "12", "network": "(32, 12)",
                            "result": {**study._median([fit]), "runs_r2": 0.8, "runs_mae_nm": 4.3}}]}
    res["experiments"].append({**res["experiments"][0], "label": "wider", "result": {
        **study._median([{**fit, "test": {"r2": 0.97, "mae_nm": 2.0}}]), "runs_r2": 0.9, "runs_mae_nm": 3.0}})
    md = study._markdown(res)
    assert "| paper recipe | 12 | (32, 12) | 0.960 | 0.950 | 2.80 | 0.950 | 300 | 0.800 / 4.30 |" in md
    assert "Test R2 against the first row: wider +0.020." in md
    assert "road friction 0.3" in md and "manoeuvre fishhook" in md


@pytest.mark.parametrize("argv, expect", [
    (["--seeds", "0"], "--seeds and --n-jobs must be >= 1"),
    (["--data", "/nonexistent/campaign"], "not a campaign directory"),
])
def test_bad_command_line_is_one_line_and_exit_2(argv, expect, capsys):
    assert study.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert expect in err and "\n" not in err
