"""ONNX export of the estimator pipeline, its model card, the onnxruntime runtime and the numpy back-end."""

from __future__ import annotations

import hashlib
import json
import warnings

import numpy as np
import onnx
import pytest
from sklearn.exceptions import ConvergenceWarning
from sklearn.linear_model import LinearRegression
from sklearn.neural_network import MLPRegressor
from sklearn.pipeline import Pipeline
from sklearn.preprocessing import RobustScaler
from threadpoolctl import threadpool_limits

from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.model import export as ex
from virtsensor.model import onnx as rt
from virtsensor.model.card import card_path_for

N_FEATURES = len(cat.INPUTS)


def _features(n: int, seed: int) -> np.ndarray:
    """Random rows spread over the catalogue inputs' physical ranges (their units)."""
    rng = np.random.default_rng(seed)
    lo = np.array([cat.SIGNALS[s].minimum for s in cat.INPUTS])
    hi = np.array([cat.SIGNALS[s].maximum for s in cat.INPUTS])
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    return mid + half * rng.uniform(-0.6, 0.6, size=(n, N_FEATURES))


def _sat(X: np.ndarray) -> np.ndarray:
    """SAT-like targets (Nm, about +-150)."""
    z = (X - X.mean(0)) / X.std(0)
    return np.c_[120 * np.sin(z[:, 1] + 0.5 * z[:, 4]) + 30 * z[:, 5], 100 * np.sin(z[:, 2] - z[:, 4]) + 20 * z[:, 6]]


def _mlp(n_out: int = 2, activation: str = "tanh") -> Pipeline:
    """A 12-32-12-n_out MLP, briefly trained (lbfgs reaches SAT-sized outputs in a few iterations)."""
    X = _features(200, 0)
    Y = _sat(X)
    # alpha=1 keeps the weights modest: float32 error grows with them (~6e-4 Nm at alpha=1e-4, ~2.6e-4 here)
    mlp = MLPRegressor(hidden_layer_sizes=(32, 12), activation=activation, solver="lbfgs", max_iter=30,
                       alpha=1.0, random_state=0)
    # one BLAS thread: on small matrices a thread pool is 5x slower than one thread
    with warnings.catch_warnings(), threadpool_limits(1):
        warnings.simplefilter("ignore", ConvergenceWarning)
        return Pipeline([("scaler", RobustScaler()), ("mlp", mlp)]).fit(X, Y if n_out == 2 else Y[:, 0])


def _card_extra() -> dict:
    return {
        "inputs": [{"name": s, "unit": cat.SIGNALS[s].unit, "dbc_message": cat.SIGNALS[s].message,
                    "dbc_signal": cat.SIGNALS[s].dbc_signal, "minimum": cat.SIGNALS[s].minimum,
                    "maximum": cat.SIGNALS[s].maximum} for s in cat.INPUTS],
        "training_data": {"sha256": "0" * 64, "rows": np.int64(200)},
        "metrics": {"rmse_nm": np.float64(3.5)},
    }


@pytest.fixture(scope="module")
def mlp2() -> Pipeline:
    return _mlp(2)


