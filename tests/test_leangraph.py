"""The lean rewrite of exported graphs (virtsensor.model.leangraph): the same function with fewer kernels."""

from __future__ import annotations

import warnings

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper
from sklearn.exceptions import ConvergenceWarning
from sklearn.linear_model import LinearRegression
from sklearn.neural_network import MLPRegressor
from sklearn.pipeline import Pipeline
from sklearn.preprocessing import MinMaxScaler, RobustScaler, StandardScaler

from virtsensor import signals as cat
from virtsensor.model import export as ex
from virtsensor.model import onnx as rt
from virtsensor.model.leangraph import MAX_FOLD_AMPLIFICATION, fold_amplification, lean_graph

N = len(cat.INPUTS)
SCALERS = {"robust": RobustScaler, "standard": StandardScaler, "minmax": MinMaxScaler}


def _data(n: int, seed: int, centre: float) -> tuple[np.ndarray, np.ndarray]:
    """Features of unlike spreads (0.1 to 4) around centres up to ``centre``; SAT-like targets (Nm)."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, N)) * np.linspace(0.1, 4, N) + np.linspace(-centre, centre, N)
    z = (X - X.mean(0)) / X.std(0)
    return X, np.c_[80 * np.tanh(z[:, 0] + z[:, 3]) + 10 * z[:, 5], 60 * np.sin(z[:, 2]) - 15 * z[:, 7]]


def _run(model: onnx.ModelProto, X: np.ndarray, dtype) -> np.ndarray:
    return rt.make_session(model.SerializeToString())[0].run(None, {"features": X.astype(dtype)})[0]


@pytest.mark.parametrize("precision", ["float32", "float64"])
@pytest.mark.parametrize("scaler", list(SCALERS))
@pytest.mark.parametrize("estimator", ["mlp_tanh", "mlp_relu", "mlp_logistic", "mlp_identity", "linear"])
def test_every_pipeline_the_trainer_may_export_keeps_its_function(tmp_path, precision, scaler, estimator):
    X, Y = _data(300, 0, centre=0.5)
    est = LinearRegression() if estimator == "linear" else MLPRegressor(
        hidden_layer_sizes=(16, 8), activation=estimator.removeprefix("mlp_"), solver="lbfgs", max_iter=40,
        alpha=100.0, random_state=0)  # (modest weights: float32 parity within 1e-3 Nm for the converted graph too)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        pipe = Pipeline([("scaler", SCALERS[scaler]()), ("est", est)]).fit(X, Y)
    Xt, _ = _data(400, 1, centre=0.5)
    card = ex.export_pipeline(pipe, N, tmp_path / "m.onnx", card_extra={"inputs": list(cat.INPUTS),
                              "weights": ex.pipeline_weights(pipe)}, parity_X=Xt, precision=precision)
    ops = [n.op_type for n in onnx.load(tmp_path / "m.onnx").graph.node]
    assert card["parity_max_abs_nm"] <= (1e-9 if precision == "float64" else rt.PARITY_TOL_NM)
    model = rt.OnnxModel.load(tmp_path / "m.onnx")
    np.testing.assert_allclose(model.predict(Xt), pipe.predict(Xt), rtol=0,
                               atol=1e-9 if precision == "float64" else rt.PARITY_TOL_NM)
    if estimator != "linear":
        act = {"tanh": "Tanh", "relu": "Relu", "logistic": "Sigmoid"}.get(estimator.removeprefix("mlp_"))
        if act is None:  # identity: no activation node
            assert ops in (["Gemm"] * 3, ["Sub"] + ["Gemm"] * 3)
            return
        assert ops in (["Gemm", act, "Gemm", act, "Gemm"], ["Sub", "Gemm", act, "Gemm", act, "Gemm"])
        assert {"fold_scaler", "fold_scale"} & set(card["onnx_rewrites"]) and card["onnx_rewrites"].count("gemm") == 3
    elif precision == "float64":
        assert ops in (["Gemm"], ["Sub", "Gemm"])
    else:  # skl2onnx's float32 LinearRegressor (ai.onnx.ml) is not a MatMul: the scaler stays
        assert "LinearRegressor" in ops and "fold_scaler" not in card["onnx_rewrites"]


def _fit(X: np.ndarray, Y: np.ndarray, scaler: str = "robust") -> Pipeline:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return Pipeline([("scaler", SCALERS[scaler]()), ("est", MLPRegressor(
            hidden_layer_sizes=(16, 8), activation="tanh", solver="lbfgs", max_iter=40, alpha=100.0,
            random_state=0))]).fit(X, Y)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_a_centre_far_from_zero_keeps_its_subtraction(tmp_path, precision):
    """A feature centred 20 spreads from zero: folding its centre into the bias (x W' + (b - c W')) would sum terms
    ~20 times the centred ones and lose float32 digits; the rewrite keeps the centring as one Sub (``fold_scale``),
    decided from the weights alone, and the graph stays as exact as the converted one."""
    X, Y = _data(300, 0, centre=2.0)
    pipe = _fit(X, Y)
    w = ex.pipeline_weights(pipe)
    c, s_ = np.array(w["center"]), np.array(w["scale"])
    assert fold_amplification(-c / s_, np.array(w["layers"][0]["W"]), np.array(w["layers"][0]["b"])) \
        > MAX_FOLD_AMPLIFICATION
    Xt, _ = _data(400, 1, centre=2.0)
    card = ex.export_pipeline(pipe, N, tmp_path / "m.onnx", card_extra={"inputs": list(cat.INPUTS)}, parity_X=Xt,
                              precision=precision)
    assert "fold_scale" in card["onnx_rewrites"]
    assert [n.op_type for n in onnx.load(tmp_path / "m.onnx").graph.node] == ["Sub", "Gemm", "Tanh", "Gemm",
                                                                              "Tanh", "Gemm"]
    plain = ex.export_pipeline(pipe, N, tmp_path / "p.onnx", card_extra={"inputs": list(cat.INPUTS)}, parity_X=Xt,
                               precision=precision, lean=False)
    assert plain["onnx_rewrites"] == [] and "Scaler" in [n.op_type for n in onnx.load(tmp_path / "p.onnx").graph.node] \
        or precision == "float64"
    assert card["parity_max_abs_nm"] <= 1.1 * plain["parity_max_abs_nm"] + (1e-12 if precision == "float64" else 1e-6)
    if precision == "float32":  # forcing the full fold here is the less exact graph
        full = ex._convert(pipe, N, 2, "float32", ex.TARGET_OPSET, cat.INPUTS, ex._outputs(None, 2))
        assert "fold_scaler" in lean_graph(full, fold_centre=True)
        assert np.abs(_run(full, Xt, np.float32) - pipe.predict(Xt)).max() > card["parity_max_abs_nm"]


def test_a_float64_graph_stays_exact_with_a_centre_of_1e8(tmp_path):
    X, Y = _data(200, 2, centre=0.5)
    X[:, 0] = 1e8 + X[:, 0]
    pipe = _fit(X, Y, "standard")
    card = ex.export_pipeline(pipe, N, tmp_path / "m.onnx", card_extra={"inputs": list(cat.INPUTS)}, parity_X=X,
                              precision="float64")
    assert "fold_scale" in card["onnx_rewrites"] and card["parity_max_abs_nm"] < 1e-9


def test_a_rewrite_the_checker_refuses_leaves_the_converted_graph(tmp_path, monkeypatch):
    import virtsensor.model.leangraph as lg

    def broken(model, **kw):
        model.graph.node[0].input[0] = "nowhere"
        onnx.checker.check_model(model, full_check=True)

    monkeypatch.setattr(lg, "lean_graph", broken)
    X, Y = _data(100, 3, centre=0.5)
    card = ex.export_pipeline(_fit(X, Y), N, tmp_path / "m.onnx", card_extra={"inputs": list(cat.INPUTS)},
                              parity_X=X)
    assert card["onnx_rewrites"] == [] and onnx.load(tmp_path / "m.onnx").graph.node[0].op_type == "Scaler"


def _graph(nodes, inits, n_out=2) -> onnx.ModelProto:
    g = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("features", TensorProto.FLOAT, ["N", 3])],
                          [helper.make_tensor_value_info("sat", TensorProto.FLOAT, ["N", n_out])],
                          [numpy_helper.from_array(np.asarray(v, np.float32), k) for k, v in inits.items()])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    return m


W = [[1.0, -2.0], [0.5, 3.0], [-1.5, 0.25]]


def test_a_scaler_read_twice_is_not_folded():
    """The scaled input also feeds a second branch: folding it into one MatMul would change the other."""
    m = _graph([helper.make_node("Sub", ["features", "c"], ["xs"]), helper.make_node("MatMul", ["xs", "W"], ["mm"]),
                helper.make_node("Add", ["mm", "b"], ["y"]),
                helper.make_node("Slice", ["xs", "s0", "s1", "ax"], ["xs2"]),
                helper.make_node("Add", ["y", "xs2"], ["sat"])],
               {"c": [1.0, 2.0, 3.0], "W": W, "b": [0.1, 0.2]})
    m.graph.initializer.extend([numpy_helper.from_array(np.array(v, np.int64), k)
                                for k, v in {"s0": [0], "s1": [2], "ax": [1]}.items()])
    X = np.random.default_rng(0).normal(size=(5, 3))
    before = _run(m, X, np.float32)
    done = lean_graph(m)
    assert "fold_scaler" not in done
    np.testing.assert_allclose(_run(m, X, np.float32), before, rtol=0, atol=1e-5)


def test_reverse_subtraction_and_division_are_not_taken_for_a_scaler():
    """``c - x`` and ``c / x`` are not ``(x - c)``/``x / c``: the chain is left alone (c / x is not affine)."""
    for op in ("Sub", "Div"):
        m = _graph([helper.make_node(op, ["c", "features"], ["xs"]), helper.make_node("MatMul", ["xs", "W"], ["mm"]),
                    helper.make_node("Add", ["mm", "b"], ["sat"])], {"c": [1.0, 2.0, 3.0], "W": W, "b": [0.1, 0.2]})
        X = np.random.default_rng(1).uniform(0.5, 2.0, size=(5, 3))
        before = _run(m, X, np.float32)
        assert "fold_scaler" not in lean_graph(m)
        np.testing.assert_allclose(_run(m, X, np.float32), before, rtol=1e-6, atol=1e-5)


def test_a_scaler_output_that_is_also_a_graph_output_is_not_folded():
    m = _graph([helper.make_node("Sub", ["features", "c"], ["xs"]), helper.make_node("MatMul", ["xs", "W"], ["mm"]),
                helper.make_node("Add", ["mm", "b"], ["sat"])], {"c": [1.0, 2.0, 3.0], "W": W, "b": [0.1, 0.2]})
    m.graph.output.append(helper.make_tensor_value_info("xs", TensorProto.FLOAT, ["N", 3]))
    assert lean_graph(m) == []  # two outputs: left as it is
    del m.graph.output[1]
    m.graph.output.append(helper.make_tensor_value_info("mm", TensorProto.FLOAT, ["N", 2]))
    assert lean_graph(m) == []


def test_single_value_scaler_and_a_zero_scale_keep_their_function():
    """ai.onnx.ml Scaler with one offset and one scale for every feature; and a Mul by a constant with a zero
    entry (a feature the layer ignores) through the centre-keeping fold."""
    sc = helper.make_node("Scaler", ["features"], ["xs"], domain="ai.onnx.ml", offset=[2.0], scale=[0.5])
    m = _graph([sc, helper.make_node("MatMul", ["xs", "W"], ["mm"]), helper.make_node("Add", ["mm", "b"], ["sat"])],
               {"W": W, "b": [0.1, 0.2]})
    m.opset_import.append(helper.make_opsetid("ai.onnx.ml", 3))
    X = np.random.default_rng(3).normal(size=(6, 3)) * 3
    before = _run(m, X, np.float32)
    assert lean_graph(m)[:1] == ["fold_scaler"]
    np.testing.assert_allclose(_run(m, X, np.float32), before, rtol=1e-6, atol=1e-5)
    m = _graph([helper.make_node("Add", ["features", "o"], ["a1"]), helper.make_node("Mul", ["a1", "k"], ["a2"]),
                helper.make_node("MatMul", ["a2", "W"], ["mm"]), helper.make_node("Add", ["mm", "b"], ["sat"])],
               {"o": [1.0, -2.0, 3.0], "k": [2.0, 0.0, 0.5], "W": W, "b": [0.1, 0.2]})
    before = _run(m, X, np.float32)
    assert lean_graph(m, fold_centre=False) == ["fold_scale", "gemm"]
    np.testing.assert_allclose(_run(m, X, np.float32), before, rtol=1e-6, atol=1e-5)


def test_fold_amplification():
    Wt = np.array(W)
    assert fold_amplification(np.zeros(3), Wt, np.array([0.1, 0.2])) == pytest.approx(1.0)
    # a centre of 10 spreads on the first feature: its weights summed 11 times over
    amp = fold_amplification(np.array([10.0, 0.0, 0.0]), Wt, np.zeros(2))
    expect = max((11 * abs(Wt[0, j]) + abs(Wt[1:, j]).sum() + abs(10 * Wt[0, j])) / abs(Wt[:, j]).sum() for j in (0, 1))
    assert amp == pytest.approx(expect)


def test_affine_chain_is_folded_exactly():
    """(x - c) / s * k + m, then MatMul + Add: one Gemm of the same function."""
    m = _graph([helper.make_node("Sub", ["features", "c"], ["a1"]), helper.make_node("Div", ["a1", "s"], ["a2"]),
                helper.make_node("Mul", ["a2", "k"], ["a3"]), helper.make_node("Add", ["a3", "o"], ["a4"]),
                helper.make_node("MatMul", ["a4", "W"], ["mm"]), helper.make_node("Add", ["mm", "b"], ["sat"])],
               {"c": [1.0, 2.0, 3.0], "s": [2.0, 0.5, 4.0], "k": [3.0], "o": [[0.5, -1.0, 2.0]], "W": W,
                "b": [[0.1, 0.2]]})
    X = np.random.default_rng(2).normal(size=(7, 3))
    before = _run(m, X, np.float32)
    assert lean_graph(m, fold_centre=True) == ["fold_scaler", "gemm"]
    assert [n.op_type for n in m.graph.node] == ["Gemm"] and len(m.graph.initializer) == 2
    np.testing.assert_allclose(_run(m, X, np.float32), before, rtol=1e-6, atol=1e-5)


def test_a_graph_with_nothing_to_rewrite_is_unchanged():
    m = _graph([helper.make_node("Gemm", ["features", "W", "b"], ["sat"])], {"W": W, "b": [0.1, 0.2]})
    before = m.SerializeToString()
    assert lean_graph(m) == []
    assert m.SerializeToString() == before
