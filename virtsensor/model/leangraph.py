"""The exported graph with fewer kernels: skl2onnx's scaler + MLP rewritten into the same function.

skl2onnx (checked with 1.20) converts ``[scaler] + MLPRegressor`` into::

    Scaler(offset o, scale s) -> Cast -> (MatMul W_k -> Add b_k -> activation)* -> MatMul -> Add -> Reshape

onnxruntime infers no shape past the ``ai.onnx.ml`` ``Scaler``, so it fuses nothing and runs ten kernels per
call for two hidden layers. Each kernel costs its dispatch, and far more on caches gone cold between the
daemon's 20 Hz ticks. :func:`lean_graph` rewrites, in place, what it recognises:

1. **the scaler folded into the first layer**: skl2onnx writes the scaler as an ``ai.onnx.ml`` ``Scaler``
   (float32 graphs) or as ``Sub``/``Div`` (Robust, Standard) and ``Mul``/``Add`` (MinMax) by constants; any such
   chain is ``x * a + d`` per feature, and ``(x * a + d) W + b = x (a[:, None] * W) + (b + d W)``, computed in
   float64 and stored in the graph's type. Folding the centre into the bias makes the first layer add terms
   larger than the centred ones it replaces, so its rounding error grows by the factor :func:`fold_amplification`
   (from the weights alone: the choice is the same on every machine and for every data set); beyond
   :data:`MAX_FOLD_AMPLIFICATION` only the scale is folded and the centring stays one ``Sub`` (``fold_scale``);
2. **MatMul + Add -> Gemm**: a ``MatMul`` by a 2-D initializer whose only consumer adds a bias initializer
   (``[n]`` or ``[1, n]``);
3. **identities dropped**: a ``Cast`` to the type its input already has, and the final ``Reshape`` to
   ``[-1, n]`` of a ``Gemm`` that already gives ``[N, n]``.

onnxruntime then fuses each ``Gemm`` + activation into one ``FusedGemm``: three kernels for two hidden layers.
A step whose pattern is not there (a linear regressor, another converter's graph, a tensor that is also a graph
output or is read twice) changes nothing, so the result is a graph of the same function up to float rounding;
:func:`virtsensor.model.export.export_pipeline` checks it against scikit-learn (``parity_max_abs_nm``) and the
model card's plain weights before writing it. What it saves per inference: README, "Measured figures".

Needs ``onnx`` (the export side; the daemon never imports this module).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["lean_graph"]

_FLOAT_TYPES = {1: np.float32, 11: np.float64}  # TensorProto.FLOAT, DOUBLE
#: The most :func:`fold_amplification` may be for the centre to fold into the bias: 8 costs the first layer at
#: most 3 of float32's 24 bits (the shipped models: 1.7, 1.7 and 4.1).
MAX_FOLD_AMPLIFICATION = 8.0
#: element-wise ops by a constant that :func:`_fold_scaler` composes: y = x * a + d
_AFFINE_OPS = ("Sub", "Div", "Mul", "Add")


def lean_graph(model: Any, *, fold_centre: bool | None = None) -> list[str]:
    """Rewrite ``model`` (an ``onnx.ModelProto``) in place; returns the names of the rewrites applied
    (``drop_cast``, ``fold_scaler`` or ``fold_scale``, ``gemm`` per fused layer, ``drop_reshape``), in order. A
    graph without exactly one input and one output is left as it is (``[]``).

    ``fold_centre``: fold the scaler's centre into the bias too (True), keep it as a ``Sub`` (False), or decide by
    :func:`fold_amplification` against :data:`MAX_FOLD_AMPLIFICATION` (None, the default).

    Raises:
        onnx.checker.ValidationError: the rewritten graph fails the ONNX checker (full shape inference): a bug
            here, never a property of the model (the caller keeps its unrewritten copy).
    """
    import onnx

    g = model.graph
    if len(g.input) != 1 or len(g.output) != 1:
        return []
    done: list[str] = []
    done += _drop_identity_casts(g)
    folded = _fold_scaler(g, fold_centre)
    if folded:
        done.append(folded)
    done += _matmul_add_to_gemm(model)
    if _drop_final_reshape(g):
        done.append("drop_reshape")
    _drop_unused_initializers(g)
    onnx.checker.check_model(model, full_check=True)
    return done


def fold_amplification(d: np.ndarray, W: np.ndarray, b: np.ndarray) -> float:
    """How much folding a scaler's centre into the bias grows the first layer's rounding error, for the scaler
    ``y = x * a + d`` (per feature) before ``y W + b``: the largest, over the layer's units ``j``, of
    ``(sum_i (|d_i| + 1) |W_ij| + |b_j + (d W)_j|) / (sum_i |W_ij| + |b_j|)``: the magnitudes the folded layer
    sums (``x a`` within one spread of ``-d``, and the folded bias) over those the centred one sums (scaled
    inputs of about one, and the bias). 1 when nothing is centred (``d = 0``)."""
    W64 = np.asarray(W, np.float64)
    d64 = np.asarray(d, np.float64).reshape(-1)
    b64 = np.asarray(b, np.float64).reshape(-1)
    aW = np.abs(W64)
    folded = ((np.abs(d64) + 1.0)[:, None] * aW).sum(0) + np.abs(b64 + d64 @ W64)
    centred = aW.sum(0) + np.abs(b64)
    return float(np.max(folded / np.maximum(centred, np.finfo(np.float64).tiny)))


def _consumers(g: Any, name: str) -> list[Any]:
    """The nodes that read tensor ``name``."""
    return [n for n in g.node if name in n.input]


def _init(g: Any, name: str) -> np.ndarray | None:
    """Initializer ``name`` as an array (None: no such initializer)."""
    from onnx import numpy_helper

    for i in g.initializer:
        if i.name == name:
            return numpy_helper.to_array(i)
    return None


def _set_init(g: Any, name: str, value: np.ndarray) -> None:
    """Set (replace or add) initializer ``name``."""
    from onnx import numpy_helper

    for i in g.initializer:
        if i.name == name:
            i.CopyFrom(numpy_helper.from_array(value, name))
            return
    g.initializer.append(numpy_helper.from_array(value, name))


def _fresh(g: Any, base: str) -> str:
    """A tensor or node name starting with ``base`` that the graph does not use yet."""
    taken = {v for n in g.node for v in (*n.input, *n.output)} | {i.name for i in g.initializer}
    k, name = 0, base
    while name in taken:
        k += 1
        name = f"{base}_{k}"
    return name


def _elem_type(g: Any, name: str, depth: int = 0) -> int | None:
    """Element type of tensor ``name`` where it is evident: a graph input's, an initializer's, a ``Scaler``'s
    (always float), an element-wise op's (that of its non-constant input), a ``Cast``'s target; else None."""
    for v in g.input:
        if v.name == name:
            return int(v.type.tensor_type.elem_type)
    for i in g.initializer:
        if i.name == name:
            return int(i.data_type)
    producer = next((p for p in g.node if name in p.output), None)
    if producer is None or depth > 16:
        return None
    if producer.op_type == "Scaler" and producer.domain == "ai.onnx.ml":
        return 1  # TensorProto.FLOAT
    if producer.op_type == "Cast":
        return next((int(a.i) for a in producer.attribute if a.name == "to"), None)
    if producer.op_type in _AFFINE_OPS:
        types = {_elem_type(g, v, depth + 1) for v in producer.input}
        return types.pop() if len(types) == 1 else None
    return None


def _drop_identity_casts(g: Any) -> list[str]:
    """Remove ``Cast`` nodes whose input evidently has the target type already (:func:`_elem_type`)."""
    out: list[str] = []
    for n in list(g.node):
        if n.op_type != "Cast" or n.domain not in ("", "ai.onnx"):
            continue
        to = next((a.i for a in n.attribute if a.name == "to"), None)
        src = n.input[0]
        if to is None or _elem_type(g, src) != to or any(o.name == n.output[0] for o in g.output):
            continue
        for c in _consumers(g, n.output[0]):
            for k, v in enumerate(c.input):
                if v == n.output[0]:
                    c.input[k] = src
        g.node.remove(n)
        out.append("drop_cast")
    return out


def _affine_step(g: Any, n: Any, src: str, a: np.ndarray, d: np.ndarray) -> bool:
    """Compose ``n`` (reading ``src``) into ``y = x * a + d`` (in place); False when it is not an element-wise
    affine op by a constant that broadcasts over the features."""
    if n.op_type == "Scaler" and n.domain == "ai.onnx.ml":  # y = (x - offset) * scale
        attrs = {at.name: list(at.floats) for at in n.attribute}
        o = np.asarray(attrs.get("offset", [0.0]), np.float64)
        s = np.asarray(attrs.get("scale", [1.0]), np.float64)
        if o.size not in (1, a.size) or s.size not in (1, a.size):
            return False
        d -= o
        a *= s
        d *= s
        return True
    if n.op_type not in _AFFINE_OPS or n.domain not in ("", "ai.onnx") or list(n.input).count(src) != 1:
        return False
    other = n.input[1] if n.input[0] == src else n.input[0]
    k = _init(g, other)
    if k is None or k.size not in (1, a.size) or k.ndim > 2 or (k.ndim == 2 and k.shape[0] != 1):
        return False
    k = k.astype(np.float64).reshape(-1)
    if n.op_type == "Add":
        d += k
    elif n.op_type == "Mul":
        a *= k
        d *= k
    elif n.input[0] != src:  # k - x, k / x: not affine in x the same way
        return False
    elif n.op_type == "Sub":
        d -= k
    else:
        a /= k
        d /= k
    return True


def _fold_scaler(g: Any, fold_centre: bool | None) -> str | None:
    """Fold the element-wise affine chain on the graph input (an ``ai.onnx.ml`` ``Scaler``, or ``Sub``/``Div``/
    ``Mul``/``Add`` by constants, as skl2onnx writes the Robust, Standard and MinMax scalers; an identity
    ``Cast`` already dropped) into the ``MatMul`` + ``Add`` that alone reads its end: with ``y = x * a + d``,
    ``y W + b = x (a[:, None] * W) + (b + d W)`` (``fold_scaler``); or, the centre kept (``fold_centre`` False, or
    None and :func:`fold_amplification` above :data:`MAX_FOLD_AMPLIFICATION`), ``y W + b = (x - c) (a[:, None] *
    W) + b`` with ``c = -d / a``, one ``Sub`` (``fold_scale``). Returns the rewrite's name, None when there is no
    such chain (or one of its tensors is a graph output or read twice)."""
    inp = g.input[0]
    dtype = _FLOAT_TYPES.get(int(inp.type.tensor_type.elem_type))
    if dtype is None:
        return None
    outputs = {v.name for v in g.output}
    chain: list[Any] = []
    src, nxt = inp.name, _consumers(g, inp.name)
    a = d = None
    while len(nxt) == 1 and nxt[0].op_type != "MatMul":
        n = nxt[0]
        if a is None or d is None:
            n_in = _first_matmul_rows(g)
            if n_in is None:
                return None
            a, d = np.ones(n_in), np.zeros(n_in)
        if n.output[0] in outputs or not _affine_step(g, n, src, a, d):
            return None
        chain.append(n)
        src, nxt = n.output[0], _consumers(g, n.output[0])
    if not chain or a is None or d is None or len(nxt) != 1:
        return None
    mm = nxt[0]
    W = _init(g, mm.input[1])
    adds = _consumers(g, mm.output[0])
    if (mm.input[0] != src or W is None or W.ndim != 2 or W.dtype != dtype or W.shape[0] != a.size
            or len(_consumers(g, mm.input[1])) != 1 or len(adds) != 1 or adds[0].op_type != "Add"
            or mm.output[0] in outputs):
        return None
    add = adds[0]
    b_name = add.input[1] if add.input[0] == mm.output[0] else add.input[0]
    b = _init(g, b_name)
    if b is None or b.size != W.shape[1] or len(_consumers(g, b_name)) != 1:
        return None
    W64, b64 = W.astype(np.float64), b.astype(np.float64).reshape(-1)
    if fold_centre is None:
        fold_centre = fold_amplification(d, W64, b64) <= MAX_FOLD_AMPLIFICATION
    if not fold_centre:  # x * a + d = (x - c) * a with c = -d / a: the centring stays a Sub, a folds into W
        live = a != 0.0
        c = np.where(live, -d / np.where(live, a, 1.0), 0.0)
        b64 = b64 + np.where(live, 0.0, d) @ W64
        centre = _fresh(g, "lean_centre")
        _set_init(g, centre, c.astype(dtype))
        centred = _fresh(g, "lean_centred")
        g.node.insert(list(g.node).index(chain[0]), _sub_node(inp.name, centre, centred))
        mm.input[0] = centred
    else:
        b64 = b64 + d @ W64
        mm.input[0] = inp.name
    _set_init(g, mm.input[1], (a[:, None] * W64).astype(dtype))
    _set_init(g, b_name, b64.reshape(b.shape).astype(dtype))
    for n in chain:
        g.node.remove(n)
    return "fold_scaler" if fold_centre else "fold_scale"


def _sub_node(x: str, c: str, out: str) -> Any:
    """``out = x - c``."""
    from onnx import helper

    return helper.make_node("Sub", [x, c], [out], name=out)


def _first_matmul_rows(g: Any) -> int | None:
    """Rows of the first ``MatMul``'s weight initializer (the features it reads), or None."""
    mm = next((n for n in g.node if n.op_type == "MatMul"), None)
    W = None if mm is None else _init(g, mm.input[1])
    return None if W is None or W.ndim != 2 else int(W.shape[0])


