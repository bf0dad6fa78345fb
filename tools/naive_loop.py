#!/usr/bin/env python3
"""The daemon's CPU at 20 Hz against a naive loop and a floor loop on the same frames and model, interleaved.

The naive loop is what an integrator writes first (issue 15, item 9): a python-can ``Notifier`` whose thread
wakes for every frame and decodes it with cantools into a dict of latest values, and a 20 Hz loop that builds
the feature vector (the project's :class:`~virtsensor.features.FeatureBuilder`, so both run the same model on
the same vectors), runs onnxruntime (``InferenceSession.run``, one thread) and sends SAT_FRONT encoded by
cantools. No E2E (a zero CRC), no timeouts, no statuses: it does less than the daemon. Both are fed by the
bench's feeder (each frame at its own instant, :func:`virtsensor.daemon.bench.feeder_thread`) on python-can's
``virtual`` bus, and both are measured as the CPU time of their own threads over wall time (% of one core); the daemon
holds its PM QoS CPU-latency request only when ``--cpu-latency-us`` is given, the naive loop never.

The floor loop is the least any daemon built on python-can and onnxruntime does at 20 Hz on these frames: one
thread that wakes every 50 ms, drains the bus (``recv(0)`` until empty) keeping each frame's raw bytes by ID (no
decode, no E2E, no timeouts, no statuses, no features), runs the model once through a preallocated onnxruntime
IOBinding and sends one preallocated SAT_FRONT frame. It holds the same PM QoS request as the daemon. Its CPU is
what the machine charges for waking, reading the frames and running the model at all; the daemon's figure
over it is what the daemon's own work costs.

Usage::

    python tools/naive_loop.py [--rounds 3] [--seconds 10] [--cpu-latency-us 0] [--json F]

Prints each round's figures, then the medians and their ratios (naive / daemon, daemon / floor).
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


@contextmanager
def fed_virtual_bus() -> Iterator[tuple[Any, threading.Event]]:
    """``(bus, stop)``: a fresh ``virtual`` bus fed by the bench's feeder (each input frame at its own instant), its
    peer's own queue drained, until the block ends (``stop`` set, threads joined, both buses shut down)."""
    import can

    from virtsensor.daemon import bench

    ch = bench.virtual_channel()
    peer, bus = can.Bus(interface="virtual", channel=ch), can.Bus(interface="virtual", channel=ch)
    stop = threading.Event()
    feeder = bench.feeder_thread(peer, bench.Inputs(), stop)

    def drain() -> None:
        while not stop.is_set():
            peer.recv(0.05)

    drainer = threading.Thread(target=drain, name="peer-drain", daemon=True)
    try:
        feeder.start()
        drainer.start()
        yield bus, stop
    finally:
        stop.set()
        for th in (feeder, drainer):
            if th.ident is not None:
                th.join(2)
        bus.shutdown()
        peer.shutdown()


def measure(threads: list[threading.Thread], seconds: float, sent: list[int]) -> tuple[float, float]:
    """CPU (% of one core) of ``threads`` over ``seconds`` after 1 s of settling, and frames sent per second
    (``sent[-1]``, counted by the loop). RuntimeError if a thread dies meanwhile."""
    from virtsensor.daemon import bench

    time.sleep(1.0)  # settle: history filled
    c0, w0, s0 = sum(bench.thread_cpu_s(threads)), time.monotonic(), sent[-1]
    time.sleep(seconds)
    c1, w1, s1 = sum(bench.thread_cpu_s(threads)), time.monotonic(), sent[-1]
    if not all(th.is_alive() for th in threads):
        raise RuntimeError(f"a thread ({', '.join(th.name for th in threads)}) died during the measurement")
    return 100.0 * (c1 - c0) / (w1 - w0), (s1 - s0) / (w1 - w0)


def naive_cpu(seconds: float) -> tuple[float, float]:
    """CPU (% of one core) of the naive loop's two threads over ``seconds`` of feeding, and its SAT_FRONT frames
    sent per second (20 when it keeps up)."""
    import can
    import cantools
    import onnxruntime as ort

    from virtsensor import assets
    from virtsensor import signals as cat
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
    counter = [0, 0]  # alive counter, frames sent

    def tick_loop(bus: Any, stop: threading.Event) -> None:
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

    with fed_virtual_bus() as (bus, stop):
        before = set(threading.enumerate())
        notifier = can.Notifier(bus, [Latest()], timeout=1.0)
        receivers = [th for th in set(threading.enumerate()) - before if th.name.startswith("Notifier")]
        ticker = threading.Thread(target=tick_loop, args=(bus, stop), name="naive-tick", daemon=True)
        try:
            ticker.start()
            if len(receivers) != 1:  # (python-can names the Notifier's receive thread "Notifier for bus")
                raise RuntimeError(f"expected the Notifier's one receive thread, found {len(receivers)}")
            return measure([ticker, *receivers], seconds, counter)
        finally:
            stop.set()
            notifier.stop()
            ticker.join(2)


