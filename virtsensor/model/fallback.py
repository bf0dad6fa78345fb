"""A model's pressure-free fallback: the estimate to use where the TPMS pressures are unknown.

A model trained with the TPMS pressures (recipe ``tpms``, :data:`virtsensor.features.TPMS`) takes the front
tyres' pressures as its last features; its card's ``fallback`` names a pressure-free model whose features are
exactly the ones before them (``{"file": "improved.onnx", "sha256": ..., "n_features": 22, "optional": [...]}``,
the file beside the card). Where a pressure is unknown (no TPMS frame yet, a stale one, a wheel's sensor
reporting SNA, a recording without TPMS), the fallback's estimate is used instead: never the TPMS model fed a
made-up (nominal or held) pressure. The daemon marks such an estimate DEGRADED; ``score`` and ``evaluate`` count
the rows.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor.errors import UserError

__all__ = ["Fallback", "fallback_entry", "load_fallback"]


class Fallback:
    """A loaded fallback: ``model`` (an :class:`~virtsensor.model.onnx.OnnxModel`), the count ``n`` of leading
    features it reads, and the ``optional`` feature names (the pressures) whose absence it covers."""

    def __init__(self, model: Any, n: int, optional: tuple[str, ...]) -> None:
        self.model, self.n, self.optional = model, int(n), tuple(optional)

    def predict(self, main: Any, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Estimates (N, outputs) in Nm for feature rows ``X`` of the main model: the main model's where every
        feature is finite, the fallback's (on the first :attr:`n` features) elsewhere. Returns
        ``(estimates, used_fallback)`` (bool per row)."""
        X = np.asarray(X, dtype=np.float64)
        full = np.isfinite(X).all(axis=1)
        P = np.empty((len(X), len(main.outputs)))
        if full.any():
            P[full] = main.predict(X[full])
        if (~full).any():
            P[~full] = self.model.predict(X[~full, : self.n])
        return P, ~full


def fallback_entry(fallback_path: Path, out: Path, spec_names: tuple[str, ...]) -> dict[str, Any]:
    """The card's ``fallback`` entry of a model written to ``out`` whose features are ``spec_names``: the
    fallback model at ``fallback_path`` (in the same directory) must read exactly a prefix of them.

    Raises:
        UserError: the fallback is elsewhere, unreadable, or its features are not a prefix of ``spec_names``.
    """
    from virtsensor.model.onnx import OnnxModel

    fallback_path, out = Path(fallback_path), Path(out)
    if fallback_path.resolve().parent != out.resolve().parent:
        raise UserError(f"--fallback {fallback_path}: must lie beside {out} (the card names it by file name)")
    fb = OnnxModel.load(fallback_path)
    names = tuple(fb.input_names)
    if names != tuple(spec_names[: len(names)]) or len(names) >= len(spec_names):
        raise UserError(f"--fallback {fallback_path}: its features {list(names)} are not the first features of "
                        f"this model ({list(spec_names)})")
    if tuple(fb.outputs) == ():
        raise UserError(f"--fallback {fallback_path}: no outputs")
    return {"file": fallback_path.name, "sha256": fb.card["sha256"], "n_features": len(names),
            "optional": list(spec_names[len(names):])}


def load_fallback(model: Any) -> Fallback | None:
    """The fallback its card names (None: none), loaded from beside the card and checked: its sha256, its
    features (the model's first ``n_features``) and its outputs (the model's).

    Raises:
        UserError: a malformed entry, a missing or modified fallback file, features or outputs that differ.
    """
    from virtsensor.model.onnx import OnnxModel

    entry = model.card.get("fallback")
    if entry is None:
        return None
    where = str(getattr(model, "card_path", "model card"))
    if not isinstance(entry, Mapping) or not {"file", "sha256", "n_features", "optional"} <= set(entry):
        raise UserError(f"{where}: malformed fallback entry (needs file, sha256, n_features, optional)")
    path = Path(str(getattr(model, "card_path", "."))).parent / Path(str(entry["file"])).name
    if not path.is_file():
        raise UserError(f"{where}: its pressure-free fallback {path} is missing")
    fb = OnnxModel.load(path)
    n = int(entry["n_features"])
    names = tuple(model.input_names)
    if fb.card["sha256"] != entry["sha256"]:
        raise UserError(f"{path}: sha256 {fb.card['sha256']} is not the fallback's {entry['sha256']} named in {where}")
    if tuple(fb.input_names) != names[:n] or tuple(entry["optional"]) != names[n:]:
        raise UserError(f"{where}: the fallback {path} does not read this model's first {n} features")
    if tuple(fb.outputs) != tuple(model.outputs):
        raise UserError(f"{where}: the fallback {path} estimates {list(fb.outputs)}, not {list(model.outputs)}")
    return Fallback(fb, n, tuple(entry["optional"]))
