"""Score a shipped model on recordings, without retraining.

The model file itself (:class:`virtsensor.model.onnx.OnnxModel`) runs on the
features its card names (:class:`virtsensor.features.FeatureSpec`), built by the
same code the daemon and the trainer use from each run's 20 Hz table (a CSV
table, or a CAN log decoded and sampled by the runtime's front-end). Rows whose
features or reference SATs are not finite are left out and counted.

Metrics come from :mod:`virtsensor.metrics` (numpy, no scikit-learn): "r2" and "mae_nm" without a
wheel are the means over the two front wheels; "axle" scores the sum of the two SATs.

When the model card states a validity envelope (:mod:`virtsensor.model.envelope`), every run and the
overall figure also give the share of rows outside it and the error inside and outside it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.features import FeatureSpec
from virtsensor.learning.dataset import Run, build_dataset, trained_on
from virtsensor.learning.gripscore import grip_markdown, grip_runs, pool, public
from virtsensor.metrics import metrics
from virtsensor.model.envelope import Envelope
from virtsensor.model.fallback import load_fallback

__all__ = ["envelope_split", "needed_signals", "score_runs", "markdown"]


def needed_signals(card: Any) -> list[str]:
    """The catalogue signals a run needs to be scored by a model of this card: its inputs and the SATs (the TPMS
    pressures are asked for too, but a run without them loads with its pressures unknown, see
    :func:`~virtsensor.learning.dataset.load_runs`, and a model with a fallback scores it with the fallback)."""
    spec = _spec(card)
    return sorted(set(spec.signals) | set(cat.OUTPUTS))


def _spec(card: Any) -> FeatureSpec:
    """The card's feature spec; UserError names the card's file (a card in memory: "model card")."""
    try:
        return FeatureSpec.from_json(card["feature_spec"])
    except (AttributeError, KeyError, TypeError, ValueError) as exc:
        path = getattr(card, "path", None)
        where = f"{path}: model card" if path is not None else "model card"
        raise UserError(f"{where} has no usable feature_spec ({exc})") from None


def score_runs(model: Any, runs: Sequence[Run]) -> dict[str, Any]:
    """Score ``model`` (an :class:`~virtsensor.model.onnx.OnnxModel`) on each run and on all together.

    Returns:
        ``{"model": {"file", "sha256"}, "overall": wheel_metrics + {"dropped_nonfinite", "envelope", "grip",
        "runs_trained_on", ["never_trained_on"], ["trained_on_listed_for"]}, "runs": [{"file", "r2", "mae_nm", "n",
        "fl", "fr", "axle", "dropped_nonfinite", "envelope", "grip", "trained_on"}, ...]}``
        in the order of ``runs``; ``trained_on_listed_for``: the training folders whose runs the card lists, where
        it lists only some (then no ``never_trained_on``); ``never_trained_on`` (only where the card lists some of
        the runs and not all):
        wheel metrics, ``runs`` and ``grip`` of the runs the card does not list, the figures that are a test;
        ``envelope`` is :func:`envelope_split` (None when the card states none);
        ``grip`` the grip margin's figures (:mod:`virtsensor.learning.gripscore`; None for a run without the
        simulator's grip truth, and overall when no run has it).

    Raises:
        UserError: a run lacking a needed signal, or with no row where every feature and
            both SATs are finite (naming the file).
    """
    spec = _spec(model.card)
    if tuple(spec.names) != tuple(model.input_names):
        raise UserError(f"{getattr(model, 'path', 'model')}: its card's feature_spec does not give its inputs "
                        f"{', '.join(model.input_names)}")
    if tuple(model.outputs) != tuple(cat.OUTPUTS):
        raise UserError(f"{getattr(model, 'path', 'model')}: it estimates {', '.join(model.outputs)}, "
                        f"not {', '.join(cat.OUTPUTS)}")
    env = _envelope(model)
    fallback = load_fallback(model)
    optional = () if fallback is None else fallback.optional
    per_run, ys, ps = [], [], []
    outs: list[np.ndarray] = []
    dropped = unknown = 0
    for run in runs:
        ds = build_dataset([run], spec, cat.OUTPUTS, optional=optional)
        where = str(run.path or run.name)
        if len(ds.Y) == 0:
            raise UserError(f"{where}: no sample with every input of the model and both reference SATs finite")
        if fallback is None:
            pred, fb_rows = model.predict(ds.X), np.zeros(len(ds.X), dtype=bool)
        else:  # rows whose pressures are unknown: the pressure-free fallback's estimate, as the daemon publishes
            pred, fb_rows = fallback.predict(model, ds.X)
        m = metrics(ds.Y, pred)
        out = None if env is None else env.outside_rows(ds.X, spec.names)
        per_run.append({"file": where, "r2": m["r2"], "mae_nm": m["mae_nm"], "n": m["n"], "fl": m["fl"],
                        "fr": m["fr"], "axle": m["axle"], "dropped_nonfinite": ds.dropped_nonfinite,
                        "envelope": envelope_split(ds.Y, pred, out),
                        **({} if fallback is None else {"pressure_unknown_rows": int(fb_rows.sum())})})
        unknown += int(fb_rows.sum())
        ys.append(ds.Y)
        ps.append(pred)
        if out is not None:
            outs.append(out)
        dropped += ds.dropped_nonfinite
    Y, P = np.concatenate(ys), np.concatenate(ps)
    overall = metrics(Y, P)
    overall["dropped_nonfinite"] = dropped
    if fallback is not None:  # said, never hidden: how many rows had no known pressure and who estimated them
        overall["pressure_unknown_rows"] = unknown
        overall["fallback"] = {"file": str(fallback.model.path), "sha256": fallback.model.card.get("sha256")}
    overall["envelope"] = envelope_split(Y, P, None if env is None else np.concatenate(outs))
    grip = grip_runs(model, runs)  # (the grip margin from these SATs, where a run carries its truth)
    scored = [m for m in grip.values() if m is not None]
    overall["grip"] = pool(scored) if scored else None
    seen = {id(r) for r in trained_on(model.card, runs)}  # (in-sample: said, per run and overall)
    for r, run in zip(per_run, runs, strict=True):
        g = grip[r["file"]]
        r["grip"] = None if g is None else public(g)
        r["trained_on"] = id(run) in seen
    overall["runs_trained_on"] = len(seen)
    _never_trained_on(overall, model.card, [r["trained_on"] for r in per_run], ys, ps,
                      [grip[r["file"]] for r in per_run])
    return {"model": {"file": str(getattr(model, "path", "")), "sha256": model.card.get("sha256")},
            "overall": overall, "runs": per_run}


def _never_trained_on(overall: dict[str, Any], card: Any, trained: Sequence[bool], ys: Sequence[np.ndarray],
                      ps: Sequence[np.ndarray], grips: Sequence[dict[str, Any] | None]) -> None:
    """Add to ``overall`` the figures of the runs the card does not list (``never_trained_on``: the ones a reader
    can take as a test), where it lists some of them; or, where the card lists the runs of only some of its
    training folders, ``trained_on_listed_for`` (an unlisted run may be in-sample too: no such figures)."""
    fresh = [i for i, t in enumerate(trained) if not t]
    data = card.get("training_data") or {}
    cover = data.get("run_digests_cover")
    if cover is not None and set(cover) != set(data.get("sources") or cover):
        overall["trained_on_listed_for"] = list(cover)
    elif fresh and len(fresh) < len(trained):
        unseen = metrics(np.concatenate([ys[i] for i in fresh]), np.concatenate([ps[i] for i in fresh]))
        fresh_grip = [g for i in fresh if (g := grips[i]) is not None]
        unseen["grip"] = pool(fresh_grip) if fresh_grip else None
        unseen["runs"] = len(fresh)
        overall["never_trained_on"] = unseen


def _envelope(model: Any) -> Envelope | None:
    doc = model.card.get("envelope")
    return None if doc is None else Envelope.from_json(doc, str(getattr(model, "card_path", "model card")))


def envelope_split(Y: np.ndarray, P: np.ndarray, outside: np.ndarray | None) -> dict[str, Any] | None:
    """The share of rows outside the envelope, and R2, MAE (Nm, means over both wheels) and rows inside
    and outside it: ``{"outside_share", "inside": {"r2", "mae_nm", "n"} | None, "outside": ... | None}``
    (a side without rows is None). None when ``outside`` (bool per row) is None."""
    if outside is None:
        return None
    res: dict[str, Any] = {"outside_share": float(outside.mean()) if len(outside) else 0.0}
    for side, rows in (("inside", ~outside), ("outside", outside)):
        if rows.any():
            m = metrics(Y[rows], P[rows])
            res[side] = {"r2": m["r2"], "mae_nm": m["mae_nm"], "n": m["n"]}
        else:
            res[side] = None
    return res


def markdown(result: dict[str, Any]) -> str:
    """The score as a Markdown table: one row per run, then all runs together."""
    env = result["overall"].get("envelope") is not None
    head = "| run | samples | R2 | MAE (Nm) | R2 FL / FR | axle R2 / MAE (Nm) |"
    head += " outside envelope | inside R2 / MAE (Nm) | outside R2 / MAE (Nm) |" if env else ""
    lines = [f"Model `{result['model']['file']}` (sha256 {str(result['model']['sha256'])[:12]}...)", "",
             head, "|---" * head.count(" | ") + "|---|"]

    def row(name: str, m: dict[str, Any]) -> str:
        text = (f"| {name} | {m['n']} | {m['r2']:.3f} | {m['mae_nm']:.2f} | {m['fl']['r2']:.3f} / "
                f"{m['fr']['r2']:.3f} | {m['axle']['r2']:.3f} / {m['axle']['mae_nm']:.2f} |")
        if env:
            e = m["envelope"]
            side = ["—" if e[k] is None else f"{e[k]['r2']:.3f} / {e[k]['mae_nm']:.2f}" for k in ("inside", "outside")]
            text += f" {100 * e['outside_share']:.1f} % | {side[0]} | {side[1]} |"
        return text

    lines += [row(r["file"] + (" (trained on)" if r.get("trained_on") else ""), r) for r in result["runs"]]
    lines.append(row("**all runs**", result["overall"]))
    o = result["overall"]
    fresh = o.get("never_trained_on")
    if fresh is not None:
        lines.append(f"| **the {fresh['runs']} runs never trained on** | {fresh['n']} | {fresh['r2']:.3f} | "
                     f"{fresh['mae_nm']:.2f} | {fresh['fl']['r2']:.3f} / {fresh['fr']['r2']:.3f} | "
                     f"{fresh['axle']['r2']:.3f} / {fresh['axle']['mae_nm']:.2f} |" + (" — | — | — |" if env else ""))
    if o.get("trained_on_listed_for"):
        listed = ", ".join(o["trained_on_listed_for"])
        lines += ["", f"The card lists the runs it was trained on only for {listed}: a run of its other training "
                      "data is not marked, so no run here is shown as never trained on."]
    if o.get("runs_trained_on"):
        lines += ["", f"{o['runs_trained_on']} of these runs the model was trained on (its card lists them, marked "
                      "\"trained on\"): in-sample, not a test; \"all runs\" includes them."]
    if "pressure_unknown_rows" in o:
        lines += ["", f"{o['pressure_unknown_rows']} of {o['n']} samples had no known front tyre pressure (no TPMS, "
                      f"or a sensor missing): estimated by the pressure-free fallback `{o['fallback']['file']}`, as "
                      "the daemon publishes them (DEGRADED)."]
    grip = o.get("grip")
    tail = "" if grip is None else "\n" + grip_markdown({"overall": grip})
    if fresh is not None and fresh.get("grip") is not None:
        tail += "\n" + grip_markdown({"overall": fresh["grip"]}, "the runs never trained on")
    return "\n".join(lines) + "\n" + tail
