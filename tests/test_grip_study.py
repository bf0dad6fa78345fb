"""tools/grip_study.py: the fit of the trail's utilisation curve and the command line (no campaign is run)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("grip_study", ROOT / "tools" / "grip_study.py")
study = importlib.util.module_from_spec(_spec)
sys.modules["grip_study"] = study
_spec.loader.exec_module(study)


def test_utilisation_curve_is_the_weighted_isotonic_fit():
    """A sparse bin at the collapsed end (a few samples, a low median) is pooled with its heavy neighbour rather
    than capping the whole curve (as a running minimum from that end would); the result never increases with the
    trail, keeps a curve that already does not, and is the weighted mean over each pooled block."""
    y = np.array([0.80, 0.92, 0.90, 0.70, 0.75, 0.40])
    w = np.array([10.0, 300.0, 300.0, 500.0, 100.0, 400.0])
    fit = study._non_increasing(y, w)
    assert np.all(np.diff(fit) <= 0)
    assert fit[0] == pytest.approx((0.80 * 10 + 0.92 * 300) / 310)
    assert fit[0] > 0.9 > np.minimum.accumulate(y)[0]
    assert fit[3] == pytest.approx(fit[4]) == pytest.approx((0.70 * 500 + 0.75 * 100) / 600)
    assert fit[5] == pytest.approx(0.40)
    mono = np.array([0.9, 0.8, 0.8, 0.3])
    assert np.array_equal(study._non_increasing(mono, np.ones(4)), mono)


def test_counts_bin_as_the_curve_does():
    """Samples per trail knot: within half a spacing of it, the end knots taking everything beyond."""
    k = np.asarray(study.TRAIL_KNOTS)
    trail = np.array([k[0] - 1.0, k[0], k[3] + 0.001, k[3] - 0.001, k[-1] + 1.0])
    c = study._counts(trail)
    assert len(c) == len(k) and c.sum() == len(trail)
    assert c[0] == 2 and c[3] == 2 and c[-1] == 1


@pytest.mark.parametrize("argv", [["accept", "--warning-only"], ["fit", "--warning-only", "--evidence-only"],
                                  ["accept", "--evidence-only"]])
def test_fit_options_are_refused_where_they_do_not_apply(argv, capsys):
    with pytest.raises(SystemExit) as e:
        study.main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "--warning-only" in err[-1] or "--evidence-only" in err[-1]