@pytest.fixture(scope="module")
def exported(mlp2, tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "sat.onnx"
    card = ex.export_pipeline(mlp2, N_FEATURES, path, card_extra=_card_extra(), parity_X=_features(500, 1))
    return path, card


def test_parity_with_sklearn_on_sat_magnitudes(mlp2, exported):
    path, card = exported
    X = _features(500, 1)
    ref = mlp2.predict(X)
    assert np.abs(ref).max() > 100.0  # the check is about SAT-sized numbers, not ~1 Nm ones
    model = rt.OnnxModel.load(path)
    assert np.abs(model.predict(X) - ref).max() <= rt.PARITY_TOL_NM
    assert 0.0 <= card["parity_max_abs_nm"] <= rt.PARITY_TOL_NM
    assert card["parity_rows"] == 500


@pytest.mark.parametrize("n", [1, 7])
def test_output_shape_is_n_by_outputs(exported, mlp2, n):
    path, _ = exported
    model = rt.OnnxModel.load(path)
    X = _features(n, 2)
    raw = model.session.run(["sat"], {"features": X.astype(np.float32)})[0]
    assert raw.shape == (n, 2)
    np.testing.assert_allclose(raw, mlp2.predict(X), atol=1e-3)
    assert model.predict(X).shape == (n, 2) and model.predict(X).dtype == np.float64
    # the declared graph output agrees: [N, 2], batch named like the input's
    g = onnx.load(path).graph
    (out,) = g.output
    dims = out.type.tensor_type.shape.dim
    assert out.name == "sat" and dims[0].dim_param == "N" and dims[1].dim_value == 2
    assert g.input[0].name == "features" and g.input[0].type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    # skl2onnx's scaler + MLP as one Gemm (+ activation) per layer: scaler folded, no Cast, no Reshape left
    assert [n.op_type for n in g.node] == ["Gemm", "Tanh", "Gemm", "Tanh", "Gemm"]


def test_one_output_model(tmp_path):
    pipe = _mlp(1)
    X = _features(7, 3)
    card = ex.export_pipeline(pipe, N_FEATURES, tmp_path / "fl.onnx", card_extra=_card_extra(),
                              parity_X=X, output_names=("sat_fl_nm",))
    model = rt.OnnxModel.load(tmp_path / "fl.onnx")
    assert model.predict(X).shape == (7, 1)
    assert model.predict_one(X[0]).shape == (1,)
    np.testing.assert_allclose(model.predict(X)[:, 0], pipe.predict(X), atol=1e-3)
    assert model.outputs == ("sat_fl_nm",) and card["n_outputs"] == 1
    with pytest.raises(ValueError, match="output_names"):
        ex.export_pipeline(pipe, N_FEATURES, tmp_path / "x.onnx", card_extra=_card_extra())


def test_card_contents_and_sha256(exported):
    path, card = exported
    on_disk = json.loads(card_path_for(path).read_text())
    assert on_disk == card and card_path_for(path).name == "sat.card.json"
    assert card["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert card["onnx_file"] == "sat.onnx" and card["n_features"] == N_FEATURES
    assert [o["name"] for o in card["outputs"]] == list(cat.OUTPUTS)
    assert {o["unit"] for o in card["outputs"]} == {"Nm"}
    assert card["feature_names"] == list(cat.INPUTS)
    assert card["inputs"][0]["dbc_signal"] == "AccelLong"  # card_extra kept
    assert card["training_data"]["rows"] == 200
    assert card["opset"]["ai.onnx"] <= ex.TARGET_OPSET[""] and card["target_opset"]["ai.onnx"] == 17
    opset = {d.domain or "ai.onnx": d.version for d in onnx.load(path).opset_import}
    assert card["opset"] == opset
    assert set(card["tool_versions"]) == {"python", "numpy", "scikit-learn", "skl2onnx", "onnx", "onnxruntime",
                                          "virtsensor"}
    assert card["created_utc"].endswith("Z")
    assert not [p for p in path.parent.iterdir() if p.name.endswith(".tmp")]  # atomic writes left nothing behind


def test_tampered_onnx_is_refused(exported, tmp_path):
    path, _ = exported
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    bad = tmp_path / "sat.onnx"
    bad.write_bytes(bytes(data))
    card = card_path_for(path)
    with pytest.raises(UserError, match="sha256") as e:
        rt.OnnxModel.load(bad, card)
    msg = str(e.value)
    assert "\n" not in msg and str(bad) in msg and str(card) in msg
    assert hashlib.sha256(bytes(data)).hexdigest() in msg and json.loads(card.read_text())["sha256"] in msg


def test_missing_card_or_onnx_is_a_user_error(exported, tmp_path):
    path, _ = exported
    (tmp_path / "sat.onnx").write_bytes(path.read_bytes())
    with pytest.raises(UserError, match="sat.card.json"):
        rt.OnnxModel.load(tmp_path / "sat.onnx")
    with pytest.raises(UserError, match="nothere.onnx"):
        rt.OnnxModel.load(tmp_path / "nothere.onnx", card_path_for(path))
    (tmp_path / "sat.card.json").write_text("{not json")
    with pytest.raises(UserError, match="not valid JSON"):
        rt.OnnxModel.load(tmp_path / "sat.onnx")


@pytest.mark.parametrize("use_iobinding", [True, False])
def test_predict_one_equals_predict(exported, use_iobinding):
    path, _ = exported
    model = rt.OnnxModel.load(path, use_iobinding=use_iobinding)
    X = _features(5, 4)
    batch = model.predict(X)
    out = model.predict_one(X[2])
    assert out.shape == (2,) and out.dtype == np.float64
    np.testing.assert_array_equal(out, batch[2])
    again = model.predict_one(X[3])
    assert again is out  # the preallocated result, overwritten in place
    np.testing.assert_array_equal(again, batch[3])
    with pytest.raises(ValueError, match="12 features"):
        model.predict_one(X[2, :5])


def test_session_is_single_threaded_without_spinning(exported):
    path, _ = exported
    model = rt.OnnxModel.load(path)
    import onnxruntime as ort

    for so in (model.session_options, model.session.get_session_options()):
        assert so.intra_op_num_threads == 1 and so.inter_op_num_threads == 1
        assert so.execution_mode == ort.ExecutionMode.ORT_SEQUENTIAL
        assert so.get_session_config_entry("session.intra_op.allow_spinning") == "0"
        assert so.get_session_config_entry("session.inter_op.allow_spinning") == "0"
    assert model.session.get_providers() == ["CPUExecutionProvider"]
    assert model.input_names == cat.INPUTS and model.outputs == cat.OUTPUTS and model.n_features == 12


def test_linear_regression_pipeline_exports(tmp_path):
    X = _features(200, 5)
    pipe = Pipeline([("scaler", RobustScaler()), ("lin", LinearRegression())]).fit(X, _sat(X))
    card = ex.export_pipeline(pipe, N_FEATURES, tmp_path / "lin.onnx", card_extra=_card_extra(), parity_X=X)
    model = rt.OnnxModel.load(tmp_path / "lin.onnx")
    assert onnx.load(tmp_path / "lin.onnx").graph.node[-1].name == "sat_reshape"  # appended: no Reshape to retarget
    for n in (1, 7):
        assert model.predict(X[:n]).shape == (n, 2)
    assert card["parity_max_abs_nm"] <= rt.PARITY_TOL_NM
    np.testing.assert_allclose(rt.numpy_forward(pipe)(X), pipe.predict(X), rtol=0, atol=1e-9)


def test_export_is_byte_reproducible(mlp2, exported, tmp_path):
    """The same fitted pipeline exports to the same bytes (and card sha256): a rebuild from
    the same data and seed can be checked against the shipped file."""
    card = ex.export_pipeline(mlp2, N_FEATURES, tmp_path / "again.onnx", card_extra=_card_extra())
    assert (tmp_path / "again.onnx").read_bytes() == exported[0].read_bytes()
    assert card["sha256"] == exported[1]["sha256"]
    assert onnx.load(tmp_path / "again.onnx").graph.name == ex.GRAPH_NAME


def test_export_bytes_do_not_depend_on_the_process_s_string_hash(mlp2, tmp_path):
    """skl2onnx lists the opsets in a set's order, which the string hash sets: with PYTHONHASHSEED 116 and 0 one
    pipeline exported to different bytes, sha256 and VS_ModelId. Exported in two processes, one seed each."""
    import os
    import pickle
    import subprocess
    import sys

    (tmp_path / "pipe.pkl").write_bytes(pickle.dumps((mlp2, _card_extra())))
    script = ("import pickle, sys; from virtsensor.model import export as ex; "
              "pipe, extra = pickle.load(open(sys.argv[1], 'rb')); "
              f"ex.export_pipeline(pipe, {N_FEATURES}, sys.argv[2], card_extra=extra)")
    procs = [subprocess.Popen([sys.executable, "-c", script, str(tmp_path / "pipe.pkl"), str(tmp_path / f"{h}.onnx")],
                              env={**os.environ, "PYTHONHASHSEED": h}) for h in ("0", "116")]
    assert [p.wait(timeout=120) for p in procs] == [0, 0]
    assert (tmp_path / "0.onnx").read_bytes() == (tmp_path / "116.onnx").read_bytes()
    domains = [d.domain for d in onnx.load(tmp_path / "0.onnx").opset_import]
    assert domains == sorted(domains)


def test_a_failed_write_leaves_the_model_and_its_card_as_they_were(mlp2, tmp_path, monkeypatch):
    """The graph and its card were written one after the other: a full disk at the card left a new graph beside
    the old card, a pair every load refuses (sha256 mismatch). Now both or neither."""
    import errno

    path = tmp_path / "m.onnx"
    ex.export_pipeline(mlp2, N_FEATURES, path, card_extra=_card_extra())
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def full(self):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ex.ModelCard, "text", full)
    with pytest.raises(OSError, match="No space left"):
        ex.export_pipeline(mlp2, N_FEATURES, path, card_extra={**_card_extra(), "metrics": {"rmse_nm": 9.0}})
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_double_precision_export(mlp2, tmp_path):
    X = _features(50, 6)
    card = ex.export_pipeline(mlp2, N_FEATURES, tmp_path / "d.onnx", card_extra=_card_extra(), parity_X=X,
                              precision="float64")
    assert card["input_dtype"] == "float64" and card["parity_max_abs_nm"] < 1e-9
    model = rt.OnnxModel.load(tmp_path / "d.onnx")
    np.testing.assert_allclose(model.predict_one(X[0]), mlp2.predict(X[:1])[0], rtol=0, atol=1e-9)


def test_parity_failure_writes_nothing(mlp2, tmp_path, monkeypatch):
    monkeypatch.setattr(rt, "PARITY_TOL_NM", 0.0)
    with pytest.raises(ValueError, match="parity"):
        ex.export_pipeline(mlp2, N_FEATURES, tmp_path / "p.onnx", card_extra=_card_extra(),
                           parity_X=_features(50, 7))
    assert list(tmp_path.iterdir()) == []


def test_bad_card_extra(mlp2, tmp_path):
    with pytest.raises(ValueError, match="sha256"):
        ex.export_pipeline(mlp2, N_FEATURES, tmp_path / "a.onnx", card_extra={**_card_extra(), "sha256": "x"})
    with pytest.raises(ValueError, match="features"):
        ex.export_pipeline(mlp2, N_FEATURES, tmp_path / "a.onnx", card_extra={"inputs": ["ax_mps2"]})


@pytest.mark.parametrize("activation", ["tanh", "relu", "identity"])
def test_numpy_forward_matches_sklearn(mlp2, activation):
    pipe = mlp2 if activation == "tanh" else _mlp(2, activation)
    X = _features(300, 8)
    fwd = rt.numpy_forward(pipe)
    np.testing.assert_allclose(fwd(X), pipe.predict(X), rtol=0, atol=1e-9)
    np.testing.assert_allclose(fwd.predict_one(X[0]), pipe.predict(X[:1])[0], rtol=0, atol=1e-9)
    # the same from the JSON-able weights
    weights = json.loads(json.dumps(ex.pipeline_weights(pipe)))
    np.testing.assert_allclose(rt.numpy_forward(weights)(X), pipe.predict(X), rtol=0, atol=1e-9)


@pytest.mark.parametrize("scaler", ["robust", "standard", "minmax"])
def test_numpy_forward_and_card_weights_for_every_scaler_the_grid_may_pick(scaler):
    """The grid search may choose another scaler than the paper's; the card's weights and the
    numpy back-end must follow (a StandardScaler winner once crashed `train --grid` at export)."""
    from virtsensor.learning.training import PAPER_PARAMS, make_pipeline
    from virtsensor.model.onnx import numpy_forward

    rng = np.random.default_rng(1)
    X = rng.normal(size=(300, 4)) * [1.0, 5.0, 0.1, 20.0] + [0.0, 3.0, 1.0, -5.0]
    Y = np.column_stack([X[:, 0] ** 2, np.sin(X[:, 1])])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = make_pipeline({**PAPER_PARAMS, "scaler": scaler, "max_iter": 20}).fit(X, Y)
    assert np.abs(numpy_forward(p)(X) - p.predict(X)).max() < 1e-9
