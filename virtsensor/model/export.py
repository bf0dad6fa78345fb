"""Export of a fitted sklearn pipeline to one ONNX graph and its sealed model card.

:func:`export_pipeline` converts the whole fitted pipeline (``RobustScaler`` + ``MLPRegressor``,
or + ``LinearRegression``) to ONE ONNX graph with skl2onnx and writes, beside it,
``<name>.card.json`` (:class:`~virtsensor.model.card.ModelCard`): what the trainer knows
(:meth:`ModelCard.trainer_fields`: inputs, DBC signals, units, ranges, feature definitions, data
fingerprint, metrics, plain weights) plus what this module computes (SHA-256 of the ONNX bytes,
outputs, opset, tool versions, export parity, the parity rows the numpy back-end is checked on at
every load, and the card's own digest). The graph contract is in :mod:`virtsensor.model.onnx`.

skl2onnx (checked with 1.20) ends an ``MLPRegressor`` graph with ``Reshape(shape=[-1, 1])`` and
declares the output ``[None, 1]`` whatever the number of outputs, so a two-output model returns
``(2N, 1)`` (rows interleaved FL, FR, FL, FR...). The linear-regressor graph is already
``(N, n_outputs)``. :func:`export_pipeline` retargets that final ``Reshape`` to ``[-1, n_outputs]``
(or appends one when the graph has none), names the output ``sat``, declares its ValueInfo
``[N, n_outputs]``, records the column names in the graph's metadata, rewrites the graph into the same
function with fewer kernels (:func:`virtsensor.model.leangraph.lean_graph`: the scaler folded into the first
layer, ``MatMul`` + ``Add`` as ``Gemm``, identity ``Cast``/``Reshape`` dropped; the card's ``onnx_rewrites``
lists what was applied), and checks the shape on a 3-row batch and the parity against scikit-learn before
writing anything.

Needs scikit-learn, skl2onnx and onnx (imported when a function runs); the daemon never imports
this module.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.fileio import staged_files
from virtsensor.model import onnx as rt
from virtsensor.model.card import ModelCard, card_path_for
from virtsensor.model.onnx import INPUT_NAME, META_FEATURES, META_OUTPUTS, N_PARITY_INPUTS, OUTPUT_NAME

#: Default ONNX opsets asked of skl2onnx: opset 17 / ai.onnx.ml 3 run on every
#: onnxruntime >= 1.13 (the project requires >= 1.16). skl2onnx may emit a lower
#: opset when no operator needs the higher one; the card records what it emitted.
TARGET_OPSET: dict[str, int] = {"": 17, "ai.onnx.ml": 3}
#: Name of the exported graph. skl2onnx names it with a random UUID unless told, which made two
#: exports of the same fitted pipeline differ in their bytes (and in the card's sha256).
GRAPH_NAME = "virtsensor_sat"
#: Keys :func:`export_pipeline` computes; ``card_extra`` may not set them.
COMPUTED_KEYS = (
    "onnx_file", "sha256", "onnx_input", "onnx_output", "input_dtype", "feature_names", "n_features",
    "outputs", "n_outputs", "opset", "target_opset", "created_utc", "tool_versions", "parity_max_abs_nm",
    "parity_rows", "parity_inputs", "card_sha256", "onnx_rewrites", "rewritten_from",
)

Precision = Literal["float32", "float64"]


def export_pipeline(pipeline: Any, n_features: int, path: str | os.PathLike[str], **options: Any) -> ModelCard:
    """Convert a fitted pipeline to one ONNX file and write its sealed model card beside it: :func:`build_export`
    (every check; arguments and errors as there), then the graph and the card written together (staged, put in
    place once both are written: a failure while writing, a full disk say, leaves neither, an existing pair as
    it was).

    Returns:
        The card as written.
    """
    onnx_bytes, sealed = build_export(pipeline, n_features, path, **options)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sealed.verify()
    card_path = card_path_for(path)
    with staged_files(path, card_path) as (graph, card):
        assert graph is not None and card is not None
        graph.write_bytes(onnx_bytes)
        card.write_bytes(sealed.text().encode("utf-8"))
    sealed.path = card_path
    return sealed


def build_export(
    pipeline: Any,
    n_features: int,
    path: str | os.PathLike[str],
    *,
    card_extra: Mapping[str, Any],
    parity_X: np.ndarray | None = None,
    output_names: Sequence[str] | None = None,
    precision: Precision = "float32",
    target_opset: Mapping[str, int] | None = None,
    lean: bool = True,
) -> ModelCard:
    """A fitted pipeline converted to ONNX and its sealed model card, checked as the runtime loads them, for
    ``path`` (the card names that file and is meant for :func:`card_path_for` it); nothing is written (a caller
    that writes other outputs with them stages all of them: :func:`export_pipeline` writes just these two).

    Args:
        pipeline: fitted sklearn pipeline (e.g. ``RobustScaler`` + ``MLPRegressor``
            or + ``LinearRegression``), 1 or more outputs, predicting SAT in Nm.
        n_features: number of input columns (must equal ``pipeline.n_features_in_``).
        path: where to write the ``.onnx`` file; the card goes to :func:`card_path_for`.
        card_extra: what the caller knows, best built by :meth:`ModelCard.trainer_fields`
            (JSON-serialisable; numpy scalars and arrays are converted). It must name the
            ``n_features`` ordered features, either as ``feature_names`` (list of str) or as
            ``inputs`` (list of str or of dicts with a ``name``) of length ``n_features``, and
            may not set any of :data:`COMPUTED_KEYS`. Its ``weights``, when given, must
            reproduce the graph (checked on the parity rows).
        parity_X: optional rows (N, n_features), in the feature units, on which the
            sklearn and onnxruntime predictions are compared; the largest absolute
            difference goes to the card as ``parity_max_abs_nm`` (Nm), and up to
            :data:`~virtsensor.model.onnx.N_PARITY_INPUTS` of them, evenly spaced, become the
            card's ``parity_inputs`` (without it: :func:`~virtsensor.model.onnx.default_parity_inputs`).
        output_names: catalogue output names of the model's columns; default the
            catalogue :data:`~virtsensor.signals.OUTPUTS` when the model has that many
            outputs (required otherwise, e.g. ``("sat_fl_nm",)`` for a 1-output model).
        precision: ``float32`` (default, what the real-time runtime uses) or ``float64``
            (input, weights and arithmetic in double).
        target_opset: opsets asked of skl2onnx, default :data:`TARGET_OPSET`.
        lean: rewrite the graph with :func:`~virtsensor.model.leangraph.lean_graph` (default); False writes
            skl2onnx's graph as converted (as exports before the rewrite existed).

    Returns:
        ``(onnx_bytes, card)``.

    Raises:
        ValueError: bad arguments, export parity worse than
            :data:`~virtsensor.model.onnx.PARITY_TOL_NM` Nm, or ``weights`` that do not reproduce
            the graph.
    """
    n_features = int(n_features)
    _check_args(pipeline, n_features, card_extra, precision)
    feature_names = _feature_names(card_extra, n_features)
    probe = np.zeros((3, n_features))
    n_outputs = int(np.asarray(pipeline.predict(probe)).reshape(3, -1).shape[1])
    outputs = _outputs(output_names, n_outputs)
    opset = dict(TARGET_OPSET if target_opset is None else target_opset)
    model = _convert(pipeline, n_features, n_outputs, precision, opset, feature_names, outputs)
    model, rewrites = _lean(model) if lean else (model, [])
    onnx_bytes = model.SerializeToString()
    parity = _parity(onnx_bytes, pipeline, probe, parity_X, n_outputs, precision)
    if "parity_inputs" not in parity:
        parity["parity_inputs"] = rt.default_parity_inputs(card_extra.get("weights"), n_features)

    path = Path(path)
    card = {**card_extra, **_computed_fields(model, onnx_bytes, path, precision, feature_names, outputs, opset),
            "onnx_rewrites": rewrites, **parity}
    sealed = ModelCard(card, path=card_path_for(path)).sealed()
    # the whole runtime check (graph metadata, weights on the parity rows) before anything touches the disk
    try:
        rt.OnnxModel(onnx_bytes, sealed, path=path, card_path=card_path_for(path), use_iobinding=False)
    except UserError as exc:
        raise ValueError(f"exported model fails its own load checks: {exc}") from None
    return onnx_bytes, sealed


def _check_args(pipeline: Any, n_features: int, card_extra: Mapping[str, Any], precision: str) -> None:
    """ValueError unless ``pipeline`` is fitted on ``n_features``, ``precision`` is known and ``card_extra`` sets
    none of :data:`COMPUTED_KEYS`."""
    from sklearn.utils.validation import check_is_fitted

    check_is_fitted(pipeline)
    if getattr(pipeline, "n_features_in_", n_features) != n_features:
        raise ValueError(f"pipeline was fitted on {pipeline.n_features_in_} features, n_features={n_features}")
    if precision not in ("float32", "float64"):
        raise ValueError(f"precision must be 'float32' or 'float64', not {precision!r}")
    clash = sorted(set(card_extra) & set(COMPUTED_KEYS))
    if clash:
        raise ValueError(f"card_extra may not set computed card keys: {', '.join(clash)}")


def _computed_fields(model: Any, onnx_bytes: bytes, path: Path, precision: str, feature_names: Sequence[str],
                     outputs: list[dict[str, Any]], opset: Mapping[str, int]) -> dict[str, Any]:
    """The card keys export computes from the graph (see :data:`COMPUTED_KEYS`), parity apart."""
    return {
        "onnx_file": path.name,
        "sha256": hashlib.sha256(onnx_bytes).hexdigest(),
        "onnx_input": INPUT_NAME,
        "onnx_output": OUTPUT_NAME,
        "input_dtype": precision,
        "feature_names": list(feature_names),
        "n_features": len(feature_names),
        "outputs": outputs,
        "n_outputs": len(outputs),
        "opset": {(d.domain or "ai.onnx"): int(d.version) for d in model.opset_import},
        "target_opset": {(k or "ai.onnx"): int(v) for k, v in opset.items()},
        "created_utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "tool_versions": tool_versions(),
    }


def _convert(pipeline: Any, n_features: int, n_outputs: int, precision: str, opset: Mapping[str, int],
             feature_names: Sequence[str], outputs: Sequence[Mapping[str, Any]]) -> Any:
    """skl2onnx conversion, output fixed to ``sat [N, n_outputs]``, column names in the metadata."""
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import DoubleTensorType, FloatTensorType

    tensor_type = FloatTensorType if precision == "float32" else DoubleTensorType
    model = convert_sklearn(pipeline, initial_types=[(INPUT_NAME, tensor_type([None, n_features]))],
                            target_opset=dict(opset), name=GRAPH_NAME)
    # skl2onnx lists the opsets in the order of a set of its own (the string hash's: it changes from one process to
    # the next); sorted, one training gives the same bytes, sha256 and VS_ModelId in every process
    opsets = sorted((d.domain, d.version) for d in model.opset_import)
    del model.opset_import[:]
    for domain, version in opsets:
        entry = model.opset_import.add()
        entry.domain, entry.version = domain, version
    _fix_output(model, n_outputs)
    for key, names in ((META_FEATURES, list(feature_names)), (META_OUTPUTS, [o["name"] for o in outputs])):
        entry = model.metadata_props.add()
        entry.key, entry.value = key, json.dumps(names)
    return model


def _lean(model: Any) -> tuple[Any, list[str]]:
    """The lean rewrite of a copy of ``model`` (:func:`~virtsensor.model.leangraph.lean_graph`; decided from the
    weights alone, so an export stays byte-reproducible) and the rewrites applied; ``model`` itself, and no
    rewrite, should the rewritten graph fail the ONNX checker."""
    import copy

    import onnx

    from virtsensor.model.leangraph import lean_graph

    lean = copy.deepcopy(model)
    try:
        return lean, lean_graph(lean)
    except onnx.checker.ValidationError:
        return model, []


def _parity(onnx_bytes: bytes, pipeline: Any, probe: np.ndarray, parity_X: np.ndarray | None, n_outputs: int,
            precision: str) -> dict[str, Any]:
    """Structural self-check (shape on 3 rows) and sklearn/onnxruntime parity on ``parity_X``."""
    session = rt.make_session(onnx_bytes)[0]
    n_features = probe.shape[1]
    dtype = np.float32 if precision == "float32" else np.float64
    got = session.run([OUTPUT_NAME], {INPUT_NAME: probe.astype(dtype)})[0]
    if got.shape != (3, n_outputs):
        raise RuntimeError(f"exported graph returns shape {got.shape} for 3 rows, expected {(3, n_outputs)}")
    if parity_X is None:
        return {}
    Xp = np.asarray(parity_X, dtype=np.float64)
    if Xp.ndim != 2 or Xp.shape[1] != n_features or len(Xp) == 0:
        raise ValueError(f"parity_X must have shape (N>0, {n_features}), got {Xp.shape}")
    ref = np.asarray(pipeline.predict(Xp), dtype=np.float64).reshape(len(Xp), n_outputs)
    onx = session.run([OUTPUT_NAME], {INPUT_NAME: Xp.astype(dtype)})[0].astype(np.float64)
    err = float(np.max(np.abs(onx - ref)))
    if not err <= rt.PARITY_TOL_NM:  # also catches NaN
        raise ValueError(
            f"ONNX export parity {err:.3g} Nm exceeds {rt.PARITY_TOL_NM:g} Nm on {len(Xp)} rows "
            f"(precision={precision}); nothing written"
            + ("; float32 rounding grows with the weights: try precision='float64'" if precision == "float32"
               else "")
        )
    pick = np.unique(np.linspace(0, len(Xp) - 1, min(N_PARITY_INPUTS, len(Xp))).round().astype(int))
    return {"parity_max_abs_nm": err, "parity_rows": len(Xp), "parity_inputs": Xp[pick].tolist()}


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
    ``[-1, n_outputs]`` is appended. The output is
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