def _matmul_add_to_gemm(model: Any) -> list[str]:
    """Each ``MatMul(X, W)`` (``X`` of rank 2 by ONNX shape inference, ``W`` a 2-D initializer) whose only
    consumer is ``Add`` of a bias initializer (``[n]`` or ``[1, n]``, read by nothing else) becomes ``Gemm(X, W,
    b)`` writing the ``Add``'s output."""
    import onnx
    from onnx import helper

    g = model.graph
    inferred = onnx.shape_inference.infer_shapes(model).graph
    rank = {v.name: len(v.type.tensor_type.shape.dim) for v in (*inferred.input, *inferred.value_info)
            if v.type.tensor_type.HasField("shape")}
    out: list[str] = []
    for mm in list(g.node):
        if mm.op_type != "MatMul" or mm.domain not in ("", "ai.onnx") or rank.get(mm.input[0]) != 2:
            continue
        W = _init(g, mm.input[1])
        adds = _consumers(g, mm.output[0])
        if W is None or W.ndim != 2 or len(adds) != 1 or adds[0].op_type != "Add":
            continue
        add = adds[0]
        b_name = add.input[1] if add.input[0] == mm.output[0] else add.input[0]
        b = _init(g, b_name)
        if (b is None or b.shape not in ((W.shape[1],), (1, W.shape[1])) or len(_consumers(g, b_name)) != 1
                or any(v.name == mm.output[0] for v in g.output)):
            continue
        gemm = helper.make_node("Gemm", [mm.input[0], mm.input[1], b_name], [add.output[0]],
                                name=_fresh(g, f"{mm.name or 'gemm'}_gemm"))
        k = list(g.node).index(mm)
        g.node.remove(add)
        g.node.remove(mm)
        g.node.insert(k, gemm)
        out.append("gemm")
    return out


def _drop_final_reshape(g: Any) -> bool:
    """Remove the final ``Reshape`` to ``[-1, n]`` of a ``Gemm`` whose weights already give ``n`` columns."""
    if len(g.output) != 1 or not len(g.node):
        return False
    last = g.node[-1]
    if last.op_type != "Reshape" or list(last.output) != [g.output[0].name]:
        return False
    shape = _init(g, last.input[1])
    src = last.input[0]
    producer = next((p for p in g.node if src in p.output), None)
    if shape is None or producer is None or producer.op_type != "Gemm" or len(_consumers(g, src)) != 1:
        return False
    W = _init(g, producer.input[1])
    trans_b = next((a.i for a in producer.attribute if a.name == "transB"), 0)
    if W is None or W.ndim != 2 or list(shape) != [-1, W.shape[0] if trans_b else W.shape[1]]:
        return False
    producer.output[0] = last.output[0]
    g.node.remove(last)
    return True


def _drop_unused_initializers(g: Any) -> None:
    """Remove the initializers no node reads (the scaler's constants, the final Reshape's shape)."""
    used = {v for n in g.node for v in n.input}
    for i in list(g.initializer):
        if i.name not in used:
            g.initializer.remove(i)
