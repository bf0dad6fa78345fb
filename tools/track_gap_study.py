#!/usr/bin/env python3
"""Why a model trained on the Table I manoeuvres misses on a circuit: where the circuit leaves the training data.

Usage::

    python tools/track_gap_study.py --model OLD.onnx --train DIR [DIR ...] --laps LAP.csv [LAP.csv ...] \\
        --figure docs/figures/track_gap.png --json docs/track_gap.json

For each lap it scores the model file and splits the rows by whether their combination of longitudinal and
lateral acceleration (ax, ay: traction or braking while cornering) occurs in the training data: a 2-D grid of
0.5 m/s^2 cells over (ax, |ay|), a cell "covered" when it holds at least 20 training rows. It reports the share
of lap rows outside the covered cells and the MAE inside and outside them, and draws the training coverage
with the lap's rows coloured by their absolute error. Run it on development circuits, never on the report
circuit, to choose what to train on.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from virtsensor.features import FeatureSpec
from virtsensor.fileio import write_json
from virtsensor.learning.dataset import build_dataset, load_runs
from virtsensor.model.onnx import OnnxModel

CELL = 0.5  # m/s^2
MIN_ROWS = 20
AX_RANGE = (-10.0, 6.0)
AY_RANGE = (0.0, 10.0)


def _grid(ax: np.ndarray, ay: np.ndarray) -> np.ndarray:
    bins = (np.arange(AX_RANGE[0], AX_RANGE[1] + CELL, CELL), np.arange(AY_RANGE[0], AY_RANGE[1] + CELL, CELL))
    h, _, _ = np.histogram2d(ax, np.abs(ay), bins=bins)
    return h


def _cells(ax: np.ndarray, ay: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    i = np.clip(((ax - AX_RANGE[0]) / CELL).astype(int), 0, int((AX_RANGE[1] - AX_RANGE[0]) / CELL))
    j = np.clip((np.abs(ay) / CELL).astype(int), 0, int((AY_RANGE[1] - AY_RANGE[0]) / CELL))
    return i, j


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--train", nargs="+", required=True)
    ap.add_argument("--laps", nargs="+", required=True)
    ap.add_argument("--figure", required=True)
    ap.add_argument("--json", required=True)
    a = ap.parse_args(argv)
    model = OnnxModel.load(a.model)
    spec = FeatureSpec.from_json(model.card["feature_spec"])
    train = load_runs(a.train, needed=["ax_mps2", "ay_mps2"])
    tax = np.concatenate([r.table["ax_mps2"] for r in train])
    tay = np.concatenate([r.table["ay_mps2"] for r in train])
    ok = np.isfinite(tax) & np.isfinite(tay)
    cover = _grid(tax[ok], tay[ok]) >= MIN_ROWS
    out: dict = {"model": Path(a.model).name, "model_sha256": model.card.get("sha256"),
                 "train": [Path(t).name for t in a.train], "cell_mps2": CELL, "min_rows": MIN_ROWS, "laps": []}
    from virtsensor import plotting

    fig = plotting.figure(5.0 * len(a.laps), 4.2)
    for k, lap_path in enumerate(a.laps):
        (run,) = load_runs([lap_path])
        ds = build_dataset([run], spec)
        err = np.abs(model.predict(ds.X) - ds.Y).mean(axis=1)
        n = len(err)
        # the lap's rows the dataset kept, by their time (it drops the first rows, and any row with a NaN)
        rows = np.searchsorted(np.asarray(run.table["time_s"], float), ds.time_s)
        ax_l = np.asarray(run.table["ax_mps2"])[rows]
        ay_l = np.asarray(run.table["ay_mps2"])[rows]
        i, j = _cells(ax_l, ay_l)
        inside = cover[np.minimum(i, cover.shape[0] - 1), np.minimum(j, cover.shape[1] - 1)]
        row = {"lap": Path(lap_path).name, "rows": int(n), "outside_share": float(1 - inside.mean()),
               "mae_inside_nm": float(err[inside].mean()) if inside.any() else None,
               "mae_outside_nm": float(err[~inside].mean()) if (~inside).any() else None,
               "mae_nm": float(err.mean())}
        out["laps"].append(row)
        print(f"{row['lap']}: MAE {row['mae_nm']:.2f} Nm; {100 * row['outside_share']:.0f} % of rows outside the "
              f"training's (ax, |ay|) cells, MAE there {row['mae_outside_nm'] or float('nan'):.2f} Nm against "
              f"{row['mae_inside_nm'] or float('nan'):.2f} Nm inside", file=sys.stderr)
        axp = fig.add_subplot(1, len(a.laps), k + 1)
        axp.imshow(cover.T, origin="lower", extent=(*AX_RANGE, *AY_RANGE), aspect="auto", cmap="Greys",
                   alpha=0.35, vmin=0, vmax=1.5)
        sc = axp.scatter(ax_l, np.abs(ay_l), c=err, s=3, cmap="viridis", vmin=0, vmax=20)
        axp.set_xlabel("ax (m/s²): braking < 0 < traction")
        axp.set_ylabel("|ay| (m/s²)")
        axp.set_title(f"{row['lap']}\nMAE {row['mae_nm']:.1f} Nm, {100 * row['outside_share']:.0f} % outside")
    fig.colorbar(sc, ax=fig.axes, label="|error| (Nm), mean of both wheels")
    plotting.save(fig, a.figure)
    write_json(a.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
