"""The exported graph with fewer kernels: skl2onnx's scaler + MLP rewritten into the same function.

skl2onnx (checked with 1.20) converts ``[scaler] + MLPRegressor`` into::

    Scaler(offset o, scale s) -> Cast -> (MatMul W_k -> Add b_k -> activation)* -> MatMul -> Add -> Reshape

onnxruntime infers no shape past the ``ai.onnx.ml`` ``Scaler``, so it fuses nothing and runs ten kernels per
call for two hidden layers. Each kernel costs its dispatch, and far more on caches gone cold between the
daemon's 20 Hz ticks. :func:`lean_graph` rewrites, in place, what it recognises:

1. **the scaler folded into the first layer**: skl2onnx writes the scaler as an ``ai.onnx.ml`` ``Scaler``
   (float32 graphs) or as ``Sub``/``Div`` (Robust, Standard) and ``Mul``/``Add`` (MinMax) by constants; any such
   chain is ``x * a + d`` per feature, and ``(x * a + d) W + b = x (a[:, None] * W) + (b + d W)``, computed in
   float64 and stored in the graph's type;
2. **MatMul + Add -> Gemm**: a ``MatMul`` by a 2-D initializer whose only consumer adds a bias initializer
   (``[n]`` or ``[1, n]``);
3. **identities dropped**: a ``Cast`` to the type its input already has, and the final ``Reshape`` to
   ``[-1, n]`` of a ``Gemm`` that already gives ``[N, n]``.

onnxruntime then fuses each ``Gemm`` + activation into one ``FusedGemm``: three kernels for two hidden layers.
A step whose pattern is not there (a linear regressor, another converter's graph) changes nothing, so the
result is always a graph of the same function; :func:`virtsensor.model.export.export_pipeline` checks it
against scikit-learn (``parity_max_abs_nm``) and the model card's plain weights before writing it. What it
saves per inference: README, "Where the CPU at 20 Hz goes".

Needs ``onnx`` (the export side; the daemon never imports this module).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["lean_graph"]

_FLOAT_TYPES = {1: np.float32, 11: np.float64}  # TensorProto.FLOAT, DOUBLE
#: element-wise ops by a constant that :func:`_fold_scaler` composes: y = x * a + d
_AFFINE_OPS = ("Sub", "Div", "Mul", "Add")


def lean_graph(model: Any, *, keep_centre: bool = False) -> list[str]:
    """Rewrite ``model`` (an ``onnx.ModelProto`` with one input and one output) in place; returns the names of
    the rewrites applied (``drop_cast``, ``fold_scaler`` or ``fold_scale``, ``gemm`` per fused layer,
    ``drop_reshape``), in order. The graph is checked with the ONNX checker (full shape inference) afterwards.

    ``keep_centre``: fold only the scaler's scale and keep its centring as one ``Sub`` (``fold_scale``). In
    float32, ``x W' + (b - c W')`` loses the digits ``(x - c)`` keeps where a feature's centre is large against
    its spread; :func:`virtsensor.model.export.export_pipeline` falls back to it when the full fold is less
    exact than the unfolded graph."""
    import onnx

    done: list[str] = []
    g = model.graph
    done += _drop_identity_casts(g)
    if _fold_scaler(g, keep_centre):
        done.append("fold_scale" if keep_centre else "fold_scaler")
    done += _matmul_add_to_gemm(g)
    if _drop_final_reshape(g):
        done.append("drop_reshape")
    _drop_unused_initializers(g)
    onnx.checker.check_model(model, full_check=True)
    return done


def _consumers(g: Any, name: str) -> list[Any]:
    return [n for n in g.node if name in n.input]


def _init(g: Any, name: str) -> np.ndarray | None:
    from onnx import numpy_helper

    for i in g.initializer:
        if i.name == name:
            return numpy_helper.to_array(i)
    return None


def _set_init(g: Any, name: str, value: np.ndarray) -> None:
    from onnx import numpy_helper

    for i in g.initializer:
        if i.name == name:
            i.CopyFrom(numpy_helper.from_array(value, name))
            return
    g.initializer.append(numpy_helper.from_array(value, name))


def _fresh(g: Any, base: str) -> str:
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


def _fold_scaler(g: Any, keep_centre: bool) -> bool:
    """Fold the element-wise affine chain on the graph input (an ``ai.onnx.ml`` ``Scaler``, or ``Sub``/``Div``/
    ``Mul``/``Add`` by constants, as skl2onnx writes the Robust, Standard and MinMax scalers; an identity
    ``Cast`` already dropped) into the ``MatMul`` + ``Add`` that alone reads its end: with ``y = x * a + d``,
    ``y W + b = x (a[:, None] * W) + (b + d W)``; ``keep_centre``: ``y W + b = (x - c) (a[:, None] * W) + b``
    with ``c = -d / a``, one ``Sub`` kept."""
    inp = g.input[0]
    dtype = _FLOAT_TYPES.get(int(inp.type.tensor_type.elem_type))
    if dtype is None:
        return False
    chain: list[Any] = []
    src, nxt = inp.name, _consumers(g, inp.name)
    a = d = None
    while len(nxt) == 1 and nxt[0].op_type != "MatMul":
        n = nxt[0]
        if a is None or d is None:
            n_in = _first_matmul_rows(g)
            if n_in is None:
                return False
            a, d = np.ones(n_in), np.zeros(n_in)
        if not _affine_step(g, n, src, a, d):
            return False
        chain.append(n)
        src, nxt = n.output[0], _consumers(g, n.output[0])
    if not chain or a is None or d is None or len(nxt) != 1:
        return False
    mm = nxt[0]
    W = _init(g, mm.input[1])
    adds = _consumers(g, mm.output[0])
    if (mm.input[0] != src or W is None or W.ndim != 2 or W.dtype != dtype or W.shape[0] != a.size
            or len(_consumers(g, mm.input[1])) != 1 or len(adds) != 1 or adds[0].op_type != "Add"):
        return False
    add = adds[0]
    b_name = add.input[1] if add.input[0] == mm.output[0] else add.input[0]
    b = _init(g, b_name)
    if b is None or b.size != W.shape[1] or len(_consumers(g, b_name)) != 1:
        return False
    W64, b64 = W.astype(np.float64), b.astype(np.float64).reshape(-1)
    if keep_centre:  # x * a + d = (x - c) * a with c = -d / a: the centring stays a Sub, a folds into W
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
    return True


def _sub_node(x: str, c: str, out: str) -> Any:
    from onnx import helper

    return helper.make_node("Sub", [x, c], [out], name=out)


def _first_matmul_rows(g: Any) -> int | None:
    """Rows of the first ``MatMul``'s weight initializer (the features it reads), or None."""
    mm = next((n for n in g.node if n.op_type == "MatMul"), None)
    W = None if mm is None else _init(g, mm.input[1])
    return None if W is None or W.ndim != 2 else int(W.shape[0])


def _matmul_add_to_gemm(g: Any) -> list[str]:
    """Each ``MatMul(X, W)`` (W a 2-D initializer) whose only consumer is ``Add`` of a 1-D bias initializer
    becomes ``Gemm(X, W, b)`` writing the ``Add``'s output."""
    from onnx import helper

    out: list[str] = []
    for mm in list(g.node):
        if mm.op_type != "MatMul" or mm.domain not in ("", "ai.onnx"):
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
    used = {v for n in g.node for v in n.input}
    for i in list(g.initializer):
        if i.name not in used:
            g.initializer.remove(i)
