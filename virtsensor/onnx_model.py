"""The deployed estimator: one ONNX file plus its model card, and the runtime that loads them.

Export (:func:`export_pipeline`) converts the whole fitted sklearn pipeline
(``RobustScaler`` + ``MLPRegressor``, or + ``LinearRegression``) to ONE ONNX
graph with skl2onnx and writes, beside it, ``<name>.card.json``: what the
trainer knows (inputs, DBC signals, units, ranges, feature definitions, data
fingerprint, metrics) plus what this module computes (SHA-256 of the ONNX
bytes, outputs, opset, tool versions, export parity).

Graph contract (what a runtime in any language may rely on):

* one input ``features``: float32 (or float64 with ``precision="float64"``),
  shape ``[N, n_features]``, columns in the card's ``feature_names`` order,
  each in the unit the card gives it (SI, catalogue units);
* one output ``sat``: same dtype, shape ``[N, n_outputs]``, columns in the
  card's ``outputs`` order, in Nm (tyre self-aligning torque, ISO-W, see
  :mod:`virtsensor.signals`).

skl2onnx (checked with 1.20) ends an ``MLPRegressor`` graph with
``Reshape(shape=[-1, 1])`` and declares the output ``[None, 1]`` whatever the
number of outputs, so a two-output model returns ``(2N, 1)`` (rows interleaved
FL, FR, FL, FR...). The linear-regressor graph is already ``(N, n_outputs)``.
:func:`export_pipeline` retargets that final ``Reshape`` to ``[-1, n_outputs]``
(or appends one when the graph has none), names the output ``sat``, declares
its ValueInfo ``[N, n_outputs]``, and checks the shape on a 3-row batch before
writing anything.

Runtime (:class:`OnnxModel`) verifies the card's SHA-256 against the ONNX
bytes, runs onnxruntime single-threaded on the CPU with spinning off, and has
an allocation-lean ``predict_one`` for the 20 Hz real-time path.

:func:`numpy_forward` is the same forward pass in plain numpy (a back-end for
the latency comparison and an independent check of the exported weights).
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import tempfile
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError

#: Largest |sklearn - onnxruntime| difference (Nm) export accepts on ``parity_X``.
PARITY_TOL_NM = 1e-3
#: Default ONNX opsets asked of skl2onnx: opset 17 / ai.onnx.ml 3 run on every
#: onnxruntime >= 1.13 (the project requires >= 1.16). skl2onnx may emit a lower
#: opset when no operator needs the higher one; the card records what it emitted.
TARGET_OPSET: dict[str, int] = {"": 17, "ai.onnx.ml": 3}
INPUT_NAME = "features"
OUTPUT_NAME = "sat"
#: Name of the exported graph. skl2onnx names it with a random UUID unless told, which made two
#: exports of the same fitted pipeline differ in their bytes (and in the card's sha256).
GRAPH_NAME = "virtsensor_sat"
#: Keys :func:`export_pipeline` computes; ``card_extra`` may not set them.
COMPUTED_KEYS = (
    "onnx_file", "sha256", "onnx_input", "onnx_output", "input_dtype", "feature_names", "n_features",
    "outputs", "n_outputs", "opset", "target_opset", "created_utc", "tool_versions", "parity_max_abs_nm",
    "parity_rows",
)

Precision = Literal["float32", "float64"]


# ---------------------------------------------------------------------------------------------------------------
# export
# ---------------------------------------------------------------------------------------------------------------
def card_path_for(onnx_path: str | os.PathLike[str]) -> Path:
    """The model-card path beside ``onnx_path``: ``models/sat.onnx`` -> ``models/sat.card.json``."""
    p = Path(onnx_path)
    return p.with_name(f"{p.stem if p.suffix == '.onnx' else p.name}.card.json")


def export_pipeline(
    pipeline: Any,
    n_features: int,
    path: str | os.PathLike[str],
    *,
    card_extra: Mapping[str, Any],
    parity_X: np.ndarray | None = None,
    output_names: Sequence[str] | None = None,
    precision: Precision = "float32",
    target_opset: Mapping[str, int] | None = None,
) -> dict[str, Any]:
    """Convert a fitted pipeline to one ONNX file and write its model card beside it.

    Args:
        pipeline: fitted sklearn pipeline (e.g. ``RobustScaler`` + ``MLPRegressor``
            or + ``LinearRegression``), 1 or more outputs, predicting SAT in Nm.
        n_features: number of input columns (must equal ``pipeline.n_features_in_``).
        path: where to write the ``.onnx`` file; the card goes to :func:`card_path_for`.
        card_extra: what the caller knows (JSON-serialisable; numpy scalars and
            arrays are converted). It must name the ``n_features`` ordered features,
            either as ``feature_names`` (list of str) or as ``inputs`` (list of str
            or of dicts with a ``name``) of length ``n_features``. It may not set
            any of :data:`COMPUTED_KEYS`.
        parity_X: optional rows (N, n_features), in the feature units, on which the
            sklearn and onnxruntime predictions are compared; the largest absolute
            difference goes to the card as ``parity_max_abs_nm`` (Nm).
        output_names: catalogue output names of the model's columns; default the
            catalogue :data:`~virtsensor.signals.OUTPUTS` when the model has that many
            outputs (required otherwise, e.g. ``("sat_fl_nm",)`` for a 1-output model).
        precision: ``float32`` (default, what the real-time runtime uses) or ``float64``
            (input, weights and arithmetic in double).
        target_opset: opsets asked of skl2onnx, default :data:`TARGET_OPSET`.

    Returns:
        The card as written (read back from its JSON).

    Raises:
        ValueError: bad arguments, or export parity worse than :data:`PARITY_TOL_NM` Nm
            (nothing is written then).
    """
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import DoubleTensorType, FloatTensorType
    from sklearn.utils.validation import check_is_fitted

    check_is_fitted(pipeline)
    n_features = int(n_features)
    if getattr(pipeline, "n_features_in_", n_features) != n_features:
        raise ValueError(f"pipeline was fitted on {pipeline.n_features_in_} features, n_features={n_features}")
    if precision not in ("float32", "float64"):
        raise ValueError(f"precision must be 'float32' or 'float64', not {precision!r}")
    clash = sorted(set(card_extra) & set(COMPUTED_KEYS))
    if clash:
        raise ValueError(f"card_extra may not set computed card keys: {', '.join(clash)}")
    feature_names = _feature_names(card_extra, n_features)

    probe = np.zeros((3, n_features))
    n_outputs = int(np.asarray(pipeline.predict(probe)).reshape(3, -1).shape[1])
    outputs = _outputs(output_names, n_outputs)

    opset = dict(TARGET_OPSET if target_opset is None else target_opset)
    tensor_type = FloatTensorType if precision == "float32" else DoubleTensorType
    model = convert_sklearn(pipeline, initial_types=[(INPUT_NAME, tensor_type([None, n_features]))],
                            target_opset=opset, name=GRAPH_NAME)
    _fix_output(model, n_outputs)
    onnx_bytes = model.SerializeToString()

    # Structural self-check and parity, before anything touches the disk.
    session = _session(onnx_bytes)[0]
    dtype = np.float32 if precision == "float32" else np.float64
    got = session.run([OUTPUT_NAME], {INPUT_NAME: probe.astype(dtype)})[0]
    if got.shape != (3, n_outputs):
        raise RuntimeError(f"exported graph returns shape {got.shape} for 3 rows, expected {(3, n_outputs)}")
    parity: dict[str, Any] = {}
    if parity_X is not None:
        Xp = np.asarray(parity_X, dtype=np.float64)
        if Xp.ndim != 2 or Xp.shape[1] != n_features or len(Xp) == 0:
            raise ValueError(f"parity_X must have shape (N>0, {n_features}), got {Xp.shape}")
        ref = np.asarray(pipeline.predict(Xp), dtype=np.float64).reshape(len(Xp), n_outputs)
        onx = session.run([OUTPUT_NAME], {INPUT_NAME: Xp.astype(dtype)})[0].astype(np.float64)
        err = float(np.max(np.abs(onx - ref)))
        if not err <= PARITY_TOL_NM:  # also catches NaN
            raise ValueError(
                f"ONNX export parity {err:.3g} Nm exceeds {PARITY_TOL_NM:g} Nm on {len(Xp)} rows "
                f"(precision={precision}); nothing written"
                + ("; float32 rounding grows with the weights: try precision='float64'" if precision == "float32"
                   else "")
            )
        parity = {"parity_max_abs_nm": err, "parity_rows": len(Xp)}

    path = Path(path)
    card: dict[str, Any] = dict(card_extra)
    card.update(
        onnx_file=path.name,
        sha256=hashlib.sha256(onnx_bytes).hexdigest(),
        onnx_input=INPUT_NAME,
        onnx_output=OUTPUT_NAME,
        input_dtype=precision,
        feature_names=list(feature_names),
        n_features=n_features,
        outputs=outputs,
        n_outputs=n_outputs,
        opset={(d.domain or "ai.onnx"): int(d.version) for d in model.opset_import},
        target_opset={(k or "ai.onnx"): int(v) for k, v in opset.items()},
        created_utc=datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        tool_versions=tool_versions(),
        **parity,
    )
    card_text = json.dumps(card, indent=2, allow_nan=False, default=_json_default) + "\n"
    _atomic_write(path, onnx_bytes)
    _atomic_write(card_path_for(path), card_text.encode("utf-8"))
    return json.loads(card_text)


def tool_versions() -> dict[str, str]:
    """Versions of the tools that make and run the model (recorded in the card)."""
    import onnx
    import onnxruntime
    import skl2onnx
    import sklearn

    import virtsensor

    return {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scikit-learn": sklearn.__version__,
        "skl2onnx": skl2onnx.__version__,
        "onnx": onnx.__version__,
        "onnxruntime": onnxruntime.__version__,
        "virtsensor": virtsensor.__version__,
    }


def _feature_names(card_extra: Mapping[str, Any], n_features: int) -> tuple[str, ...]:
    if "feature_names" in card_extra:
        names = [str(n) for n in card_extra["feature_names"]]
    elif "inputs" in card_extra:
        names = [str(i if isinstance(i, str) else i["name"]) for i in card_extra["inputs"]]
    else:
        raise ValueError(f"card_extra must list the {n_features} ordered features as 'feature_names' or 'inputs'")
    if len(names) != n_features or len(set(names)) != n_features:
        raise ValueError(f"card_extra names {len(names)} features ({len(set(names))} distinct), "
                         f"the model has {n_features}")
    return tuple(names)


def _outputs(output_names: Sequence[str] | None, n_outputs: int) -> list[dict[str, Any]]:
    if output_names is None:
        if n_outputs != len(cat.OUTPUTS):
            raise ValueError(f"the model has {n_outputs} output(s): pass output_names (catalogue outputs "
                             f"{', '.join(cat.OUTPUTS)})")
        output_names = cat.OUTPUTS
    if len(output_names) != n_outputs:
        raise ValueError(f"{len(output_names)} output_names for a model with {n_outputs} output(s)")
    out = []
    for name in output_names:
        s = cat.signal(name)
        if s.role not in ("output", "truth") or s.unit != "Nm":
            raise ValueError(f"output {name!r} is not a catalogued torque output (role {s.role}, unit {s.unit})")
        out.append({"name": s.name, "unit": s.unit, "minimum": s.minimum, "maximum": s.maximum,
                    "description": s.description})
    return out


def _fix_output(model: Any, n_outputs: int) -> None:
    """Make the single graph output ``sat`` of shape ``[N, n_outputs]`` (in place).

    When the graph ends with a ``Reshape`` whose target shape is a constant of its
    own (skl2onnx's ``[-1, 1]`` after an MLPRegressor), that constant becomes
    ``[-1, n_outputs]`` (row-major, so FL/FR land in the right columns); otherwise
    (e.g. a linear regressor, already ``(N, n_outputs)``) a ``Reshape`` to
    ``[-1, n_outputs]`` is appended (about 0.4 us more at batch 1). The output is
    renamed ``sat`` and declared ``[N, n_outputs]``; the input's batch dimension
    is named ``N`` too. The ONNX checker then runs strict shape inference.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    g = model.graph
    if len(g.output) != 1 or len(g.input) != 1:
        raise RuntimeError(f"expected one input and one output, skl2onnx made {len(g.input)} and {len(g.output)}")
    raw = g.output[0]
    elem_type = raw.type.tensor_type.elem_type
    if elem_type not in (TensorProto.FLOAT, TensorProto.DOUBLE):
        raise RuntimeError(f"unexpected output element type {elem_type}")
    taken = {v for n in g.node for v in (*n.input, *n.output)} | {i.name for i in g.initializer}
    if OUTPUT_NAME in taken or "sat_shape" in taken:
        raise RuntimeError(f"skl2onnx graph already uses the name {OUTPUT_NAME!r} or 'sat_shape'")
    target = numpy_helper.from_array(np.array([-1, n_outputs], dtype=np.int64), "sat_shape")
    inputs = [v for n in g.node for v in n.input]
    last = g.node[-1] if len(g.node) else None
    inits = {i.name: i for i in g.initializer}
    if (last is not None and last.op_type == "Reshape" and list(last.output) == [raw.name] and len(last.input) == 2
            and last.input[1] in inits and inputs.count(last.input[1]) == 1 and raw.name not in inputs):
        target.name = last.input[1]
        inits[last.input[1]].CopyFrom(target)
        last.output[0] = OUTPUT_NAME
    else:
        g.initializer.append(target)
        g.node.append(helper.make_node("Reshape", [raw.name, target.name], [OUTPUT_NAME], name="sat_reshape"))
    del g.output[:]
    g.output.append(helper.make_tensor_value_info(OUTPUT_NAME, elem_type, ["N", n_outputs]))
    g.input[0].type.tensor_type.shape.dim[0].dim_param = "N"
    onnx.checker.check_model(model, full_check=True)  # strict shape inference: the declared shapes must agree


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"card value of type {type(obj).__name__} is not JSON-serialisable")


