"""tools/lean_models.py: migrating exported graphs to the lean rewrite without retraining."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import warnings
from pathlib import Path

import numpy as np
import onnx
import pytest
from sklearn.exceptions import ConvergenceWarning
from sklearn.neural_network import MLPRegressor
from sklearn.pipeline import Pipeline
from sklearn.preprocessing import RobustScaler

from virtsensor import signals as cat
from virtsensor.model import export as ex
from virtsensor.model.fallback import fallback_entry, load_fallback
from virtsensor.model.onnx import OnnxModel

TOOL = Path(__file__).resolve().parents[1] / "tools" / "lean_models.py"
spec = importlib.util.spec_from_file_location("lean_models", TOOL)
lean_models = importlib.util.module_from_spec(spec)
spec.loader.exec_module(lean_models)

PRESSURES = ["tyre_pressure_fl_pa", "tyre_pressure_fr_pa"]


def _pipe(n_features: int, seed: int) -> tuple[Pipeline, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(200, n_features)) * 2 + 1
    Y = np.c_[30 * np.tanh(X[:, 0] - X[:, 1]), 20 * np.sin(X[:, 2])]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return Pipeline([("s", RobustScaler()), ("m", MLPRegressor(
            hidden_layer_sizes=(8,), solver="lbfgs", max_iter=30, alpha=10.0, random_state=seed))]).fit(X, Y), X


@pytest.fixture
def old_models(tmp_path):
    """A pressure-free model and a TPMS model naming it as fallback, both exported as before the rewrite."""
    names = list(cat.INPUTS)
    free, X = _pipe(len(names), 0)
    ex.export_pipeline(free, len(names), tmp_path / "free.onnx", card_extra={
        "inputs": names, "weights": ex.pipeline_weights(free)}, parity_X=X, lean=False)
    tpms, X2 = _pipe(len(names) + 2, 1)
    entry = fallback_entry(tmp_path / "free.onnx", tmp_path / "tpms.onnx", tuple(names + PRESSURES))
    ex.export_pipeline(tpms, len(names) + 2, tmp_path / "tpms.onnx", card_extra={
        "inputs": names + PRESSURES, "weights": ex.pipeline_weights(tpms), "fallback": entry}, parity_X=X2,
        lean=False)
    return tmp_path


def test_the_fallback_of_a_model_not_named_follows_its_rewrite(old_models, capsys):
    d = old_models
    was = json.loads((d / "free.card.json").read_text())["sha256"]
    assert lean_models.main([str(d / "free.onnx")]) == 0  # tpms.onnx not named
    free = OnnxModel.load(d / "free.onnx")
    assert [n.op_type for n in onnx.load(d / "free.onnx").graph.node] == ["Gemm", "Relu", "Gemm"]
    assert free.card["rewritten_from"]["sha256"] == was and free.card["sha256"] != was
    assert free.card["rewritten_from"]["max_abs_diff_nm"] <= 1e-3 and "fold_scaler" in free.card["onnx_rewrites"]
    tpms = OnnxModel.load(d / "tpms.onnx")
    assert tpms.card["fallback"]["sha256"] == free.card["sha256"] and "rewritten_from" not in tpms.card
    assert load_fallback(tpms) is not None
    out = capsys.readouterr().out
    assert "free.onnx: drop_cast, fold_scaler" in out and "tpms.onnx: its fallback's new sha256" in out
    # a second run changes nothing
    before = {p.name: p.read_bytes() for p in d.iterdir()}
    assert lean_models.main([str(d / "free.onnx")]) == 0
    assert {p.name: p.read_bytes() for p in d.iterdir()} == before
    assert capsys.readouterr().out.count("nothing to rewrite") == 1


def test_both_rewritten_at_once(old_models):
    d = old_models
    assert lean_models.main([str(d / "tpms.onnx"), str(d / "free.onnx")]) == 0
    tpms = OnnxModel.load(d / "tpms.onnx")
    assert "rewritten_from" in tpms.card and load_fallback(tpms) is not None


def test_a_graph_its_card_does_not_name_is_refused_and_nothing_written(old_models, capsys):
    d = old_models
    (d / "free.onnx").write_bytes((d / "free.onnx").read_bytes() + b"\0")
    before = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in d.iterdir()}
    assert lean_models.main([str(d / "tpms.onnx"), str(d / "free.onnx")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "free.onnx" in err and "sha256" in err
    assert {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in d.iterdir()} == before
