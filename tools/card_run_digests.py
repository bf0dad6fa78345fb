#!/usr/bin/env python3
"""Migration: give a model card written before ``training_data.run_digests`` the table digests of its training runs.

A card lists the folders it was trained on (``training_data.sources``) and the sha256 of its training rows
(``training_data.fingerprint_sha256``). This tool loads those folders again, builds the card's features and checks
that they give exactly that fingerprint: only then are the runs' table digests
(:func:`virtsensor.learning.dataset.trained_digests`, the runs that gave rows) written into the card, which is
sealed again; the ONNX file is not touched. With ``--proof OTHER_CARD``, the folders both cards list and OTHER_CARD's
fingerprint proves unchanged give their runs' digests to this card (a card trained on them and more, whose other
folders were simulated again since), and ``training_data.run_digests_cover`` names the folders covered. Usage::

    python tools/card_run_digests.py models/paper.card.json
    python tools/card_run_digests.py models/improved.card.json --proof models/paper.card.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.features import FeatureSpec
from virtsensor.learning.dataset import build_dataset, load_runs, trained_digests
from virtsensor.model.card import ModelCard
from virtsensor.model.onnx import OnnxModel


def _proven(card: ModelCard, root: Path) -> tuple[list[str], list[str]]:
    """(sources, run digests) of ``card``'s training data, checked against its fingerprint."""
    data = card["training_data"]
    spec = FeatureSpec.from_json(card["feature_spec"])
    sources = [str(s) for s in data["sources"]]
    runs = load_runs([root / s for s in sources], needed=(*spec.signals, *cat.OUTPUTS))
    ds = build_dataset(runs, spec)
    if ds.fingerprint() != data["fingerprint_sha256"]:
        raise UserError(f"{card.path}: {', '.join(sources)} no longer give its training rows (fingerprint "
                        f"{ds.fingerprint()[:12]}..., the card's {data['fingerprint_sha256'][:12]}...): simulated "
                        "again since; nothing written")
    given = {int(g) for g in set(ds.groups.tolist())}
    return sources, trained_digests([r for i, r in enumerate(runs) if i in given])


def add_digests(card_path: Path, proof: Path | None, root: Path) -> str:
    card = ModelCard.read(card_path)
    data: dict[str, Any] = dict(card["training_data"])
    if data.get("run_digests"):
        return f"{card_path}: already lists {len(data['run_digests'])} runs; unchanged"
    if proof is None:
        cover, digests = _proven(card, root)
    else:
        other = ModelCard.read(proof)
        cover, digests = _proven(other, root)
        if not set(cover) <= set(str(s) for s in data["sources"]):
            raise UserError(f"{proof}: its sources {', '.join(cover)} are not all {card_path}'s; nothing written")
    data["run_digests"] = digests
    data["run_digests_cover"] = cover
    doc = card.to_dict()
    doc["training_data"] = data
    ModelCard(doc, path=card_path).sealed().write(card_path)
    onnx = card_path.with_name(str(card.get("onnx_file", card_path.name.replace(".card.json", ".onnx"))))
    OnnxModel.load(onnx, card_path)  # (the digest, the graph and the weights checked again)
    return f"{card_path}: {len(digests)} runs of {', '.join(cover)} listed; sealed; {onnx} untouched"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("card", type=Path)
    parser.add_argument("--proof", type=Path, default=None, help="a card whose fingerprint proves shared sources")
    parser.add_argument("--root", type=Path, default=Path("."), help="where the sources' paths start")
    args = parser.parse_args(argv)
    try:
        print(add_digests(args.card, args.proof, args.root))
    except UserError as exc:
        print(f"card_run_digests: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
