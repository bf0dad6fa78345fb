#!/usr/bin/env python3
"""Migration: rewrite exported ONNX graphs with :func:`virtsensor.model.leangraph.lean_graph` (the same function
with fewer kernels, as :func:`virtsensor.model.export.export_pipeline` now writes them), without retraining.

For each model (its card beside it, ``<name>.card.json``, whose ``sha256`` the ONNX must match): the graph is
rewritten; its outputs are compared with the old graph's on the card's ``parity_inputs`` and on 2,000 rows drawn
around the card's scaler (:func:`~virtsensor.model.onnx.default_parity_inputs`), and the largest difference must
be within :data:`~virtsensor.model.onnx.PARITY_TOL_NM`; the card gets the new ``sha256``, ``onnx_rewrites`` and
``rewritten_from`` (the old graph's sha256, which figures measured before name, and that difference), and is
re-sealed. ``parity_max_abs_nm`` stays the export's (the old graph against scikit-learn). Every other card in
the rewritten models' directories whose ``fallback`` names a rewritten graph (a fallback lies beside its model)
gets the new sha256. Everything is checked in memory (:class:`~virtsensor.model.onnx.OnnxModel` on the new bytes
and cards) before any file is replaced; files are written atomically. A graph with nothing to rewrite is left
untouched (running it twice changes nothing). Usage::

    python tools/lean_models.py models/improved.onnx models/paper.onnx models/tpms.onnx

Note: a daemon configured without ``model_id`` publishes the first byte of the ONNX sha256 as
``VS_ModelId``; a rewritten graph has a new sha256, so that byte changes.
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import sys
from pathlib import Path

import numpy as np

from virtsensor.errors import UserError
from virtsensor.fileio import atomic_write_bytes
from virtsensor.model.card import ModelCard, card_path_for
from virtsensor.model.onnx import PARITY_TOL_NM, OnnxModel, default_parity_inputs, make_session

N_CHECK_ROWS = 2000


def _rows(card: ModelCard) -> np.ndarray:
    """The card's parity rows and :data:`N_CHECK_ROWS` rows drawn around its scaler."""
    n = int(card["n_features"])
    rows = list(card.get("parity_inputs") or [])
    rows += default_parity_inputs(card.get("weights"), n, N_CHECK_ROWS)
    return np.asarray(rows, dtype=float)


def _run(onnx_bytes: bytes, X: np.ndarray, dtype: type) -> np.ndarray:
    return np.asarray(make_session(onnx_bytes)[0].run(None, {"features": X.astype(dtype)})[0], dtype=float)


def lean_one(path: Path) -> tuple[bytes, ModelCard] | None:
    """The rewritten graph and re-sealed card of one model, checked (None: nothing to rewrite).

    Raises:
        UserError: the ONNX is not the one its card names, or the rewrite moves an output by more than
            :data:`~virtsensor.model.onnx.PARITY_TOL_NM`.
    """
    import onnx

    from virtsensor.model.leangraph import lean_graph

    card = ModelCard.read(card_path_for(path))
    try:
        old = path.read_bytes()
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc.strerror or exc}") from None
    if hashlib.sha256(old).hexdigest() != card["sha256"]:
        raise UserError(f"{path}: not the graph its card names (sha256); not rewriting it")
    model = onnx.load_from_string(old)
    lean = copy.deepcopy(model)
    rewrites = lean_graph(lean)
    if not rewrites:
        return None
    new = lean.SerializeToString()
    X = _rows(card)
    dtype = np.float64 if card.get("input_dtype") == "float64" else np.float32
    diff = float(np.max(np.abs(_run(new, X, dtype) - _run(old, X, dtype))))
    if not diff <= PARITY_TOL_NM:
        raise UserError(f"{path}: the rewritten graph differs by {diff:.3g} Nm (limit {PARITY_TOL_NM:g}); not written")
    data = card.to_dict()
    data.update(sha256=hashlib.sha256(new).hexdigest(), onnx_rewrites=rewrites,
                rewritten_from={"sha256": card["sha256"], "max_abs_diff_nm": diff, "rows": len(X)})
    return new, ModelCard(data, path=card_path_for(path)).sealed()


def _follow_fallbacks(done: dict[Path, tuple[bytes, ModelCard]], renamed: dict[str, str]) -> set[Path]:
    """Point every card beside a rewritten model whose ``fallback`` names a rewritten graph at its new sha256;
    returns the models whose card only that changed."""
    followed: set[Path] = set()
    dirs = {p.resolve().parent for p in done}
    for d in sorted(dirs):
        for card_file in sorted(d.glob("*.card.json")):
            path = card_file.with_name(card_file.name.removesuffix(".card.json") + ".onnx")
            key = next((p for p in done if p.resolve() == path.resolve()), path)
            card = done[key][1] if key in done else ModelCard.read(card_file)
            fb = card.get("fallback")
            if not isinstance(fb, dict) or fb.get("sha256") not in renamed:
                continue
            data = card.to_dict()
            data["fallback"] = {**fb, "sha256": renamed[fb["sha256"]]}
            if key not in done:
                followed.add(key)
            onnx_bytes = done[key][0] if key in done else key.read_bytes()
            done[key] = (onnx_bytes, ModelCard(data, path=card_file).sealed())
    return followed


def migrate(paths: list[Path]) -> list[str]:
    """Rewrite ``paths`` (see the module doc); returns one line per model."""
    done: dict[Path, tuple[bytes, ModelCard]] = {}
    renamed: dict[str, str] = {}
    lines = []
    for path in paths:
        got = lean_one(path)
        if got is None:
            lines.append(f"{path}: nothing to rewrite")
            continue
        done[path] = got
        renamed[got[1]["rewritten_from"]["sha256"]] = got[1]["sha256"]
    followed = _follow_fallbacks(done, renamed)
    for path, (onnx_bytes, card) in done.items():  # every new graph and card checked before any is written
        OnnxModel(onnx_bytes, card, path=path, card_path=card_path_for(path))
    for path, (onnx_bytes, card) in done.items():
        atomic_write_bytes(path, onnx_bytes)
        card.write(card_path_for(path))
    for path in done:
        card = OnnxModel.load(path).card
        rf = card["rewritten_from"] if path not in followed else None
        if rf is None:
            lines.append(f"{path}: its fallback's new sha256")
            continue
        lines.append(f"{path}: {', '.join(card['onnx_rewrites'])}; sha256 {card['sha256'][:12]}... "
                     f"(was {rf['sha256'][:12]}..., max |diff| {rf['max_abs_diff_nm']:.2g} Nm on {rf['rows']} rows)")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", nargs="+", type=Path, metavar="MODEL.onnx")
    args = parser.parse_args(argv)
    try:
        for line in migrate(args.models):
            print(line)
    except UserError as exc:
        print(f"lean_models: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
