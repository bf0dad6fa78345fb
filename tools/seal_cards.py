#!/usr/bin/env python3
"""Migration: give model cards written before card digests their ``parity_inputs`` and ``card_sha256``.

The ONNX files are not touched (their bytes, and so the cards' ``sha256``, stay as they are). For each
card: the ONNX beside it must match the card's ``sha256``; ``parity_inputs`` (if absent) become
:func:`virtsensor.model.onnx.default_parity_inputs` of the card's weights; the card is sealed, written
atomically, and loaded back through :meth:`virtsensor.model.onnx.OnnxModel.load` (which checks the
digest, the graph and the numpy weights on those rows). Usage::

    python tools/seal_cards.py models/paper.card.json models/improved.card.json
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

from virtsensor.errors import UserError
from virtsensor.model.card import DIGEST_KEY, ModelCard, seal_file
from virtsensor.model.onnx import OnnxModel, default_parity_inputs


def seal(card_path: Path) -> str:
    """Seal one card; returns a one-line summary. Raises UserError when the ONNX does not match it."""
    card = ModelCard.read(card_path, verify=False)
    onnx_path = card_path.with_name(str(card.get("onnx_file", card_path.name.replace(".card.json", ".onnx"))))
    digest = hashlib.sha256(onnx_path.read_bytes()).hexdigest()
    if digest != card.get("sha256"):
        raise UserError(f"{onnx_path}: sha256 {digest} is not the card's {card.get('sha256')}; not sealing {card_path}")
    extra = {}
    if card.get("weights") is not None:
        extra["parity_inputs"] = default_parity_inputs(card["weights"], int(card["n_features"]))
    was = card.get(DIGEST_KEY)
    sealed = seal_file(card_path, extra)
    OnnxModel.load(onnx_path, card_path)
    state = "unchanged" if was == sealed[DIGEST_KEY] else "sealed"
    return f"{card_path}: {state}, card_sha256 {sealed[DIGEST_KEY][:12]}..., onnx {onnx_path} untouched"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("cards", nargs="+", type=Path, metavar="CARD.json")
    args = parser.parse_args(argv)
    try:
        for path in args.cards:
            print(seal(path))
    except UserError as exc:
        print(f"seal_cards: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
