#!/usr/bin/env python3
"""Micro-benchmarks behind the README's "Measured figures" rows that no other command makes.

* the MF 6.1 tyre model: one ``steady_state`` call on 150 runs x 4 wheels;
* the CAN codec: encode and decode (with the E2E check) of one input frame;
* ONNX batch inference of the shipped models on a paper-sized matrix (46,885 rows);
* with ``--data DIR`` (a ``paper`` campaign, e.g. ``build/rebuild/paper``): the
  fit of the paper recipe on it, with one BLAS thread.

Every figure is the median over ``--repeats`` timings. Usage::

    python tools/microbench.py [--data build/rebuild/paper] [--json bench_micro.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PAPER_ROWS = 46885


def _median_s(fn: Callable[[], object], repeats: int, inner: int = 1) -> float:
    """Median over ``repeats`` of the time of ``inner`` calls, per call (s)."""
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        times.append((time.perf_counter() - t0) / inner)
    return statistics.median(times)


def tyre_call_ms(repeats: int) -> float:
    from sim.params import car_parameters, resolve_data_file
    from sim.tyre import MagicFormula61

    tyre = MagicFormula61.from_tir(resolve_data_file(car_parameters()["tyres"]["file"]))
    rng = np.random.default_rng(0)
    shape = (150, 4)
    fz = rng.uniform(2000.0, 7000.0, shape)
    kappa = rng.uniform(-0.1, 0.1, shape)
    alpha = rng.uniform(-0.2, 0.2, shape)
    gamma = rng.uniform(-0.05, 0.05, shape)
    vx = rng.uniform(5.0, 40.0, shape)
    return 1e3 * _median_s(lambda: tyre.steady_state(fz, kappa, alpha, gamma, vx), repeats, inner=20)


def can_frame_us(repeats: int) -> dict[str, float]:
    from virtsensor import signals as cat
    from virtsensor.canbus.codec import CanMatrix
    from virtsensor.canbus.e2e import next_counter

    matrix = CanMatrix.load()
    values = {n: 0.5 * (cat.SIGNALS[n].minimum + cat.SIGNALS[n].maximum) for n in cat.INPUTS}
    msgs = [matrix.messages[m] for m in sorted({matrix.message_of(n) for n in cat.INPUTS})]
    # one alive-counter period of frames, decoded in order with a timestamp 10 ms apart, so the E2E check
    # sees an intact sequence (decode timed on its own: no difference of two noisy medians)
    rounds = []
    counter = 0
    for _ in range(15):
        rounds.append([(m.frame_id, matrix.encode(m.name, values, counter)) for m in msgs])
        counter = next_counter(counter)
    state = {"t": 0.0, "k": 0}

    def encode() -> None:
        for m in msgs:
            matrix.encode(m.name, values, 1)

    def decode() -> None:
        k = state["k"]
        state["k"] = k + 1
        state["t"] += 0.01
        t = state["t"]
        for fid, data in rounds[k % 15]:
            matrix.decode(fid, data, t)

    enc = _median_s(encode, repeats, inner=200) / len(msgs)
    dec = _median_s(decode, repeats, inner=200) / len(msgs)
    return {"encode_us": 1e6 * enc, "decode_us": 1e6 * dec}


def onnx_rows_per_s(repeats: int) -> dict[str, float]:
    from virtsensor.model.onnx import OnnxModel

    out = {}
    for name in ("paper", "improved"):
        model = OnnxModel.load(ROOT / "models" / f"{name}.onnx")
        X = np.random.default_rng(0).normal(size=(PAPER_ROWS, model.n_features))
        out[name] = PAPER_ROWS / _median_s(lambda m=model, x=X: m.predict(x), repeats)
    return out


def paper_fit_s(data: Path, repeats: int) -> float:
    import warnings

    from threadpoolctl import threadpool_limits

    from virtsensor.features import PAPER
    from virtsensor.learning.dataset import build_dataset, load_runs
    from virtsensor.learning.training import PAPER_PARAMS, make_pipeline

    ds = build_dataset(load_runs([data]), PAPER)
    times = []
    with threadpool_limits(1), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for _ in range(repeats):
            t0 = time.perf_counter()
            make_pipeline(PAPER_PARAMS, 0).fit(ds.X, ds.Y)
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, help="a paper campaign: also time the paper recipe's fit on it")
    ap.add_argument("--repeats", type=int, default=5, help="timings per figure (median reported)")
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        print("microbench: --repeats must be >= 1", file=sys.stderr)
        return 2
    if args.data is not None and not args.data.is_dir():
        print(f"microbench: --data {args.data}: no such directory", file=sys.stderr)
        return 2

    res: dict[str, object] = {"repeats": args.repeats, "tyre_call_150x4_ms": tyre_call_ms(args.repeats),
                              "can_frame": can_frame_us(args.repeats),
                              "onnx_rows_per_s_46885": onnx_rows_per_s(args.repeats)}
    if args.data is not None:
        res["paper_fit_s"] = paper_fit_s(args.data, min(args.repeats, 3))
    can = res["can_frame"]
    onnx = res["onnx_rows_per_s_46885"]
    print(f"tyre model, one call on 150 runs x 4 wheels: {res['tyre_call_150x4_ms']:.2f} ms")
    print(f"CAN encode / decode (with E2E), one frame: {can['encode_us']:.1f} / {can['decode_us']:.1f} us")
    print(f"ONNX batch inference, {PAPER_ROWS:,} rows: {onnx['paper'] / 1e6:.1f} M rows/s (paper), "
          f"{onnx['improved'] / 1e6:.1f} M rows/s (improved)")
    if "paper_fit_s" in res:
        print(f"paper recipe fit, one BLAS thread: {res['paper_fit_s']:.1f} s")
    if args.json is not None:
        args.json.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
