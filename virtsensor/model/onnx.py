"""The deployed estimator at run time: one ONNX graph checked against its model card.

Graph contract (what a runtime in any language may rely on):

* one input ``features``: float32 (or float64 when the card's ``input_dtype`` says so),
  shape ``[N, n_features]``, columns in the card's ``feature_names`` order, each in the
  unit the card gives it (SI, catalogue units);
* one output ``sat``: same dtype, shape ``[N, n_outputs]``, columns in the card's
  ``outputs`` order, in Nm (tyre self-aligning torque, ISO-W, see :mod:`virtsensor.signals`);
* graphs exported since cards carry digests also name their feature and output columns in
  the ONNX metadata (:data:`META_FEATURES`, :data:`META_OUTPUTS`, JSON lists).

:meth:`OnnxModel.load` refuses (:class:`~virtsensor.errors.UserError`, one line naming the file)
a card whose digest does not match its content (see :mod:`virtsensor.model.card`), an ONNX
whose SHA-256 is not the card's, a graph whose metadata names other columns than the card,
and a card whose plain ``weights`` (the numpy back-end) do not reproduce the graph on the
card's ``parity_inputs`` rows within :data:`PARITY_TOL_NM`.

It runs onnxruntime single-threaded on the CPU with spinning off, with an allocation-lean
``predict_one`` for the 20 Hz real-time path. This module imports neither scikit-learn,
skl2onnx, onnx nor scipy (the export side is :mod:`virtsensor.model.export`).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor.errors import UserError
from virtsensor.model.card import ACTIVATIONS, ModelCard, card_path_for

#: Largest |reference - onnxruntime| difference (Nm) accepted: sklearn at export, the numpy back-end at load.
PARITY_TOL_NM = 1e-3
INPUT_NAME = "features"
OUTPUT_NAME = "sat"
#: ONNX metadata keys naming the graph's input and output columns (JSON lists of names).
META_FEATURES = "virtsensor.feature_names"
META_OUTPUTS = "virtsensor.outputs"
#: Rows of ``parity_inputs`` a card carries (the numpy back-end is checked on them at every load).
N_PARITY_INPUTS = 8


def session_options() -> Any:
    """onnxruntime options of the real-time runtime: one thread, sequential, no spinning.

    Spinning threads would burn a core waiting for work between 20 Hz ticks; a small MLP
    gains nothing from a pool.
    """
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    return so


def make_session(onnx_bytes: bytes) -> tuple[Any, Any]:
    """An onnxruntime ``InferenceSession`` on the CPU with :func:`session_options`, and those options."""
    import onnxruntime as ort

    so = session_options()
    return ort.InferenceSession(onnx_bytes, sess_options=so, providers=["CPUExecutionProvider"]), so


def default_parity_inputs(weights: Mapping[str, Any] | None, n_features: int,
                          n: int = N_PARITY_INPUTS) -> list[list[float]]:
    """Deterministic check rows when no data rows are at hand: ``center + scale * N(0, 1)`` (seed 0).

    ``center``/``scale`` come from the weights' scaler (0 and 1 without one), so the rows
    lie where the network was trained, in the feature units.
    """
    rng = np.random.default_rng(0)
    w = weights or {}
    center = np.zeros(n_features) if w.get("center") is None else np.asarray(w["center"], float)
    scale = np.ones(n_features) if w.get("scale") is None else np.asarray(w["scale"], float)
    return (center + scale * rng.normal(size=(n, n_features))).tolist()


class OnnxModel:
    """An exported estimator loaded for inference (see :meth:`load`).

    Attributes:
        card: the model card (:class:`~virtsensor.model.card.ModelCard`, a read-only Mapping).
        input_names: ordered feature names (the card's ``feature_names``), each in
            the unit the card gives it.
        n_features: number of features.
        outputs: ordered output names (catalogue names, Nm), e.g. ``("sat_fl_nm", "sat_fr_nm")``.
        n_outputs: number of outputs.
        path, card_path: the files it was loaded from.
        session: the onnxruntime ``InferenceSession``.
        session_options: the ``SessionOptions`` it was created with.
        uses_iobinding: whether :meth:`predict_one` runs through an IOBinding.
        numpy_forward: the numpy back-end built from the card's ``weights``, checked against the
            graph at load (None when the card has no weights).

    ``predict`` is safe to call from several threads; ``predict_one`` is not (it
    reuses its buffers).
    """

    def __init__(self, onnx_bytes: bytes, card: Mapping[str, Any], *, path: Path, card_path: Path,
                 use_iobinding: bool = True) -> None:
        self.card = card if isinstance(card, ModelCard) else ModelCard(card, path=card_path)
        self.path, self.card_path = path, card_path
        try:
            self.n_features = int(card["n_features"])
            self.input_names = tuple(str(n) for n in card["feature_names"])
            self.outputs = tuple(str(o["name"] if isinstance(o, Mapping) else o) for o in card["outputs"])
            in_name = str(card.get("onnx_input", INPUT_NAME))
            out_name = str(card.get("onnx_output", OUTPUT_NAME))
        except (KeyError, TypeError, ValueError) as e:
            raise UserError(f"{card_path}: not a model card (bad or missing {e})") from None
        self.n_outputs = len(self.outputs)
        if len(self.input_names) != self.n_features:
            raise UserError(f"{card_path}: {len(self.input_names)} feature_names but n_features={self.n_features}")
        try:
            self.session, self.session_options = make_session(onnx_bytes)
        except Exception as e:  # onnxruntime raises its own exception types
            raise UserError(f"{path}: onnxruntime cannot load it: {str(e).splitlines()[0]}") from None
        self._check_graph(in_name, out_name)
        self._in_name, self._out_name = in_name, out_name
        self._setup_buffers(use_iobinding)
        self.numpy_forward = self._checked_numpy_forward()

    def _check_graph(self, in_name: str, out_name: str) -> None:
        """The graph's names, shapes, dtype and column metadata against the card."""
        path, card_path = self.path, self.card_path
        inp, out = self.session.get_inputs(), self.session.get_outputs()
        if [i.name for i in inp] != [in_name] or [o.name for o in out] != [out_name]:
            raise UserError(f"{path}: graph has inputs {[i.name for i in inp]} / outputs {[o.name for o in out]}, "
                            f"{card_path} says {in_name!r} / {out_name!r}")
        if inp[0].shape[1:] != [self.n_features] or out[0].shape[1:] != [self.n_outputs]:
            raise UserError(f"{path}: graph shapes {inp[0].shape} -> {out[0].shape} disagree with {card_path} "
                            f"({self.n_features} features, {self.n_outputs} outputs)")
        self._dtype = {"tensor(float)": np.float32, "tensor(double)": np.float64}.get(inp[0].type)
        if self._dtype is None:
            raise UserError(f"{path}: unsupported input type {inp[0].type}")
        meta = self.session.get_modelmeta().custom_metadata_map
        for key, mine, what in ((META_OUTPUTS, self.outputs, "outputs"), (META_FEATURES, self.input_names,
                                                                         "feature_names")):
            if key not in meta:
                continue  # graphs exported before the metadata existed: the card's digest covers the order
            try:
                theirs = tuple(str(x) for x in json.loads(meta[key]))
            except (ValueError, TypeError):
                raise UserError(f"{path}: ONNX metadata {key} is not a JSON list") from None
            if theirs != mine:
                raise UserError(f"{card_path}: {what} {list(mine)} differ from the ONNX graph's {list(theirs)} "
                                f"({path}); refusing a card that does not describe its graph")

    def _checked_numpy_forward(self) -> NumpyForward | None:
        """The card's weights as a numpy back-end, refused unless it reproduces the graph on the parity rows."""
        weights = self.card.get("weights")
        if weights is None:
            return None
        where = self.card_path
        rows = self.card.get("parity_inputs")
        try:
            fwd = NumpyForward(weights)
            X = np.asarray(rows, dtype=float)
        except (AttributeError, KeyError, TypeError, ValueError, IndexError) as exc:
            raise UserError(f"{where}: unusable weights or parity_inputs: {exc}") from None
        if X.ndim != 2 or len(X) == 0 or X.shape[1] != self.n_features or not np.isfinite(X).all():
            raise UserError(f"{where}: the card has weights but no usable parity_inputs "
                            f"(rows of {self.n_features} finite features) to check them on")
        if (fwd.n_features, fwd.n_outputs) != (self.n_features, self.n_outputs):
            raise UserError(f"{where}: weights are {fwd.n_features} -> {fwd.n_outputs}, the graph "
                            f"{self.n_features} -> {self.n_outputs}")
        err = float(np.max(np.abs(fwd(X) - self.predict(X))))
        if not err <= PARITY_TOL_NM:  # also NaN
            raise UserError(f"{where}: the card's weights differ from the ONNX graph {self.path} by {err:.3g} Nm "
                            f"on its {len(X)} parity_inputs rows (limit {PARITY_TOL_NM:g} Nm); refusing it")
        return fwd

    def _setup_buffers(self, use_iobinding: bool) -> None:
        # Real-time path: buffers allocated once; the IOBinding wraps their memory (no copies).
        self._in_buf = np.zeros((1, self.n_features), dtype=self._dtype)
        self._out_buf = np.zeros((1, self.n_outputs), dtype=self._dtype)
        self._in_row = self._in_buf[0]
        self._out_row = self._out_buf[0]
        self._result = np.zeros(self.n_outputs, dtype=np.float64)
        self._feed = {self._in_name: self._in_buf}
        self._fetch = [self._out_name]
        self.uses_iobinding = bool(use_iobinding)
        if self.uses_iobinding:
            import onnxruntime as ort

            self._in_ort = ort.OrtValue.ortvalue_from_numpy(self._in_buf)
            self._out_ort = ort.OrtValue.ortvalue_from_numpy(self._out_buf)
            self._binding = self.session.io_binding()
            self._binding.bind_ortvalue_input(self._in_name, self._in_ort)
            self._binding.bind_ortvalue_output(self._out_name, self._out_ort)

    @classmethod
    def load(cls, path: str | os.PathLike[str], card_path: str | os.PathLike[str] | None = None, *,
             use_iobinding: bool = True) -> OnnxModel:
        """Load ``path`` (ONNX) after checking it against its card.

        Args:
            path: the ``.onnx`` file.
            card_path: its model card; default :func:`~virtsensor.model.card.card_path_for` ``(path)``.
            use_iobinding: run :meth:`predict_one` through an onnxruntime IOBinding
                (default) instead of ``InferenceSession.run``.

        Raises:
            UserError: card or ONNX missing/unreadable/invalid; the card's digest does not match its
                content; the ONNX bytes' SHA-256 differs from the card's (one line naming both files and
                hashes); the graph's column metadata or the numpy weights disagree with the card.
        """
        path = Path(path)
        card_path = card_path_for(path) if card_path is None else Path(card_path)
        card = ModelCard.read(card_path)
        if path.is_dir():
            raise UserError(f"cannot read ONNX model {path}: is a directory")
        try:
            onnx_bytes = path.read_bytes()
        except OSError as e:
            raise UserError(f"cannot read ONNX model {path}: {e.strerror or e}") from None
        digest = hashlib.sha256(onnx_bytes).hexdigest()
        if digest != card["sha256"]:
            raise UserError(f"{path}: sha256 {digest} does not match sha256 {card['sha256']} "
                            f"recorded in {card_path} (wrong or modified file)")
        return cls(onnx_bytes, card, path=path, card_path=card_path, use_iobinding=use_iobinding)

    def predict(self, X: np.ndarray) -> np.ndarray:
        """SAT estimates (N, n_outputs) in Nm, float64, for feature rows ``X`` (N, n_features)."""
        X = np.asarray(X)
        if X.ndim == 1:
            X = X[None, :]
        if X.ndim != 2 or X.shape[1] != self.n_features:
            raise ValueError(f"expected features of shape (N, {self.n_features}), got {X.shape}")
        if len(X) == 0:
            return np.zeros((0, self.n_outputs))
        y = self.session.run(self._fetch, {self._in_name: np.ascontiguousarray(X, dtype=self._dtype)})[0]
        return y.astype(np.float64, copy=False)

    def predict_one(self, x: Sequence[float] | np.ndarray) -> np.ndarray:
        """SAT estimate (n_outputs,) in Nm, float64, for one feature vector ``x`` (n_features; a list of floats
        or a 1-D array).

        The real-time path: ``x`` is copied into a preallocated input buffer, the
        result into a preallocated output array, which is returned and **overwritten
        by the next call** (copy it to keep it). Not thread-safe.
        """
        if len(x) != self.n_features:
            raise ValueError(f"expected {self.n_features} features, got {len(x)}")
        np.copyto(self._in_row, x, casting="same_kind")
        if self.uses_iobinding:
            self.session.run_with_iobinding(self._binding)
            np.copyto(self._result, self._out_row)
        else:
            np.copyto(self._result, self.session.run(self._fetch, self._feed)[0][0])
        return self._result

    def __repr__(self) -> str:
        return (f"OnnxModel({str(self.path)!r}, {self.n_features} features -> {', '.join(self.outputs)}, "
                f"sha256={self.card['sha256'][:12]})")


# ---------------------------------------------------------------------------------------------------------------
# numpy back-end
# ---------------------------------------------------------------------------------------------------------------


class NumpyForward:
    """Pure-numpy forward pass: ``(x - center) / scale``, then dense layers with the MLP's activations.

    Call it with feature rows (N, n_features) to get (N, n_outputs) float64 in Nm;
    :meth:`predict_one` takes one vector (n_features,) and returns (n_outputs,).
    Same operation order as sklearn, so it matches ``pipeline.predict`` to float64 rounding.
    """

    def __init__(self, weights: Mapping[str, Any]) -> None:
        self.center = None if weights.get("center") is None else np.asarray(weights["center"], float)
        self.scale = None if weights.get("scale") is None else np.asarray(weights["scale"], float)
        self.Ws = [np.ascontiguousarray(layer["W"], dtype=float) for layer in weights["layers"]]
        self.bs = [np.asarray(layer["b"], dtype=float) for layer in weights["layers"]]
        self.activation = str(weights.get("activation", "identity"))
        self.out_activation = str(weights.get("out_activation", "identity"))
        for a in (self.activation, self.out_activation):
            if a not in ACTIVATIONS:
                raise ValueError(f"unsupported activation {a!r} (one of {', '.join(ACTIVATIONS)})")
        for W, b, W_next in zip(self.Ws, self.bs, [*self.Ws[1:], None], strict=True):
            if W.ndim != 2 or b.shape != (W.shape[1],) or (W_next is not None and W_next.shape[0] != W.shape[1]):
                raise ValueError("inconsistent layer shapes in the weights")
        self.n_features = self.Ws[0].shape[0]
        self.n_outputs = self.Ws[-1].shape[1]
        acts = [self.activation] * (len(self.Ws) - 1) + [self.out_activation]
        self._layers = tuple(zip(self.Ws, self.bs, acts, strict=True))

    @staticmethod
    def _act(a: np.ndarray, name: str) -> np.ndarray:
        if name == "tanh":
            return np.tanh(a, out=a)
        if name == "relu":
            return np.maximum(a, 0.0, out=a)
        if name == "logistic":
            return np.divide(1.0, np.add(1.0, np.exp(np.negative(a, out=a), out=a), out=a), out=a)
        return a

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """SAT (N, n_outputs) in Nm for feature rows ``X`` (N, n_features) (or one row (n_features,))."""
        X = np.asarray(X, dtype=float)
        one = X.ndim == 1
        a = X[None, :] if one else X
        if a.ndim != 2 or a.shape[1] != self.n_features:
            raise ValueError(f"expected features of shape (N, {self.n_features}), got {X.shape}")
        a = self._forward(a)
        return a[0] if one else a

    def _forward(self, a: np.ndarray) -> np.ndarray:
        if self.center is not None:
            a = a - self.center
        if self.scale is not None:
            a = a / self.scale
        for W, b, act in self._layers:
            a = a @ W
            a += b
            a = self._act(a, act)
        return a

    def predict_one(self, x: np.ndarray) -> np.ndarray:
        """SAT (n_outputs,) in Nm for one feature vector ``x`` (n_features,) (a new array)."""
        a = np.asarray(x, dtype=float)
        if a.shape != (self.n_features,):
            raise ValueError(f"expected {self.n_features} features, got shape {a.shape}")
        return self._forward(a)


def numpy_forward(pipeline_or_card_weights: Any) -> NumpyForward:
    """A :class:`NumpyForward` from a card's ``weights`` dict or a fitted sklearn pipeline.

    A pipeline goes through :func:`virtsensor.model.export.pipeline_weights` (imported only then:
    it needs scikit-learn).
    """
    if isinstance(pipeline_or_card_weights, Mapping):
        return NumpyForward(pipeline_or_card_weights)
    from virtsensor.model.export import pipeline_weights

    return NumpyForward(pipeline_weights(pipeline_or_card_weights))