def _atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the new one, never half of one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.fchmod(fd, 0o644)  # mkstemp makes 0600; a model file is meant to be read by the daemon's user
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if hasattr(os, "O_DIRECTORY"):  # make the rename itself durable (POSIX)
        dfd = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


# ---------------------------------------------------------------------------------------------------------------
# runtime
# ---------------------------------------------------------------------------------------------------------------
def session_options() -> Any:
    """onnxruntime options of the real-time runtime: one thread, sequential, no spinning.

    Spinning threads would burn a core waiting for work between 20 Hz ticks; one
    thread is faster than a pool for a 12-32-12-2 MLP anyway.
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


def _session(onnx_bytes: bytes) -> tuple[Any, Any]:
    import onnxruntime as ort

    so = session_options()
    return ort.InferenceSession(onnx_bytes, sess_options=so, providers=["CPUExecutionProvider"]), so


class OnnxModel:
    """An exported estimator loaded for inference (see :meth:`load`).

    Attributes:
        card: the model card (dict).
        input_names: ordered feature names (the card's ``feature_names``), each in
            the unit the card gives it.
        n_features: number of features.
        outputs: ordered output names (catalogue names, Nm), e.g. ``("sat_fl_nm", "sat_fr_nm")``.
        n_outputs: number of outputs.
        path, card_path: the files it was loaded from.
        session: the onnxruntime ``InferenceSession``.
        session_options: the ``SessionOptions`` it was created with.
        uses_iobinding: whether :meth:`predict_one` runs through an IOBinding.

    ``predict`` is safe to call from several threads; ``predict_one`` is not (it
    reuses its buffers).
    """

    def __init__(self, onnx_bytes: bytes, card: Mapping[str, Any], *, path: Path, card_path: Path,
                 use_iobinding: bool = True) -> None:
        self.card = dict(card)
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
            self.session, self.session_options = _session(onnx_bytes)
        except Exception as e:  # onnxruntime raises its own exception types
            raise UserError(f"{path}: onnxruntime cannot load it: {str(e).splitlines()[0]}") from None
        inp, out = self.session.get_inputs(), self.session.get_outputs()
        if [i.name for i in inp] != [in_name] or [o.name for o in out] != [out_name]:
            raise UserError(f"{path}: graph has inputs {[i.name for i in inp]} / outputs {[o.name for o in out]}, "
                            f"{card_path} says {in_name!r} / {out_name!r}")
        if inp[0].shape[1:] != [self.n_features] or out[0].shape[1:] != [self.n_outputs]:
            raise UserError(f"{path}: graph shapes {inp[0].shape} -> {out[0].shape} disagree with {card_path} "
                            f"({self.n_features} features, {self.n_outputs} outputs)")
        self._in_name, self._out_name = in_name, out_name
        self._dtype = {"tensor(float)": np.float32, "tensor(double)": np.float64}.get(inp[0].type)
        if self._dtype is None:
            raise UserError(f"{path}: unsupported input type {inp[0].type}")

        # Real-time path: buffers allocated once; the IOBinding wraps their memory (no copies).
        self._in_buf = np.zeros((1, self.n_features), dtype=self._dtype)
        self._out_buf = np.zeros((1, self.n_outputs), dtype=self._dtype)
        self._in_row = self._in_buf[0]
        self._out_row = self._out_buf[0]
        self._result = np.zeros(self.n_outputs, dtype=np.float64)
        self._feed = {in_name: self._in_buf}
        self._fetch = [out_name]
        self.uses_iobinding = bool(use_iobinding)
        if self.uses_iobinding:
            import onnxruntime as ort

            self._in_ort = ort.OrtValue.ortvalue_from_numpy(self._in_buf)
            self._out_ort = ort.OrtValue.ortvalue_from_numpy(self._out_buf)
            self._binding = self.session.io_binding()
            self._binding.bind_ortvalue_input(in_name, self._in_ort)
            self._binding.bind_ortvalue_output(out_name, self._out_ort)

    @classmethod
    def load(cls, path: str | os.PathLike[str], card_path: str | os.PathLike[str] | None = None, *,
             use_iobinding: bool = True) -> OnnxModel:
        """Load ``path`` (ONNX) after checking it against its card.

        Args:
            path: the ``.onnx`` file.
            card_path: its model card; default :func:`card_path_for` ``(path)``.
            use_iobinding: run :meth:`predict_one` through an onnxruntime IOBinding
                (default; measured faster than ``run`` at batch 1).

        Raises:
            UserError: card or ONNX missing/unreadable/invalid, or the ONNX bytes'
                SHA-256 differs from the card's (one line naming both files and hashes).
        """
        path = Path(path)
        card_path = card_path_for(path) if card_path is None else Path(card_path)
        try:
            card_text = card_path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise UserError(f"cannot read model card {card_path}: {_reason(e)}") from None
        try:
            card = json.loads(card_text)
        except json.JSONDecodeError as e:
            raise UserError(f"{card_path}:{e.lineno}: model card is not valid JSON: {e.msg}") from None
        if not isinstance(card, dict) or not isinstance(card.get("sha256"), str):
            raise UserError(f"{card_path}: not a model card (no sha256)")
        try:
            onnx_bytes = path.read_bytes()
        except OSError as e:
            raise UserError(f"cannot read ONNX model {path}: {_reason(e)}") from None
        digest = hashlib.sha256(onnx_bytes).hexdigest()
        if digest != card["sha256"].lower():
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

    def predict_one(self, x: np.ndarray) -> np.ndarray:
        """SAT estimate (n_outputs,) in Nm, float64, for one feature vector ``x`` (n_features,).

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


def _reason(e: BaseException) -> str:
    return getattr(e, "strerror", None) or str(e)


# ---------------------------------------------------------------------------------------------------------------
# numpy back-end
# ---------------------------------------------------------------------------------------------------------------
_ACTIVATIONS = ("identity", "tanh", "relu", "logistic")


def pipeline_weights(pipeline: Any) -> dict[str, Any]:
    """The weights of a ``[scaler] + MLPRegressor|LinearRegression`` pipeline as plain lists (JSON-able).

    The scaler (Robust, Standard or MinMax, as the grid search may pick) becomes
    ``(x - center) / scale``.

    Keys: ``center``/``scale`` (feature units, or None when the scaler does not
    centre/scale or is absent), ``layers`` (list of ``{"W": (n_in, n_out), "b": (n_out,)}``),
    ``activation`` (hidden layers) and ``out_activation``. Outputs are in Nm.
    """
    from sklearn.linear_model import LinearRegression
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import MinMaxScaler, RobustScaler, StandardScaler

    steps = [s for _, s in pipeline.steps] if isinstance(pipeline, Pipeline) else [pipeline]
    steps = [s for s in steps if s not in (None, "passthrough")]
    center = scale = None

    def as_list(a):
        return None if a is None else np.asarray(a, float).tolist()

    if len(steps) == 2 and isinstance(steps[0], RobustScaler):
        center, scale = as_list(steps[0].center_), as_list(steps[0].scale_)
    elif len(steps) == 2 and isinstance(steps[0], StandardScaler):
        center, scale = as_list(steps[0].mean_), as_list(steps[0].scale_)
    elif len(steps) == 2 and isinstance(steps[0], MinMaxScaler):
        # x * scale_ + min_ == (x - (-min_ / scale_)) / (1 / scale_)
        k = np.asarray(steps[0].scale_, float)
        center, scale = (-np.asarray(steps[0].min_, float) / k).tolist(), (1.0 / k).tolist()
    elif len(steps) != 1:
        raise TypeError("numpy forward supports [Robust|Standard|MinMax scaler] + MLPRegressor|LinearRegression, "
                        f"got {steps}")
    est = steps[-1]
    if isinstance(est, MLPRegressor):
        layers = [{"W": np.asarray(W, float).tolist(), "b": np.asarray(b, float).tolist()}
                  for W, b in zip(est.coefs_, est.intercepts_, strict=True)]
        activation, out_activation = est.activation, est.out_activation_
    elif isinstance(est, LinearRegression):
        coef = np.atleast_2d(np.asarray(est.coef_, float))
        layers = [{"W": coef.T.tolist(), "b": np.atleast_1d(np.asarray(est.intercept_, float)).tolist()}]
        activation, out_activation = "identity", "identity"
    else:
        raise TypeError(f"numpy forward supports MLPRegressor and LinearRegression, not {type(est).__name__}")
    return {"center": center, "scale": scale, "layers": layers, "activation": activation,
            "out_activation": out_activation}


class NumpyForward:
    """Pure-numpy forward pass: ``(x - center) / scale``, then dense layers with the MLP's activations.

    Call it with feature rows (N, n_features) to get (N, n_outputs) float64 in Nm;
    :meth:`predict_one` takes one vector (n_features,) and returns (n_outputs,).
    Same operation order as sklearn, so it matches ``pipeline.predict`` to ~1e-13 Nm.
    """

    def __init__(self, weights: Mapping[str, Any]) -> None:
        self.center = None if weights.get("center") is None else np.asarray(weights["center"], float)
        self.scale = None if weights.get("scale") is None else np.asarray(weights["scale"], float)
        self.Ws = [np.ascontiguousarray(layer["W"], dtype=float) for layer in weights["layers"]]
        self.bs = [np.asarray(layer["b"], dtype=float) for layer in weights["layers"]]
        self.activation = str(weights.get("activation", "identity"))
        self.out_activation = str(weights.get("out_activation", "identity"))
        for a in (self.activation, self.out_activation):
            if a not in _ACTIVATIONS:
                raise ValueError(f"unsupported activation {a!r} (one of {', '.join(_ACTIVATIONS)})")
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
    """A :class:`NumpyForward` from a fitted pipeline or from a :func:`pipeline_weights` dict."""
    if isinstance(pipeline_or_card_weights, Mapping):
        return NumpyForward(pipeline_or_card_weights)
    return NumpyForward(pipeline_weights(pipeline_or_card_weights))
