#!/usr/bin/env python3
"""Migration: rewrite shipped ONNX graphs with :func:`virtsensor.model.leangraph.lean_graph` (the same function
with fewer kernels), without retraining.

For each model (its card beside it, ``<name>.card.json``): the graph is rewritten as the export does
(:func:`virtsensor.model.export.lean_as_exact`: the rewrite as exact as the old graph against the card's plain
float64 weights, on the card's ``parity_inputs`` and 2,000 rows drawn around its scaler); the new graph's
largest difference from the old one on those rows must be within :data:`~virtsensor.model.onnx.PARITY_TOL_NM`;
the card gets the new ``sha256``, ``onnx_rewrites`` and ``rewritten_from`` (the old graph's sha256, which
earlier evaluations name, and the measured difference), and is re-sealed; a card whose ``fallback`` names a
rewritten model gets that model's new sha256. Everything is checked in memory
(:class:`~virtsensor.model.onnx.OnnxModel` on the new bytes and card) before any file is replaced; the files are
written atomically. A graph with nothing to rewrite is left untouched. Usage::

    python tools/lean_models.py models/improved.onnx models/paper.onnx models/tpms.onnx
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor.errors import UserError
from virtsensor.fileio import atomic_write_bytes
from virtsensor.model.card import ModelCard, card_path_for
from virtsensor.model.onnx import PARITY_TOL_NM, OnnxModel, default_parity_inputs, make_session

N_CHECK_ROWS = 2000


def _rows(card: ModelCard) -> np.ndarray:
    n = int(card["n_features"])
    rows = list(card.get("parity_inputs") or [])
    rows += default_parity_inputs(card.get("weights"), n, N_CHECK_ROWS)
    return np.asarray(rows, dtype=float)


def _run(onnx_bytes: bytes, X: np.ndarray, dtype: Any) -> np.ndarray:
    return np.asarray(make_session(onnx_bytes)[0].run(None, {"features": X.astype(dtype)})[0], dtype=float)


def lean_one(path: Path) -> tuple[bytes, ModelCard, dict[str, str]] | None:
    """The rewritten graph and card of one model, checked (None: nothing to rewrite)."""
    import onnx

    from virtsensor.model.export import lean_as_exact

    card = ModelCard.read(card_path_for(path))
    old = path.read_bytes()
    if hashlib.sha256(old).hexdigest() != card["sha256"]:
        raise UserError(f"{path}: not the graph its card names; not rewriting it")
    reference = OnnxModel(old, card, path=path, card_path=card_path_for(path)).numpy_forward
    if reference is None:
        raise UserError(f"{card_path_for(path)}: no plain weights to check a rewrite against; not rewriting {path}")
    X = _rows(card)
    precision = "float64" if card.get("input_dtype") == "float64" else "float32"
    model, rewrites = lean_as_exact(onnx.load_from_string(old), reference, X, precision)
    if not rewrites:
        return None
    new = model.SerializeToString()
    dtype = np.float64 if precision == "float64" else np.float32
    diff = float(np.max(np.abs(_run(new, X, dtype) - _run(old, X, dtype))))
    if not diff <= PARITY_TOL_NM:
        raise UserError(f"{path}: the rewritten graph differs by {diff:.3g} Nm (limit {PARITY_TOL_NM:g}); not written")
    data = card.to_dict()
    data.update(sha256=hashlib.sha256(new).hexdigest(), onnx_rewrites=rewrites,
                rewritten_from={"sha256": card["sha256"], "max_abs_diff_nm": diff, "rows": len(X)})
    return new, ModelCard(data, path=card_path_for(path)).sealed(), {card["sha256"]: data["sha256"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+", type=Path, metavar="MODEL.onnx")
    args = parser.parse_args(argv)
    try:
        done: dict[Path, tuple[bytes, ModelCard]] = {}
        renamed: dict[str, str] = {}
        for path in args.models:
            got = lean_one(path)
            if got is None:
                print(f"{path}: nothing to rewrite")
                continue
            done[path] = got[:2]
            renamed.update(got[2])
        for path in args.models:  # a fallback entry naming a rewritten graph follows it
            card = done[path][1] if path in done else ModelCard.read(card_path_for(path))
            fb = card.get("fallback")
            if isinstance(fb, dict) and fb.get("sha256") in renamed:
                data = card.to_dict()
                data["fallback"] = {**fb, "sha256": renamed[fb["sha256"]]}
                onnx_bytes = done[path][0] if path in done else path.read_bytes()
                done[path] = (onnx_bytes, ModelCard(data, path=card_path_for(path)).sealed())
        for path, (onnx_bytes, card) in done.items():
            OnnxModel(onnx_bytes, card, path=path, card_path=card_path_for(path))
        for path, (onnx_bytes, card) in done.items():
            atomic_write_bytes(path, onnx_bytes)
            card.write(card_path_for(path))
        for path in done:
            m = OnnxModel.load(path)
            rf = m.card.get("rewritten_from") or {}
            print(f"{path}: {', '.join(m.card.get('onnx_rewrites') or ['fallback sha256 updated'])}; "
                  f"{len(onnx_load_ops(path))} nodes; sha256 {m.card['sha256'][:12]}... "
                  f"(was {str(rf.get('sha256', '-'))[:12]}..., max |diff| {rf.get('max_abs_diff_nm', 0):.2g} Nm)")
    except UserError as exc:
        print(f"lean_models: error: {exc}", file=sys.stderr)
        return 2
    return 0


def onnx_load_ops(path: Path) -> list[str]:
    import onnx

    return [n.op_type for n in onnx.load(path).graph.node]


if __name__ == "__main__":
    sys.exit(main())
