"""R2 of fewer than two samples is undefined (NaN), as in scikit-learn: one row scored 0.0 and read as a fit."""

import math

import numpy as np
import pytest

from virtsensor.metrics import metrics, r2


def test_r2_of_fewer_than_two_samples_is_nan_and_otherwise_sklearns():
    from sklearn.metrics import r2_score

    assert math.isnan(r2(np.array([1.0]), np.array([2.0]))) and math.isnan(r2(np.zeros(0), np.zeros(0)))
    rng = np.random.default_rng(0)
    y, p = rng.normal(size=50), rng.normal(size=50)
    assert r2(y, p) == pytest.approx(r2_score(y, p))
    assert r2(np.ones(5), np.ones(5)) == 1.0 and r2(np.ones(5), np.zeros(5)) == 0.0
    assert math.isnan(metrics(np.array([[1.0, 2.0]]), np.array([[1.5, 2.5]]))["r2"])
