#!/usr/bin/env python3
"""Why the paper-faithful MLP scores a lower test R2 on our ``paper`` preset than Table IV.

The paper reports test R2 0.982 / MAE 2.59 Nm for ``RobustScaler + MLP(32, 12)``
on its random 70/30 split. On our ``paper`` campaign the same recipe scores
about 0.95. This study tests, one at a time, the causes that could explain the
gap, each on the same runs and the same random split:

* optimisation: the recipe as shipped stops early on 10 % of its rows; the
  same trained to convergence;
* sensor realism: the same campaign with ideal sensors (no noise, latency,
  bias or quantisation beyond the DBC's; every signal updated at 100 Hz);
* eq. (1)'s hidden state: the same (32, 12) network given the steering-wheel
  rate and acceleration that a static MLP cannot see;
* capacity: wider networks on the same 12 inputs (an estimate of how far a
  static map of the 12 inputs can go on these data);
* error anatomy: how the squared error (which R2 measures) is spread over rows,
  manoeuvres and road friction, and how much the fast-steering rows carry.

Every MLP figure is the median over ``--seeds`` initialisations. Usage::

    python tools/paper_gap_study.py --out docs/paper_gap      # about 10 min on 2 cores
    # -> docs/paper_gap.json (every figure) and docs/paper_gap.md (tables)

``--data DIR`` reuses an existing ``paper`` campaign (e.g. ``build/rebuild/paper``
of ``tools/rebuild_models.sh``) instead of simulating it; it must have been
made with the same ``--seed``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

FAST_RATE_RADPS = np.radians(200.0)  # steering-wheel rate counted as "fast steering"
FAST_ACCEL_RADPS2 = np.radians(1000.0)


def _campaign(out: Path, seed: int, n_jobs: int, params: Path | None = None) -> None:
    from virtsensor.cli import main as cli

    argv = ["campaign", "paper", "--out", str(out), "--seed", str(seed), "--quiet", "--jobs", str(n_jobs)]
    if params is not None:
        argv += ["--params", str(params)]
    if cli(argv) != 0:
        raise SystemExit(f"paper_gap_study: simulating the campaign into {out} failed")


def _ideal_sensor_params(path: Path) -> Path:
    """A car-parameter TOML that makes every sensor ideal (updated at 100 Hz, exact)."""
    from sim.params import load_defaults

    lines = ["[sensors]"]
    for key in load_defaults()["sensors"]:
        lines.append(f"{key} = {{ rate_hz = 100.0, latency_s = 0.0, noise = 0.0, bias = 0.0, gain = 1.0, "
                     "resolution = 0.0 }")
    path.write_text("\n".join(lines) + "\n")
    return path


def _dataset(directory: Path):
    from virtsensor.features import PAPER, Feature, FeatureSpec
    from virtsensor.learning.dataset import build_dataset, load_runs

    spec = FeatureSpec("paper+eq1", PAPER.features + (Feature("steer_angle_rad", "rate"),
                                                      Feature("steer_angle_rad", "accel")))
    return build_dataset(load_runs([directory]), spec)


def _fit(X: np.ndarray, Y: np.ndarray, train: np.ndarray, test: np.ndarray, params: dict[str, Any],
         seed: int) -> dict[str, Any]:
    from sklearn.exceptions import ConvergenceWarning
    from threadpoolctl import threadpool_limits

    from virtsensor.learning.training import make_pipeline
    from virtsensor.metrics import metrics

    t0 = time.perf_counter()
    with warnings.catch_warnings(), threadpool_limits(1):
        warnings.simplefilter("ignore", ConvergenceWarning)
        model = make_pipeline(params, seed).fit(X[train], Y[train])
    P = model.predict(X[test])
    return {"train": metrics(Y[train], model.predict(X[train])), "test": metrics(Y[test], P),
            "epochs": int(model.named_steps["mlp"].n_iter_), "seconds": time.perf_counter() - t0,
            "pred": P.astype(np.float32)}


def _median(fits: list[dict[str, Any]]) -> dict[str, Any]:
    def med(part: str, key: str) -> float:
        return float(np.median([f[part][key] for f in fits]))

    return {"train_r2": med("train", "r2"), "test_r2": med("test", "r2"), "test_mae_nm": med("test", "mae_nm"),
            "test_r2_per_seed": [round(f["test"]["r2"], 4) for f in fits],
            "epochs": int(np.median([f["epochs"] for f in fits])),
            "fit_s": float(np.median([f["seconds"] for f in fits]))}


def _anatomy(ds, test: np.ndarray, P: np.ndarray) -> dict[str, Any]:
    """Where the test error sits (squared error is what R2 counts)."""
    from virtsensor.metrics import metrics

    Y = ds.Y[test]
    E = P - Y
    se = (E ** 2).sum(axis=1)
    sse = float(se.sum())
    worst = np.sort(se)[::-1]
    k = max(1, len(se) // 100)
    rate = np.abs(ds.X[test, 12])
    accel = np.abs(ds.X[test, 13])
    fast = (rate >= FAST_RATE_RADPS) | (accel >= FAST_ACCEL_RADPS2)
    meta_mu = np.array([m.get("mu", np.nan) for m in ds.meta])[ds.groups[test]]
    meta_man = np.array([m.get("manoeuvre", "?") for m in ds.meta])[ds.groups[test]]

    def group(mask: np.ndarray) -> dict[str, Any]:
        m = metrics(Y[mask], P[mask])
        return {"rows": int(mask.sum()), "row_share": float(mask.mean()), "sse_share": float(se[mask].sum() / sse),
                "sat_std_nm": float(Y[mask].std(axis=0).mean()), "mae_nm": m["mae_nm"], "r2": m["r2"]}

    return {
        "mae_nm": float(np.abs(E).mean()), "rmse_nm": float(np.sqrt((E ** 2).mean())),
        "rmse_over_mae": float(np.sqrt((E ** 2).mean()) / np.abs(E).mean()),
        "worst_1pct_sse_share": float(worst[:k].sum() / sse),
        "sat_std_nm": float(Y.std(axis=0).mean()),
        "fast_steering": group(fast), "rest": group(~fast),
        "by_mu": {f"{mu:g}": group(meta_mu == mu) for mu in np.unique(meta_mu)},
        "by_manoeuvre": {m: group(meta_man == m) for m in np.unique(meta_man)},
    }


def _markdown(res: dict[str, Any]) -> str:
    ex = res["experiments"]
    out = ["# Why the paper-faithful MLP scores test R2 ≈ 0.95 on our `paper` preset", "",
           f"Made by `python tools/paper_gap_study.py` (campaign seed {res['seed']}, "
           f"{res['rows']:,} rows, MLP figures on the random split are medians over "
           f"{res['seeds']} initialisations; {res['seconds'] / 60:.0f} min). Table IV: test R2 0.982, MAE 2.59 Nm.",
           "", "## One cause at a time", "",
           "Random split: the paper's protocol (70/30 of the rows; medians over the seeds). Runs held out: "
           "30 % of the runs never seen in training (seed 0), as in `virtsensor evaluate`.", "",
           "| experiment | inputs | network | train R2 | test R2 | test MAE (Nm) | test R2 per seed | epochs "
           "| runs held out R2 / MAE (Nm) |",
           "|---|---|---|---:|---:|---:|---|---:|---:|"]
    for e in ex:
        m = e["result"]
        out.append(f"| {e['label']} | {e['inputs']} | {e['network']} | {m['train_r2']:.3f} | {m['test_r2']:.3f} | "
                   f"{m['test_mae_nm']:.2f} | {', '.join(f'{v:.3f}' for v in m['test_r2_per_seed'])} | {m['epochs']} "
                   f"| {m['runs_r2']:.3f} / {m['runs_mae_nm']:.2f} |")
    base = ex[0]["result"]["test_r2"]
    gains = sorted(((e["result"]["test_r2"] - base, e["label"]) for e in ex[1:]), reverse=True)
    out += ["", "Test R2 against the first row: " + "; ".join(f"{label} {g:+.3f}" for g, label in gains) + "."]
    a = res["anatomy"]
    out += ["", "## Where the squared error sits (paper recipe as shipped, seed 0, test rows)", "",
            f"- MAE {a['mae_nm']:.2f} Nm, RMSE {a['rmse_nm']:.2f} Nm: RMSE/MAE = {a['rmse_over_mae']:.2f} "
            "(1.25 for Gaussian errors; larger means heavy tails).",
            f"- The worst 1 % of rows carry {100 * a['worst_1pct_sse_share']:.0f} % of the squared error.",
            f"- Fast steering (|rate| ≥ 200 °/s or |acceleration| ≥ 1000 °/s²): "
            f"{100 * a['fast_steering']['row_share']:.0f} % of rows, "
            f"{100 * a['fast_steering']['sse_share']:.0f} % of the squared error, "
            f"MAE {a['fast_steering']['mae_nm']:.2f} Nm, R2 {a['fast_steering']['r2']:.3f}; "
            f"the other rows: MAE {a['rest']['mae_nm']:.2f} Nm, R2 {a['rest']['r2']:.3f}.", "",
            "| group | rows | SAT std (Nm) | MAE (Nm) | R2 | share of squared error |",
            "|---|---:|---:|---:|---:|---:|"]
    for title, groups in (("road friction", a["by_mu"]), ("manoeuvre", a["by_manoeuvre"])):
        for name, g in groups.items():
            out.append(f"| {title} {name} | {g['rows']} | {g['sat_std_nm']:.1f} | {g['mae_nm']:.2f} | {g['r2']:.3f} | "
                       f"{100 * g['sse_share']:.0f} % |")
    out += ["", "Every figure, per seed, is in the JSON file of the same name.", ""]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, help="existing paper campaign of --seed (default: simulate it)")
    ap.add_argument("--seed", type=int, default=0, help="campaign and split seed")
    ap.add_argument("--seeds", type=int, default=3, help="MLP initialisations per experiment")
    ap.add_argument("--n-jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("docs/paper_gap"), help="writes OUT.json and OUT.md")
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.n_jobs < 1:
        print("paper_gap_study: --seeds and --n-jobs must be >= 1", file=sys.stderr)
        return 2
    if args.data is not None and not (args.data / "manifest.json").exists():
        print(f"paper_gap_study: --data {args.data}: not a campaign directory (no manifest.json)", file=sys.stderr)
        return 2

    from joblib import Parallel, delayed
    from tqdm import tqdm

    from virtsensor.learning.evaluation import grouped_split, random_split
    from virtsensor.learning.training import PAPER_PARAMS

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        bus_dir = args.data
        if bus_dir is None:
            bus_dir = Path(tmp) / "paper"
            _campaign(bus_dir, args.seed, args.n_jobs)
        ideal_dir = Path(tmp) / "paper-ideal-sensors"
        _campaign(ideal_dir, args.seed, args.n_jobs, _ideal_sensor_params(Path(tmp) / "ideal.toml"))
        data = {"bus": _dataset(bus_dir), "ideal": _dataset(ideal_dir)}

    paper12 = list(range(12))
    eq1 = list(range(14))
    converged = {"early_stopping": False, "max_iter": 2000}
    experiments = [
        ("paper recipe as shipped (early stopping on 10 % of rows)", "bus", paper12, {}),
        ("same, trained to convergence (no early stopping)", "bus", paper12, converged),
        ("ideal sensors", "ideal", paper12, {}),
        ("+ steering rate and acceleration of eq. (1)", "bus", eq1, {}),
        ("wider network, to convergence", "bus", paper12, {**converged, "hidden_layer_sizes": (64, 32)}),
        ("much wider network, to convergence", "bus", paper12, {**converged, "hidden_layer_sizes": (128, 64)}),
    ]
    # the splits of `virtsensor evaluate`: the paper's rows at random, and whole runs held out
    splits = {k: {"random": random_split(len(d.X), args.seed), "runs": grouped_split(d.groups, args.seed)}
              for k, d in data.items()}
    jobs = [(i, s, "random") for i in range(len(experiments)) for s in range(args.seeds)]
    jobs += [(i, 0, "runs") for i in range(len(experiments))]
    # longest fits first, so the short ones fill the workers at the end
    jobs.sort(key=lambda j: -sum(experiments[j[0]][3].get("hidden_layer_sizes", (32, 12))))

    def task(i: int, s: int, split: str):
        _, key, cols, over = experiments[i]
        # the arrays go to the workers as arguments, which joblib memory-maps, not inside a closure
        return delayed(_fit)(data[key].X[:, cols], data[key].Y, *splits[key][split], {**PAPER_PARAMS, **over}, s)

    fits: dict[int, list[dict[str, Any]]] = {i: [] for i in range(len(experiments))}
    held_out: dict[int, dict[str, Any]] = {}
    preds: dict[int, np.ndarray] = {}
    with tqdm(total=len(jobs), desc="fits", unit="fit") as bar:
        results = Parallel(n_jobs=args.n_jobs, return_as="generator")(task(*job) for job in jobs)
        for (i, s, split), f in zip(jobs, results, strict=True):
            pred = f.pop("pred")
            if split == "runs":
                held_out[i] = f
            else:
                fits[i].append(f)
                if s == 0:
                    preds[i] = pred
            bar.update(1)

    res: dict[str, Any] = {
        "seed": args.seed, "seeds": args.seeds, "rows": int(len(data["bus"].X)),
        "paper_table_iv": {"test_r2": 0.982, "test_mae_nm": 2.59},
        "experiments": [{"label": label, "data": key,
                         "inputs": "12 of Table II" + (" + steering rate, acceleration" if len(cols) > 12 else ""),
                         "network": str(tuple((PAPER_PARAMS | over)["hidden_layer_sizes"])),
                         "params": dict(over),
                         "result": {**_median(fits[i]), "runs_r2": held_out[i]["test"]["r2"],
                                    "runs_mae_nm": held_out[i]["test"]["mae_nm"]},
                         "fits": fits[i], "runs_held_out": held_out[i]}
                        for i, (label, key, cols, over) in enumerate(experiments)],
        "anatomy": _anatomy(data["bus"], splits["bus"]["random"][1], preds[0].astype(np.float64)),
    }
    res["seconds"] = time.perf_counter() - t0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{args.out}.json").write_text(json.dumps(res, indent=1, default=str) + "\n")
    Path(f"{args.out}.md").write_text(_markdown(res))
    print(_markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
