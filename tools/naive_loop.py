#!/usr/bin/env python3
"""The daemon's CPU at 20 Hz against a naive loop on the same frames and model, interleaved.

The naive loop is what an integrator writes first (issue 15, item 9): a python-can ``Notifier`` whose thread
wakes for every frame and decodes it with cantools into a dict of latest values, and a 20 Hz loop that builds
the feature vector (the project's :class:`~virtsensor.features.FeatureBuilder`, so both run the same model on
the same vectors), runs onnxruntime (``InferenceSession.run``, one thread) and sends SAT_FRONT encoded by
cantools. No E2E (a zero CRC), no timeouts, no statuses: it does less than the daemon. Both are fed by the
bench's feeder (each frame at its own instant, :func:`virtsensor.daemon.bench.feeder_thread`) on python-can's
``virtual`` bus, and both are measured as the CPU time of their own threads over wall time (% of one core); the daemon
holds its PM QoS CPU-latency request only when ``--cpu-latency-us`` is given, the naive loop never.

Usage::

    python tools/naive_loop.py [--rounds 3] [--seconds 10] [--cpu-latency-us 0] [--json F]

Prints each round's figures, then the medians and their ratio (naive / daemon).
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def naive_cpu(seconds: float) -> tuple[float, float]:
    """CPU (% of one core) of the naive loop's two threads over ``seconds`` of feeding, and its SAT_FRONT frames
    sent per second (20 when it keeps up)."""
    import can
    import cantools
    import onnxruntime as ort

    from virtsensor import assets
    from virtsensor import signals as cat
    from virtsensor.daemon import bench
    from virtsensor.features import FeatureBuilder, FeatureSpec
    from virtsensor.model.card import ModelCard, card_path_for

    model = assets.model_path()
    card = ModelCard.read(card_path_for(model))
    spec = FeatureSpec.from_json(card["feature_spec"])
    db = cantools.database.load_file(str(assets.dbc_path()))
    where = {(cat.SIGNALS[n].message, cat.SIGNALS[n].dbc_signal): i for i, n in enumerate(spec.signals)}
    latest = [float("nan")] * len(spec.signals)
    by_id = {m.frame_id: m for m in db.messages}

    class Latest(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            m = by_id.get(msg.arbitration_id)
            if m is None:
                return
            for k, v in m.decode(msg.data, decode_choices=False).items():
                i = where.get((m.name, k))
                if i is not None:
                    latest[i] = float(v)

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    sess = ort.InferenceSession(str(model), opts, providers=["CPUExecutionProvider"])
    in_name = sess.get_inputs()[0].name
    sat = db.get_message_by_name("SAT_FRONT")
    lo, hi = sat.get_signal_by_name("SAT_FL").minimum, sat.get_signal_by_name("SAT_FL").maximum  # (the DBC's range)
    alive_max = int(sat.get_signal_by_name("SAT_FRONT_Counter").maximum)
    builder = FeatureBuilder(spec)
    ch = bench.virtual_channel()
    peer, bus = can.Bus(interface="virtual", channel=ch), can.Bus(interface="virtual", channel=ch)
    stop = threading.Event()
    feeder = bench.feeder_thread(peer, bench.Inputs(), stop)
    counter = [0, 0]  # alive counter, frames sent

    def tick_loop() -> None:
        t0 = time.monotonic()
        k = 0
        while not stop.is_set():
            k += 1
            rem = t0 + k * 0.05 - time.monotonic()
            if rem > 0 and stop.wait(rem):
                return
            x = builder.push(latest)
            if x is None or not np.all(np.isfinite(x)):
                continue
            y = sess.run(None, {in_name: np.asarray([x], dtype=np.float32)})[0][0]
            counter[0] = (counter[0] + 1) % (alive_max + 1)
            values = {"SAT_FRONT_CRC": 0, "SAT_FRONT_Counter": counter[0], "SAT_FL_Status": 0, "SAT_FR_Status": 0,
                      "SAT_FL": min(max(float(y[0]), lo), hi), "SAT_FR": min(max(float(y[1]), lo), hi)}
            bus.send(can.Message(arbitration_id=sat.frame_id, data=sat.encode(values), is_extended_id=False))
            counter[1] += 1

    def drain() -> None:
        while not stop.is_set():
            peer.recv(0.05)

    before = set(threading.enumerate())
    notifier = can.Notifier(bus, [Latest()], timeout=1.0)
    receivers = [th for th in set(threading.enumerate()) - before if th.name.startswith("Notifier")]
    ticker = threading.Thread(target=tick_loop, name="naive-tick", daemon=True)
    drainer = threading.Thread(target=drain, name="naive-drain", daemon=True)
    try:
        feeder.start()
        drainer.start()
        ticker.start()
        time.sleep(1.0)  # settle: history filled
        threads = [ticker, *receivers]  # (the Notifier's receive thread: python-can names it "Notifier for bus")
        if len(threads) != 2:
            raise RuntimeError(f"expected the Notifier's one receive thread, found {len(receivers)}")
        c0, w0, s0 = sum(bench.thread_cpu_s(threads)), time.monotonic(), counter[1]
        time.sleep(seconds)
        c1, w1, s1 = sum(bench.thread_cpu_s(threads)), time.monotonic(), counter[1]
        if not all(th.is_alive() for th in threads):
            raise RuntimeError("a thread of the naive loop died during the measurement")
    finally:
        stop.set()
        notifier.stop()
        for th in (ticker, feeder, drainer):
            if th.ident is not None:
                th.join(2)
        bus.shutdown()
        peer.shutdown()
    return 100.0 * (c1 - c0) / (w1 - w0), (s1 - s0) / (w1 - w0)


def daemon_cpu(seconds: float, cpu_latency_us: int | None) -> float:
    from virtsensor import assets
    from virtsensor.canbus.codec import CanMatrix
    from virtsensor.daemon import bench
    from virtsensor.model.onnx import OnnxModel

    model = OnnxModel.load(assets.model_path())
    fr = bench.measure_free_running(model, CanMatrix.load(assets.dbc_path()), bench.Inputs(), seconds,
                                    cpu_latency_us)
    return float(bench.daemon_cpu_percent(fr))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--cpu-latency-us", type=int, default=None,
                    help="the daemon's PM QoS CPU-latency request (default: none, as the naive loop)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    logging.getLogger("virtsensor").setLevel(logging.ERROR)  # (the daemon's events, e.g. envelope exits: not here)
    rows = []
    for r in range(args.rounds):  # (the order alternates: a drift of the machine falls on both alike)
        if r % 2:
            n, rate = naive_cpu(args.seconds)
            d = daemon_cpu(args.seconds, args.cpu_latency_us)
        else:
            d = daemon_cpu(args.seconds, args.cpu_latency_us)
            n, rate = naive_cpu(args.seconds)
        rows.append({"round": r + 1, "daemon_cpu_percent": round(d, 3), "naive_cpu_percent": round(n, 3),
                     "naive_sat_front_per_s": round(rate, 2)})
        print(f"round {r + 1}: daemon {d:.3f} %  naive {n:.3f} % ({rate:.1f} SAT_FRONT/s)", flush=True)
    med_d = statistics.median(x["daemon_cpu_percent"] for x in rows)
    med_n = statistics.median(x["naive_cpu_percent"] for x in rows)
    out = {"rounds": rows, "seconds": args.seconds, "cpu_latency_us": args.cpu_latency_us,
           "daemon_median": med_d, "naive_median": med_n, "ratio_naive_over_daemon": round(med_n / med_d, 2)}
    print(f"medians: daemon {med_d:.3f} %, naive {med_n:.3f} %; naive / daemon {med_n / med_d:.2f}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