def floor_cpu(seconds: float, cpu_latency_us: int | None) -> tuple[float, float]:
    """CPU (% of one core) of the floor loop's thread over ``seconds`` of feeding (holding a PM QoS request of
    ``cpu_latency_us`` when given), and its SAT_FRONT frames sent per second (20 when it keeps up)."""
    import can
    import onnxruntime as ort

    from virtsensor import assets
    from virtsensor.daemon.pmqos import CpuLatencyRequest
    from virtsensor.model.onnx import INPUT_NAME, OUTPUT_NAME, make_session

    sess, _ = make_session(assets.model_path().read_bytes())
    n_in = sess.get_inputs()[0].shape[1]
    x, y = np.zeros((1, n_in), np.float32), np.zeros((1, 2), np.float32)
    binding = sess.io_binding()
    binding.bind_ortvalue_input(INPUT_NAME, ort.OrtValue.ortvalue_from_numpy(x))
    binding.bind_ortvalue_output(OUTPUT_NAME, ort.OrtValue.ortvalue_from_numpy(y))
    out = can.Message(arbitration_id=0x300, data=bytearray(8), is_extended_id=False)
    raw: dict[int, bytes] = {}
    sent = [0]

    def tick_loop(bus: Any, stop: threading.Event) -> None:
        recv, run, send = bus.recv, sess.run_with_iobinding, bus.send
        t0 = time.monotonic()
        k = 0
        while not stop.is_set():
            k += 1
            rem = t0 + k * 0.05 - time.monotonic()
            if rem > 0 and stop.wait(rem):
                return
            msg = recv(0)
            while msg is not None:
                raw[msg.arbitration_id] = msg.data
                msg = recv(0)
            run(binding)
            send(out)
            sent[0] += 1

    request = CpuLatencyRequest(cpu_latency_us) if cpu_latency_us is not None else None
    if request is not None and not request.acquire():
        raise RuntimeError(f"PM QoS request refused: {request.error}")
    try:
        with fed_virtual_bus() as (bus, stop):
            ticker = threading.Thread(target=tick_loop, args=(bus, stop), name="floor-tick", daemon=True)
            try:
                ticker.start()
                return measure([ticker], seconds, sent)
            finally:
                stop.set()
                ticker.join(2)
    finally:
        if request is not None:
            request.release()


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
    loops = {"daemon": lambda: (daemon_cpu(args.seconds, args.cpu_latency_us), None),
             "naive": lambda: naive_cpu(args.seconds), "floor": lambda: floor_cpu(args.seconds, args.cpu_latency_us)}
    order = list(loops)
    for r in range(args.rounds):  # (the order rotates: a drift of the machine falls on all three alike)
        row: dict[str, float | int | None] = {"round": r + 1}
        for name in order[r % 3:] + order[:r % 3]:
            cpu, rate = loops[name]()
            row[f"{name}_cpu_percent"] = round(cpu, 3)
            if rate is not None:
                row[f"{name}_sat_front_per_s"] = round(rate, 2)
        rows.append(row)
        print(f"round {r + 1}: daemon {row['daemon_cpu_percent']:.3f} %  naive {row['naive_cpu_percent']:.3f} % "
              f"({row['naive_sat_front_per_s']:.1f} SAT_FRONT/s)  floor {row['floor_cpu_percent']:.3f} % "
              f"({row['floor_sat_front_per_s']:.1f} SAT_FRONT/s)", flush=True)
    med = {name: statistics.median(float(x[f"{name}_cpu_percent"]) for x in rows) for name in loops}  # type: ignore[arg-type]
    out = {"rounds": rows, "seconds": args.seconds, "cpu_latency_us": args.cpu_latency_us,
           "daemon_median": med["daemon"], "naive_median": med["naive"], "floor_median": med["floor"],
           "ratio_naive_over_daemon": round(med["naive"] / med["daemon"], 2),
           "ratio_daemon_over_floor": round(med["daemon"] / med["floor"], 2)}
    print(f"medians: daemon {med['daemon']:.3f} %, naive {med['naive']:.3f} %, floor {med['floor']:.3f} %; "
          f"naive / daemon {out['ratio_naive_over_daemon']:.2f}, daemon / floor {out['ratio_daemon_over_floor']:.2f}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
