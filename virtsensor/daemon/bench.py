"""``virtsensor bench``: latency, jitter, throughput, CPU/RSS and soak figures of the daemon.

Every figure is taken on a real :class:`~virtsensor.daemon.VirtualSensor` on python-can's in-process
``virtual`` bus (``cross_process``: ``udp_multicast`` in a private network namespace, null with a reason
where that is not permitted). Input: the frames of a simulated manoeuvre (:data:`MANOEUVRE`) as
:func:`virtsensor.recordings.canlog.iter_frames` writes them, shipped with the package
(:func:`virtsensor.assets.bench_inputs_path`: the bench runs on the base install; only another manoeuvre is
simulated, :func:`simulated_frames`, which needs the simulator), a sync
frame (:func:`~virtsensor.daemon.layout.sync_frames`) after each 20 Hz instant, and a window of ``LOOP_S``
seconds replayed in a loop (timestamps shifted by ``LOOP_S`` per loop; the window holds a whole multiple of
15 frames of every 10/20/100 ms message, so the Profile 11 alive counters, 0..14, stay continuous).

Figures (keys of :func:`run_bench`'s result; times in us unless the key says otherwise):

* ``stages_us``: per stage of a sync-mode tick (decode per input frame; features, inference, encode, send per
  tick), timed with ``perf_counter_ns`` by thin proxies put in place on that instance (each figure includes
  the proxy call);
* ``stages_after_idle_us``: the same stages when the bench thread sleeps :data:`IDLE_S` before each tick's
  frames, as the 20 Hz daemon sleeps between ticks, plus ``tick``: each tick's whole work (its frames, the
  tick, its sends). Against ``stages_us`` it shows what running on caches gone cold costs each stage, which is
  what ``cpu_percent_at_20hz`` pays;
* ``tick_compute_us``: the daemon's own tick start -> SAT_FRONT encoded (no bus I/O), un-instrumented;
* ``e2e_latency_us``: send of a tick's last input frame -> SAT_FRONT received by a listener;
* ``jitter_us``, ``cpu_percent_at_20hz``, ``rss_mb_20hz``: the daemon on its free-running 20 Hz clock, fed
  in real time; jitter is wake-up lateness against the drift-free schedule; CPU is the CPU time of the
  daemon's two threads over wall time, in % of one core. The daemon holds a PM QoS CPU-latency request
  (``cpu_latency_request``; :mod:`virtsensor.daemon.pmqos`) as ``virtsensor run --cpu-latency-us`` does; the
  same figures with the machine's own idle policy are ``*_default_idle``;
* ``inference_us``: onnxruntime, the scikit-learn pipeline rebuilt from the card's ``weights`` and the numpy
  forward pass on the same feature vectors (skipped with a reason when the card has no ``weights``);
* soak: ``soak_ticks`` ticks as fast as possible; ``max_tick_rate_hz`` = ticks / wall time,
  ``missed_ticks`` = ticks whose SAT_FRONT did not arrive or whose compute exceeded :data:`BUDGET_US`;
* ``feature_cost``: the max tick rate without each optional feature of the tick (:data:`FEATURES`) and without
  all of them, and what each costs per tick (:func:`measure_feature_cost`).

Measured figures and the command that makes them: README, "Measured figures".
"""

from __future__ import annotations

import gc
import hashlib
import logging
import math
import os
import platform
import threading
import time
import uuid
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import assets
from virtsensor.daemon.layout import SYNC_ID, SYNC_OFFSET_S, sync_frames
from virtsensor.errors import UserError
from virtsensor.fileio import atomic_write_bytes
from virtsensor.signals import TABLE_TICK_S as TICK_S

__all__ = ["run_bench", "write_markdown", "write_histogram", "percentiles", "await_frame", "Inputs",
           "measure_free_running", "feeder_thread", "virtual_channel", "thread_cpu_s", "daemon_cpu_percent"]

#: replayed window (s): 3.0 s holds a multiple of 15 frames (one alive-counter period) of every 10/20/100 ms message
LOOP_S = 3.0
WINDOW_START_S = 1.0
BUDGET_US = 50_000.0
MANOEUVRE = ("steering-pulse", 60.0, 1.0, 7)

#: counts of a full run and of ``--quick``
FULL = {"stage_ticks": 5000, "idle_ticks": 100, "e2e_ticks": 2000, "jitter_s": 10.0, "soak_ticks": 72_000,
        "xproc_ticks": 400, "cost_ticks": 10_000, "cost_rounds": 3}
QUICK = {"stage_ticks": 200, "idle_ticks": 10, "e2e_ticks": 100, "jitter_s": 1.5, "soak_ticks": 1_000,
         "xproc_ticks": 60, "cost_ticks": 500, "cost_rounds": 1}
#: the tick's optional features (what :func:`measure_feature_cost` switches off): the grip output (VS_Grip; off:
#: a matrix without VS_Grip, as an older DBC, so the daemon publishes SAT_FRONT and VS_Health only), the model
#: card's validity envelope (off: as a card that states none) and the redundancy checks (off: as a model whose
#: inputs include no redundant pair)
FEATURES = ("grip", "envelope", "plausibility")
#: sleep before each tick of the after-idle stage run (s): the 20 Hz daemon's time asleep between ticks
IDLE_S = 0.05


# ---------------------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------------------

def await_frame(bus, frame_id: int, timeout_s: float = 1.0) -> bool:
    """Wait up to ``timeout_s`` for a standard frame ``frame_id`` on ``bus``; True when it came."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        m = bus.recv(0.5)
        if m is not None and m.arbitration_id == frame_id and not m.is_extended_id:
            return True
    return False


def timed_response(tx: Any, rx: Any, batch: list[Any], sync: Any, sat_id: int) -> float | None:
    """Send a tick's last input frame and its sync frame on ``tx``; the time (us) until ``SAT_FRONT`` (``sat_id``)
    arrives on ``rx``, whose stale frames are drained first. None when none comes within :func:`await_frame`'s
    timeout."""
    while rx.recv(0) is not None:
        pass
    t0 = time.perf_counter_ns()
    if batch:
        tx.send(batch[-1])
    tx.send(sync)
    got = await_frame(rx, sat_id)
    return (time.perf_counter_ns() - t0) / 1e3 if got else None


def percentiles(values: Any) -> dict[str, float] | None:
    """p50/p99/p999/max (and mean, n) of ``values``; None when empty."""
    a = np.asarray(values, dtype=float).ravel()
    if a.size == 0:
        return None
    p50, p99, p999 = np.percentile(a, [50, 99, 99.9])
    return {"p50": round(float(p50), 3), "p99": round(float(p99), 3), "p999": round(float(p999), 3),
            "max": round(float(a.max()), 3), "mean": round(float(a.mean()), 3), "n": int(a.size)}


def rss_mb() -> float:
    """Resident set size of this process (MB) from /proc/self/status VmRSS (0 where unavailable)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def machine_info() -> dict[str, Any]:
    cpu = platform.processor() or None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = None
    return {"platform": platform.platform(), "python": platform.python_version(), "cpu_model": cpu,
            "cores": os.cpu_count(), "usable_cores": usable}


# ---------------------------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------------------------
def simulated_frames(manoeuvre: tuple = MANOEUVRE) -> list[Any]:
    """The input frames of ``manoeuvre`` (``simulate``'s arguments) stamped in the bench's window
    ``(WINDOW_START_S, WINDOW_START_S + LOOP_S)`` (s), in time order; needs the simulator (the ``train`` extra)."""
    from sim.api import simulate
    from virtsensor.recordings.canlog import iter_frames

    run = simulate(*manoeuvre)
    time_s = run.streams["time_s"]
    sig = {k: v for k, v in run.streams.items() if k != "time_s"}
    a = WINDOW_START_S
    b = a + LOOP_S
    if time_s[-1] < b + 0.1:
        raise UserError(f"the bench manoeuvre {manoeuvre} is shorter than {b} s")
    return [m for m in iter_frames(time_s, sig) if a - 1e-9 < m.timestamp < b - 1e-9]


def save_frames(frames: Sequence[Any], path: str | os.PathLike) -> None:
    """Write ``frames`` (standard ``can.Message``, at most 8 data bytes) as ``.npz`` arrays, atomically:
    ``timestamp`` (s, float64), ``arbitration_id``, ``dlc``, ``is_extended_id`` and ``data`` (n x 8 bytes)."""
    import io

    data = np.zeros((len(frames), 8), np.uint8)
    for i, m in enumerate(frames):
        data[i, : m.dlc] = np.frombuffer(bytes(m.data), np.uint8)
    buf = io.BytesIO()
    np.savez_compressed(buf, timestamp=np.array([m.timestamp for m in frames], np.float64),
                        arbitration_id=np.array([m.arbitration_id for m in frames], np.uint32),
                        dlc=np.array([m.dlc for m in frames], np.uint8),
                        is_extended_id=np.array([m.is_extended_id for m in frames], bool), data=data)
    atomic_write_bytes(path, buf.getvalue())


def load_frames(path: str | os.PathLike) -> list[Any]:
    """The frames :func:`save_frames` wrote (new ``can.Message`` objects)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            ts, ids, dlc, ext, data = (z[k] for k in ("timestamp", "arbitration_id", "dlc", "is_extended_id",
                                                      "data"))
        if not len(ts) == len(ids) == len(dlc) == len(ext) == len(data):
            raise ValueError("its arrays differ in length")
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise UserError(f"{path}: not the bench's input frames ({type(exc).__name__}: {exc})") from None
    import can

    return [can.Message(timestamp=float(t), arbitration_id=int(i), is_extended_id=bool(e), dlc=int(n),
                        data=bytes(d[:n])) for t, i, e, n, d in zip(ts, ids, ext, dlc, data, strict=True)]


class Inputs:
    """One ``LOOP_S`` window of a simulated manoeuvre's frames, per tick, replayable in a loop.

    ``batches[k]`` is the list of input ``can.Message`` of tick ``k`` of the window (frames stamped after the
    previous tick's grid instant up to this tick's instant), ``syncs[k]`` its sync frame. The default
    manoeuvre's frames are the shipped ones (:func:`virtsensor.assets.bench_inputs_path`: no simulator needed);
    another manoeuvre is simulated (:func:`simulated_frames`).
    """

    def __init__(self, manoeuvre: tuple = MANOEUVRE) -> None:
        a = WINDOW_START_S
        frames = load_frames(assets.bench_inputs_path()) if tuple(manoeuvre) == MANOEUVRE else simulated_frames(
            manoeuvre)
        n_ticks = round(LOOP_S / TICK_S)
        grid = a + np.arange(n_ticks) * TICK_S
        # frame of tick k: stamped in (grid[k-1], grid[k]]; the first window tick also gets frames at grid[0]
        idx = np.searchsorted(grid, [m.timestamp for m in frames], side="left")
        batches: list[list[Any]] = [[] for _ in range(n_ticks + 1)]
        for m, k in zip(frames, idx.tolist(), strict=True):
            batches[k].append(m)
        # frames after the last grid instant belong to the next loop's first tick
        tail = batches.pop()
        batches[0] = tail + batches[0]
        self.batches = batches
        self.base_ts = [[m.timestamp for m in b_] for b_ in batches]
        self.syncs = sync_frames(grid, SYNC_ID)
        self.grid = grid
        self.n_ticks = n_ticks
        self.frames_per_tick = len(frames) / n_ticks
        self.manoeuvre = manoeuvre
        # the tail frames (after the last instant) of loop L are stamped before loop L+1's first instant
        self._tail_n = len(tail)
        self._recount = _slow_message_counters(batches, len(tail))

    def tick(self, k: int) -> tuple[list[Any], Any]:
        """Frames and sync frame of global tick ``k`` (timestamps set for its loop; objects are reused). Tick 0 has
        no frames of a previous loop: every message's alive counter runs on without a jump from the first frame."""
        loop, j = divmod(k, self.n_ticks)
        off = loop * LOOP_S
        batch = self.batches[j]
        ts = self.base_ts[j]
        if j == 0:  # the tail frames come from the previous loop's window end
            tn = self._tail_n
            for i, m in enumerate(batch):
                m.timestamp = ts[i] + off - (LOOP_S if i < tn else 0.0)
        else:
            for i, m in enumerate(batch):
                m.timestamp = ts[i] + off
        for i, variants, base, per_loop in self._recount[j]:  # (a message slower than the loop: the TPMS)
            lp = loop - 1 if j == 0 and i < self._tail_n else loop
            batch[i].data = variants[(base + lp * per_loop) % len(variants)]
        s = self.syncs[j]
        s.timestamp = float(self.grid[j] + SYNC_OFFSET_S + off)
        if k == 0:  # (the tail frames of a loop before the first: none was sent, its counters would jump)
            return batch[self._tail_n:], s
        return batch, s


def _slow_message_counters(batches: list[list[Any]], tail_n: int) -> list[list[tuple[Any, ...]]]:
    """Per tick of the window, ``(index in batch, payloads by alive counter, counter, frames per loop)`` of the
    frames of messages whose frames in the window are not a whole number of counter periods (the TPMS, one frame
    a second, three per 3 s loop): each loop then sends them with their counters continued (CRC recomputed), so
    the Profile 11 check sees an unbroken sequence, as on a car."""
    from virtsensor.canbus.codec import CanMatrix
    from virtsensor.canbus.e2e import COUNTER_MAX

    matrix = CanMatrix.load()
    period = COUNTER_MAX + 1
    count: dict[int, int] = {}
    for b_ in batches:
        for m in b_:
            count[m.arbitration_id] = count.get(m.arbitration_id, 0) + 1
    out: list[list[tuple[Any, ...]]] = [[] for _ in batches]
    for j, b_ in enumerate(batches):
        for i, m in enumerate(b_):
            n = count[m.arbitration_id]
            if n % period == 0 or m.arbitration_id not in matrix.by_id:
                continue
            d = matrix.fresh().decode(m.arbitration_id, bytes(m.data), 0.0)
            if d is None:
                continue
            name = matrix.by_id[m.arbitration_id].name
            variants = [bytearray(matrix.encode(name, dict(d.values), c)) for c in range(period)]
            out[j].append((i, variants, int(m.data[1]) & 0xF, n))
    return out


# ---------------------------------------------------------------------------------------------------------------
# the measurements
# ---------------------------------------------------------------------------------------------------------------
def virtual_channel() -> str:
    """A fresh channel name for python-can's ``virtual`` interface, shared by nothing else in the process."""
    return f"bench-{uuid.uuid4().hex[:10]}"


def _sensor(model: Any, matrix: Any, bus: Any, **kw: Any) -> Any:
    from virtsensor.daemon.sensor import VirtualSensor

    return VirtualSensor(bus, model, matrix, **kw)


def _sync_rig(model: Any, matrix: Any, **kw: Any) -> tuple[str, Any, Any, int]:
    """A sync-mode daemon on a fresh virtual channel (driven from this thread, or started) and a listener
    on the same channel: ``(channel, listener, daemon, SAT_FRONT id)``. The daemon owns its bus
    (``stop()`` shuts it down); the channel lets a caller add its own buses."""
    import can

    ch = virtual_channel()
    bus = can.Bus(interface="virtual", channel=ch)
    listener = can.Bus(interface="virtual", channel=ch)
    vs = _sensor(model, matrix, bus, sync_id=SYNC_ID, **kw)
    return ch, listener, vs, vs.matrix.messages["SAT_FRONT"].frame_id


def _stage_timer(rec: dict[str, list[float]], xs: list[np.ndarray]) -> Callable[[str, Callable[..., Any]], Any]:
    """A ``stage_hook`` of :class:`VirtualSensor` timing each stage call into ``rec[stage]`` (us, with
    ``perf_counter_ns``; each figure includes the wrapper call) and keeping the
    feature vectors in ``xs``."""
    pc = time.perf_counter_ns

    def hook(stage: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        out = rec.setdefault(stage, [])
        if stage == "feature_vector":
            def timed_push(values: Any) -> Any:
                t0 = pc()
                r = fn(values)
                out.append((pc() - t0) / 1e3)
                if r is not None:
                    xs.append(np.array(r, dtype=float))
                return r
            return timed_push

        if stage == "decode":  # per input frame: the generated receiver's own (data, t) signature
            def timed_decode(data: Any, t: float) -> None:
                t0 = pc()
                fn(data, t)
                out.append((pc() - t0) / 1e3)
            return timed_decode

        def timed(*a: Any) -> Any:
            t0 = pc()
            r = fn(*a)
            out.append((pc() - t0) / 1e3)
            return r
        return timed

    return hook


def measure_stages(model: Any, matrix: Any, inputs: Inputs, n_ticks: int,
                   idle_s: float = 0.0) -> tuple[dict[str, Any], np.ndarray]:
    """Per-stage times (us) of a sync-mode daemon driven in this thread, through its ``stage_hook``; also
    returns the feature vectors. ``idle_s`` > 0: the thread sleeps that long before each tick's frames, as the
    daemon does between 20 Hz ticks, so every stage runs on caches other work had the time to evict. The stage
    ``tick`` is each tick's whole work: its frames, the tick, its sends."""
    from virtsensor.daemon.sensor import STAGES

    rec: dict[str, list[float]] = {k: [] for k in STAGES}
    xs: list[np.ndarray] = []
    whole: list[float] = []
    pc = time.perf_counter_ns
    _, listener, vs, _ = _sync_rig(model, matrix, stage_hook=_stage_timer(rec, xs))
    try:
        for k in range(n_ticks):
            batch, sync = inputs.tick(k)
            if idle_s > 0.0:
                time.sleep(idle_s)
            t0 = pc()
            for m in batch:
                vs.process(m)
            vs.process(sync)
            whole.append((pc() - t0) / 1e3)
            if k % 200 == 199 or idle_s > 0.0:
                while listener.recv(0) is not None:
                    pass
        errors = vs.counters["tick_errors"]
    finally:
        vs.stop()
        listener.shutdown()
    if errors:
        raise RuntimeError(f"{errors} tick errors in the stage run")
    out = {k: percentiles(v) for k, v in rec.items()}
    out["tick"] = percentiles(whole)
    return out, (np.array(xs) if xs else np.zeros((0, 0)))


def measure_e2e_in_process(model: Any, matrix: Any, inputs: Inputs, n_ticks: int) -> dict[str, Any]:
    """Last input frame sent -> SAT_FRONT received, daemon started (receive thread) on the virtual bus."""
    import can

    ch, listener, vs, sat_id = _sync_rig(model, matrix)
    listener.shutdown()  # one peer node sends the inputs and reads SAT_FRONT (no never-read queue to copy into)
    tx = can.Bus(interface="virtual", channel=ch, preserve_timestamps=True)
    lat: list[float] = []
    lost = 0
    vs.start()
    try:
        sent = 0
        for k in range(n_ticks):
            batch, sync = inputs.tick(k)
            for m in batch[:-1]:
                tx.send(m)
            sent += len(batch) - 1
            end = time.monotonic() + 2.0
            while vs.counters["frames"] < sent and time.monotonic() < end:
                time.sleep(0)
            us = timed_response(tx, tx, batch, sync, sat_id)
            sent += 1 + bool(batch)
            if us is not None:
                lat.append(us)
            else:
                lost += 1
        st = vs.stats()
    finally:
        vs.stop()
        tx.shutdown()
    out = percentiles(lat) or {}
    out.update(lost=lost, tick_errors=st["tick_errors"])
    return out


def thread_cpu_s(threads: Any) -> list[float]:
    """CPU time (s) of each thread (``pthread_getcpuclockid``; nan where unavailable)."""
    out = []
    for th in threads:
        try:
            out.append(time.clock_gettime(time.pthread_getcpuclockid(th.ident)))
        except (AttributeError, OSError, TypeError):
            out.append(math.nan)
    return out


def feeder_thread(tx: Any, inputs: Inputs, stop: threading.Event) -> threading.Thread:
    """A thread sending the input frames in real time, each at its own simulated instant (frames due
    within 1 ms of each other go together), so every message keeps its cycle on the wire: a 10 ms message
    arrives every 10 ms, not in one burst per tick (which an E2E receiver rightly judges a timeout)."""
    def feed() -> None:
        k = 0
        t0 = time.monotonic()
        while not stop.is_set():
            batch, _ = inputs.tick(k)
            if batch:
                loop, j = divmod(k, inputs.n_ticks)
                opens = float(inputs.grid[j]) + loop * LOOP_S - TICK_S  # the tick's window opens (stamps)
                due_base = t0 + k * TICK_S - opens  # stamp -> send time
                i, n = 0, len(batch)
                while i < n:
                    due = due_base + batch[i].timestamp
                    rem = due - time.monotonic()
                    if rem > 0 and stop.wait(rem):
                        return
                    while i < n and due_base + batch[i].timestamp <= due + 1e-3:
                        tx.send(batch[i])
                        i += 1
            k += 1
            rem = t0 + k * TICK_S - time.monotonic()
            if rem > 0 and stop.wait(rem):
                break

    return threading.Thread(target=feed, name="bench-feeder", daemon=True)


def measure_free_running(model: Any, matrix: Any, inputs: Inputs, seconds: float,
                         cpu_latency_us: int | None = None) -> dict[str, Any]:
    """The daemon on its own 20 Hz timer, inputs fed in real time: jitter, CPU (daemon threads, process), RSS.
    ``cpu_latency_us``: the daemon's PM QoS CPU-latency request (None: none); ``cpu_latency`` in the result says
    whether it was held."""
    import can

    from virtsensor.daemon.runner import SPIN_S

    ch = virtual_channel()
    # one peer node on the channel, as on a car's bus: it sends the inputs (feeder thread) and reads the
    # daemon's frames (drain thread). A second, never-read peer bus would make every daemon send copy its
    # frame into one more queue, which grows without bound.
    peer = can.Bus(interface="virtual", channel=ch)
    vs = _sensor(model, matrix, can.Bus(interface="virtual", channel=ch), cpu_latency_us=cpu_latency_us)
    stop = threading.Event()
    feeder = feeder_thread(peer, inputs, stop)

    def drain() -> None:
        while not stop.is_set():
            peer.recv(0.05)

    drainer = threading.Thread(target=drain, name="bench-drain", daemon=True)
    feeder.start()
    drainer.start()
    time.sleep(0.5)  # the inputs flow before the daemon starts
    vs.start()
    time.sleep(0.5)  # settle: history filled, first ticks done
    threads, ts = vs.threads, vs.tick_stats
    wakes0, ticks0, ov0 = ts.wakes, vs.counters["ticks"], vs.counters["overruns"]
    pt0, p0, w0, rss0 = thread_cpu_s(threads), os.times(), time.monotonic(), rss_mb()
    time.sleep(seconds)
    pt1, p1, w1, rss1 = thread_cpu_s(threads), os.times(), time.monotonic(), rss_mb()
    jit = ts.wake_late_us(wakes0)
    ticks, overruns = vs.counters["ticks"] - ticks0, vs.counters["overruns"] - ov0
    st = vs.stats()
    req = vs.cpu_latency
    latency = None if req is None else {"us": req.us, "held": req.held, "error": req.error}
    vs.stop()
    stop.set()
    feeder.join(2)
    drainer.join(2)
    peer.shutdown()
    wall = w1 - w0
    proc = (p1.user - p0.user) + (p1.system - p0.system)
    cpu = sum(pt1) - sum(pt0)
    return {"jitter_us": percentiles(jit), "ticks": ticks, "overruns": overruns, "wall_s": round(wall, 3),
            "tick_rate_hz": round(ticks / wall, 3) if wall > 0 else None,
            "cpu_percent_daemon_threads": round(100 * cpu / wall, 3) if math.isfinite(cpu) else None,
            "cpu_percent_process": round(100 * proc / wall, 3), "rss_mb": round(max(rss0, rss1), 3),
            "cpu_percent_per_thread": {th.name: (round(100 * (b - a) / wall, 3) if math.isfinite(b - a) else None)
                                       for th, a, b in zip(threads, pt0, pt1, strict=True)},
            "spin_budget_percent": round(100 * SPIN_S * 20, 3),
            "frames_drained_per_tick": round(st["drained_frames"] / max(st["ticks"], 1), 2),
            "tick_compute_p50_us": st.get("compute_p50_us"), "tick_compute_p99_us": st.get("compute_p99_us"),
            "tick_latency_p50_us": st.get("latency_p50_us"), "tick_latency_p99_us": st.get("latency_p99_us"),
            "statuses_at_end": st["statuses"], "cpu_latency": latency}


def _sklearn_pipeline(weights: dict[str, Any]) -> Any:
    """RobustScaler + MLPRegressor rebuilt from :func:`virtsensor.model.export.pipeline_weights` output."""
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import RobustScaler

    Ws = [np.asarray(la["W"], dtype=float) for la in weights["layers"]]
    bs = [np.asarray(la["b"], dtype=float) for la in weights["layers"]]
    n_in = Ws[0].shape[0]
    mlp = MLPRegressor(hidden_layer_sizes=tuple(W.shape[1] for W in Ws[:-1]),
                       activation=str(weights.get("activation", "relu")))
    mlp.coefs_, mlp.intercepts_ = Ws, bs
    mlp.n_layers_ = len(Ws) + 1
    mlp.n_outputs_ = Ws[-1].shape[1]
    mlp.out_activation_ = str(weights.get("out_activation", "identity"))
    mlp.n_features_in_ = n_in
    mlp.n_iter_ = 1
    mlp.t_ = 1
    sc = RobustScaler(with_centering=weights.get("center") is not None,
                      with_scaling=weights.get("scale") is not None)
    sc.center_ = None if weights.get("center") is None else np.asarray(weights["center"], dtype=float)
    sc.scale_ = None if weights.get("scale") is None else np.asarray(weights["scale"], dtype=float)
    sc.n_features_in_ = n_in
    return Pipeline([("scaler", sc), ("mlp", mlp)])


def measure_backends(model: Any, X: np.ndarray, n_max: int) -> dict[str, Any]:
    """onnxruntime / sklearn / numpy on the same feature vectors, one vector per call (us per call)."""
    from virtsensor.model.onnx import numpy_forward

    out: dict[str, Any] = {}
    if X.size == 0:
        return {"onnxruntime": None, "sklearn": None, "numpy": None,
                "skipped": "no feature vectors (the stage run never left INIT)"}
    X = X[:n_max]
    pc = time.perf_counter_ns
    reference = np.array([np.array(model.predict_one(x)) for x in X])

    def time_one(fn: Callable[[np.ndarray], Any]) -> tuple[dict[str, Any] | None, np.ndarray]:
        for x in X[: min(50, len(X))]:  # warm-up
            fn(x)
        ts = np.empty(len(X))
        ys = []
        was = gc.isenabled()
        gc.disable()
        try:
            for i, x in enumerate(X):
                t0 = pc()
                y = fn(x)
                ts[i] = (pc() - t0) / 1e3
                ys.append(np.array(y, dtype=float).ravel())
        finally:
            if was:
                gc.enable()
        return percentiles(ts), np.array(ys)

    out["onnxruntime"], _ = time_one(model.predict_one)
    weights = model.card.get("weights")
    if not isinstance(weights, dict):
        reason = "the model card has no 'weights' (plain arrays) to rebuild the model from"
        out["sklearn"] = out["numpy"] = None
        out["skipped"] = {"sklearn": reason, "numpy": reason}
        return out
    skipped: dict[str, str] = {}
    agree: dict[str, float] = {}
    try:
        pipe = _sklearn_pipeline(weights)
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1):
            out["sklearn"], ys = time_one(lambda x: pipe.predict(x[None, :])[0])
        agree["sklearn"] = float(np.max(np.abs(ys - reference)))
    except Exception as exc:  # noqa: BLE001 - report, do not fail the bench
        out["sklearn"] = None
        skipped["sklearn"] = f"cannot rebuild an sklearn pipeline from the card weights: {type(exc).__name__}: {exc}"
    try:
        fwd = numpy_forward(weights)
        out["numpy"], ys = time_one(fwd.predict_one)
        agree["numpy"] = float(np.max(np.abs(ys - reference)))
    except Exception as exc:  # noqa: BLE001
        out["numpy"] = None
        skipped["numpy"] = f"numpy forward failed: {type(exc).__name__}: {exc}"
    out["max_abs_diff_vs_onnxruntime_nm"] = agree
    if skipped:
        out["skipped"] = skipped
    return out


def run_soak(model: Any, matrix: Any, inputs: Inputs, n_ticks: int,
             progress: Callable[[str], None] | None = None, stage_hook: Any = None) -> dict[str, Any]:
    """``n_ticks`` ticks as fast as possible (sync mode, this thread): compute of every tick, missed ticks,
    RSS every 1,000 ticks, ticks/s. ``stage_hook``: passed to the daemon (see :data:`~virtsensor.daemon.sensor.
    STAGES`; e.g. to replace a stage and measure what it costs). ``e2e_errors``: failed E2E checks after the first
    frame of every input message; ``e2e_errors_first_frames``: those until then, where a message's first frame is a
    wrong sequence unless its alive counter follows 14 (the Profile 11 check starts from counter 14, as AUTOSAR
    specifies) while the replayed window starts mid-sequence."""
    _, listener, vs, sat_id = _sync_rig(model, matrix, stage_hook=stage_hook)
    first_errors = 0
    waiting = [vs.matrix.receivers[name] for name in vs.layout.input_messages]
    compute = np.empty(n_ticks)
    rss_samples: list[tuple[int, float]] = [(0, rss_mb())]
    sat_seen = 0
    done = 0
    chunk = 1000

    def checkpoint(upto: int) -> None:
        nonlocal sat_seen, done
        while True:
            m = listener.recv(0)
            if m is None:
                break
            if m.arbitration_id == sat_id:
                sat_seen += 1
        got = vs.tick_stats.compute_us(done)
        compute[done:done + len(got)] = got
        done += len(got)
        rss_samples.append((upto, rss_mb()))

    gc.collect()
    pc = time.perf_counter_ns
    tick_ns = 0
    t_start = time.perf_counter()
    c_start = time.thread_time()
    for k in range(n_ticks):
        batch, sync = inputs.tick(k)
        for m in batch:
            vs.process(m)
        t0 = pc()
        vs.process(sync)
        tick_ns += pc() - t0
        if waiting and all(r.last_rx_s > -math.inf for r in waiting):  # (every input message's first frame in)
            first_errors, waiting = _e2e_errors(vs.counters), []
        if (k + 1) % chunk == 0 or k + 1 == n_ticks:
            checkpoint(k + 1)
            if progress and (k + 1) % 10_000 == 0:
                progress(f"soak {k + 1}/{n_ticks} ticks")
    wall = time.perf_counter() - t_start
    cpu = time.thread_time() - c_start
    st = vs.stats()
    vs.stop()
    listener.shutdown()
    produced = st["ticks"]
    compute = compute[:done]
    over = int((compute > BUDGET_US).sum())
    not_produced = n_ticks - min(sat_seen, n_ticks)
    rss = [r for _, r in rss_samples]
    return {"ticks": n_ticks, "ticks_produced": produced, "sat_front_received": sat_seen,
            "missed_ticks": not_produced + over, "missed_no_sat_front": not_produced, "missed_over_budget": over,
            "tick_errors": st["tick_errors"], "wall_s": round(wall, 3), "ticks_per_s": round(n_ticks / wall, 1),
            "ticks_per_s_tick_only": round(n_ticks / (tick_ns * 1e-9), 1),
            "cpu_s": round(cpu, 3), "ticks_per_cpu_s": round(n_ticks / cpu, 1) if cpu > 0 else None,
            "frames_per_tick": round(inputs.frames_per_tick, 2), "compute_us": percentiles(compute),
            "compute_samples": compute, "rss_mb_samples": [[k, round(r, 3)] for k, r in rss_samples],
            "rss_mb_start": round(rss[0], 3), "rss_mb_end": round(rss[-1], 3),
            "rss_mb_drift": round(rss[-1] - rss[0], 3),
            "rss_mb_range_after_first_1000": round(max(rss[1:]) - min(rss[1:]), 3) if len(rss) > 1 else 0.0,
            "e2e_errors": _e2e_errors(st) - first_errors, "e2e_errors_first_frames": first_errors,
            "statuses_at_end": st["statuses"]}


def _e2e_errors(counters: Any) -> int:
    """E2E checks that failed (CRC or length, wrong sequence, repeated frame) in a daemon's counters."""
    return counters.get("e2e_error", 0) + counters.get("e2e_wrongsequence", 0) + counters.get("e2e_repeated", 0)


def _without(matrix: Any, features: tuple[str, ...]) -> tuple[Any, Any]:
    """``(matrix, stage_hook)`` of a daemon without ``features`` (names in :data:`FEATURES`)."""
    from virtsensor.canbus.codec import CanMatrix

    if "grip" in features:
        matrix = CanMatrix(matrix.db, {k: v for k, v in matrix.messages.items() if k != "VS_Grip"}, matrix.source)
    off = {"envelope": _never_outside, "plausibility": _never_implausible}
    off = {k: fn for k, fn in off.items() if k in features}
    return matrix, (lambda stage, fn: off.get(stage, fn)) if off else None


def _never_outside(values: Any, rules: Any) -> bool:
    return False


def _never_implausible(values: Any, stale: Any) -> bool:
    return False


def measure_feature_cost(model: Any, matrix: Any, inputs: Inputs, n_ticks: int, rounds: int) -> dict[str, Any]:
    """The soak's max tick rate (ticks/s, with the input frames; and of the ticks alone) of the daemon as shipped,
    without each of :data:`FEATURES` and without all of them (the tick's work before they were added): medians
    over ``rounds`` interleaved rounds of ``n_ticks`` ticks each, and what each feature costs per tick (us, from
    the medians: 1/rate without it minus 1/rate with everything)."""
    configs = {"all": (), **{f"without_{f}": (f,) for f in FEATURES}, "without_all": FEATURES}
    rates: dict[str, list[tuple[float, float]]] = {k: [] for k in configs}
    for _ in range(rounds):
        for name, feats in configs.items():
            m, hook = _without(matrix, feats)
            s = run_soak(model, m, inputs, n_ticks, stage_hook=hook)
            rates[name].append((s["ticks_per_s"], s["ticks_per_s_tick_only"]))
    out: dict[str, Any] = {"ticks": n_ticks, "rounds": rounds, "max_tick_rate_hz": {}, "tick_only_hz": {}}
    for name, v in rates.items():
        out["max_tick_rate_hz"][name] = float(np.median([a for a, _ in v]))
        out["tick_only_hz"][name] = float(np.median([b for _, b in v]))
    full = out["max_tick_rate_hz"]["all"]
    out["cost_us_per_tick"] = {k.removeprefix("without_"): round(1e6 / full - 1e6 / r, 2)
                               for k, r in out["max_tick_rate_hz"].items() if k != "all"}
    return out


# ---------------------------------------------------------------------------------------------------------------
# the whole bench
# ---------------------------------------------------------------------------------------------------------------
class _EventCounter(logging.Handler):
    """Counts the daemon's log events by message (``envelope_exit``, ``status_change``...) instead of printing."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.counts: dict[str, int] = {}

    def emit(self, record: logging.LogRecord) -> None:
        key = str(record.msg)
        self.counts[key] = self.counts.get(key, 0) + 1


def run_bench(model_path: str | os.PathLike | None = None, *, quick: bool = False, soak_ticks: int | None = None,
              cross_process: bool = True, progress: Callable[[str], None] | None = None,
              cpu_latency_us: int | None = 0) -> dict[str, Any]:
    """Run every measurement; returns the JSON-able result (plus ``_samples`` for the histogram).

    ``cpu_latency_us``: the PM QoS CPU-latency request of the free-running daemon (as in ``virtsensor run
    --cpu-latency-us``; None: measure it with the machine's idle policy only); see :func:`_free_running_figures`.

    The daemons' log events (WARNING and above; INFO when the logger is set to it) are counted into
    ``daemon_log_events`` instead of reaching stderr."""
    logger = logging.getLogger("virtsensor.daemon")
    counter = _EventCounter()
    old_propagate = logger.propagate
    logger.addHandler(counter)
    logger.propagate = False
    try:
        result = _run_bench(model_path, quick=quick, soak_ticks=soak_ticks, cross_process=cross_process,
                            progress=progress, cpu_latency_us=cpu_latency_us)
    finally:
        logger.removeHandler(counter)
        logger.propagate = old_propagate
    result["daemon_log_events"] = dict(sorted(counter.counts.items()))
    return result


def daemon_cpu_percent(fr: dict[str, Any]) -> float:
    """The daemon's CPU (% of one core) in a :func:`measure_free_running` result: its own threads' CPU time where
    the platform gives per-thread clocks, else the whole process's."""
    d = fr["cpu_percent_daemon_threads"]
    return float(d if d is not None else fr["cpu_percent_process"])


def _free_running_figures(model: Any, matrix: Any, inputs: Inputs, seconds: float, cpu_latency_us: int | None,
                          say: Callable[[str], None]) -> dict[str, Any]:
    """The free-running daemon with its PM QoS CPU-latency request (``cpu_latency_us``; None: not asked) and
    with the machine's own idle policy. The headline figures (``jitter_us``, ``cpu_percent_at_20hz``,
    ``free_running``...) are the run with the request when the daemon could hold it, else the other one; the
    run without is also under ``*_default_idle``."""
    out: dict[str, Any] = {"cpu_latency_request": None}
    runs = []
    if cpu_latency_us is not None:
        say(f"free-running 20 Hz, CPU-latency request {cpu_latency_us} us: {seconds} s")
        fr = measure_free_running(model, matrix, inputs, seconds, cpu_latency_us)
        out["cpu_latency_request"] = fr["cpu_latency"]
        if fr["cpu_latency"]["held"]:
            runs.append(fr)
    say(f"free-running 20 Hz, the machine's idle policy: {seconds} s")
    idle = measure_free_running(model, matrix, inputs, seconds)
    runs.append(idle)
    head = runs[0]
    out.update(jitter_us=head["jitter_us"], cpu_percent_at_20hz=daemon_cpu_percent(head),
               cpu_percent_process_at_20hz=head["cpu_percent_process"], rss_mb_at_20hz=head["rss_mb"],
               free_running=head, jitter_us_default_idle=idle["jitter_us"],
               cpu_percent_at_20hz_default_idle=daemon_cpu_percent(idle), free_running_default_idle=idle)
    return out


def _run_bench(model_path: str | os.PathLike | None, *, quick: bool, soak_ticks: int | None, cross_process: bool,
               progress: Callable[[str], None] | None, cpu_latency_us: int | None = 0) -> dict[str, Any]:
    from virtsensor.canbus.codec import CanMatrix
    from virtsensor.model.onnx import OnnxModel

    say = progress or (lambda s: None)
    counts: dict[str, Any] = dict(QUICK if quick else FULL)
    if soak_ticks is not None:
        if soak_ticks < 1:
            raise UserError("--soak-ticks must be at least 1")
        counts["soak_ticks"] = int(soak_ticks)
    model_path = assets.model_path() if model_path is None else Path(model_path)
    if not model_path.exists():
        raise UserError(f"model {model_path} not found (give one with --model)")
    model = OnnxModel.load(model_path)
    matrix = CanMatrix.load()
    sha = hashlib.sha256(model_path.read_bytes()).hexdigest()
    say(f"model {model_path} ({sha[:12]}); input frames of the manoeuvre {MANOEUVRE} (shipped)")
    inputs = Inputs()
    result: dict[str, Any] = {
        "schema": "virtsensor-bench/1", "quick": quick, "counts": counts,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": machine_info(), "model": {"file": str(model_path), "sha256": sha},
        "inputs": {"manoeuvre": list(MANOEUVRE), "window_s": [WINDOW_START_S, WINDOW_START_S + LOOP_S],
                   "frames_per_tick": round(inputs.frames_per_tick, 2)},
    }
    rss_start = rss_mb()

    say(f"stages: {counts['stage_ticks']} ticks, instrumented")
    stages, X = measure_stages(model, matrix, inputs, counts["stage_ticks"])
    result["stages_us"] = stages
    result["stages_method"] = ("VirtualSensor in sync mode driven with process() in the bench thread; the tick's "
                               "calls timed in place by proxies (decode = the generated receiver per input frame: "
                               "DLC, CRC, E2E, decode, store; plausibility = the redundancy checks; validity = the "
                               "input status and health bitmap; envelope = the model card's envelope test; grip = "
                               "the VS_Grip estimate and its encoding; encode/send of SAT_FRONT)")
    say(f"stages after {IDLE_S * 1e3:.0f} ms idle: {counts['idle_ticks']} ticks")
    result["stages_after_idle_us"], _ = measure_stages(model, matrix, inputs, counts["idle_ticks"], idle_s=IDLE_S)

    say(f"end to end in process: {counts['e2e_ticks']} ticks")
    e2e_in = measure_e2e_in_process(model, matrix, inputs, counts["e2e_ticks"])
    xproc: dict | None = None
    reason: str | None = "disabled (--no-cross-process)"
    if cross_process:
        say(f"end to end across processes (udp_multicast, private netns): {counts['xproc_ticks']} ticks")
        from virtsensor.daemon.xproc import measure_e2e_cross_process

        xproc, reason = measure_e2e_cross_process(model_path, counts["xproc_ticks"])
    result["e2e_latency_us"] = {k: e2e_in.get(k) for k in ("p50", "p99", "p999", "max", "mean", "n")}
    result["e2e_latency_us"].update(
        in_process=e2e_in, cross_process=xproc,
        cross_process_skipped=reason,
        method="send of the tick's last input frame -> SAT_FRONT received by a listener bus")

    result.update(_free_running_figures(model, matrix, inputs, counts["jitter_s"], cpu_latency_us, say))

    say(f"inference back-ends on {min(len(X), counts['stage_ticks'])} feature vectors")
    result["inference_us"] = measure_backends(model, X, counts["stage_ticks"])

    say(f"soak: {counts['soak_ticks']} ticks as fast as possible")
    soak = run_soak(model, matrix, inputs, counts["soak_ticks"], progress=say)
    samples = soak.pop("compute_samples")
    result["tick_compute_us"] = soak["compute_us"]
    result["max_tick_rate_hz"] = soak["ticks_per_s"]
    result["max_tick_rate_hz_tick_only"] = soak["ticks_per_s_tick_only"]
    result["max_tick_rate_hz_per_cpu_s"] = soak["ticks_per_cpu_s"]
    result["missed_ticks"] = soak["missed_ticks"]
    result["rss_mb_start"] = soak["rss_mb_start"]
    result["rss_mb_end"] = soak["rss_mb_end"]
    result["rss_mb_process_start"] = round(rss_start, 3)
    result["soak"] = soak
    say(f"feature cost: {counts['cost_rounds']} x {len(FEATURES) + 2} soaks of {counts['cost_ticks']} ticks")
    result["feature_cost"] = measure_feature_cost(model, matrix, inputs, counts["cost_ticks"], counts["cost_rounds"])
    result["targets"] = targets(result)
    result["_samples"] = {"tick_compute_us": samples}
    return result


def targets(r: dict[str, Any]) -> dict[str, Any]:
    """The daemon's performance targets: per target its value, limit and whether it is met (None: not measured)."""
    def get(d: Any, *keys: str) -> Any:
        for k in keys:
            d = d.get(k) if isinstance(d, dict) else None
        return d

    def entry(value: Any, limit: str, ok: bool | None) -> dict[str, Any]:
        return {"value": value, "limit": limit, "met": ok}

    tc = get(r, "tick_compute_us", "p99")
    e2e = get(r, "e2e_latency_us", "p99")
    soak = r.get("soak", {})
    cpu = r.get("cpu_percent_at_20hz")
    rate = r.get("max_tick_rate_hz")
    drift = soak.get("rss_mb_drift")
    return {
        "tick_compute_p99_us": entry(tc, "<= 200", None if tc is None else tc <= 200),
        "e2e_in_process_p99_us": entry(e2e, "<= 1000", None if e2e is None else e2e <= 1000),
        "soak_missed_ticks": entry(r.get("missed_ticks"), "== 0", r.get("missed_ticks") == 0),
        "soak_rss_drift_mb": entry(drift, "within +-5", None if drift is None else abs(drift) <= 5),
        "max_tick_rate_hz": entry(rate, ">= 5000", None if rate is None else rate >= 5000),
        "max_tick_rate_hz_tick_only": entry(r.get("max_tick_rate_hz_tick_only"), ">= 5000 (inputs decoded elsewhere)",
                                            None if r.get("max_tick_rate_hz_tick_only") is None
                                            else r["max_tick_rate_hz_tick_only"] >= 5000),
        "cpu_percent_at_20hz": entry(cpu, "<= 0.6", None if cpu is None else cpu <= 0.6),
    }


# ---------------------------------------------------------------------------------------------------------------
# reports
# ---------------------------------------------------------------------------------------------------------------
def _row(name: str, p: dict | None) -> str:
    if not p:
        return f"| {name} | - | - | - | - |"
    return f"| {name} | {p['p50']:.1f} | {p['p99']:.1f} | {p['p999']:.1f} | {p['max']:.1f} |"


def _latency_note(r: dict[str, Any]) -> str:
    req = r.get("cpu_latency_request")
    idle = f"with the machine's idle policy: CPU {r.get('cpu_percent_at_20hz_default_idle')} %, jitter p50 " \
           f"{(r.get('jitter_us_default_idle') or {}).get('p50')} us"
    if req is None:
        return f"no PM QoS CPU-latency request ({idle})"
    if not req["held"]:
        return f"PM QoS CPU-latency request {req['us']} us refused ({req['error']}): figures {idle}"
    return f"daemon holding a PM QoS CPU-latency request of {req['us']} us ({idle})"


def _cost_line(r: dict[str, Any]) -> str:
    fc = r.get("feature_cost")
    if not fc:
        return "* feature cost: not measured"
    rate, cost = fc["max_tick_rate_hz"], fc["cost_us_per_tick"]
    return (f"* max tick rate by feature (medians of {fc['rounds']} interleaved rounds of {fc['ticks']} ticks): "
            f"{rate['all']:.0f} ticks/s as shipped, " + ", ".join(
                f"{rate['without_' + k]:.0f} without {k} ({cost[k]:+.1f} us per tick)" for k in FEATURES)
            + f", {rate['without_all']:.0f} without all three ({cost['all']:+.1f} us)")


def write_markdown(r: dict[str, Any], path: str | os.PathLike) -> None:
    m = r["machine"]
    lines = [f"# virtsensor bench{' (quick)' if r.get('quick') else ''}", "",
             f"Model `{r['model']['file']}` (sha256 `{r['model']['sha256'][:16]}`), {r['created_utc']}.  ",
             f"Machine: {m['cpu_model']}, {m['cores']} cores, {m['platform']}, Python {m['python']}.", "",
             "## Latency (us)", "", "| what | p50 | p99 | p99.9 | max |", "|---|---:|---:|---:|---:|",
             _row("tick compute (soak)", r.get("tick_compute_us"))]
    for k, v in (r.get("stages_us") or {}).items():
        lines.append(_row(f"stage: {k}", v))
    e2e = r["e2e_latency_us"]
    lines.append(_row("end to end, in process", e2e.get("in_process")))
    lines.append(_row("end to end, cross process", e2e.get("cross_process")))
    for k in ("onnxruntime", "sklearn", "numpy"):
        lines.append(_row(f"inference: {k}", r["inference_us"].get(k)))
    lines.append(_row("tick jitter (20 Hz)", r.get("jitter_us")))
    idle = r.get("stages_after_idle_us") or {}
    lines += ["", f"After {IDLE_S * 1e3:.0f} ms idle before each tick (as at 20 Hz), p50 per stage (us): "
              + ", ".join(f"{k} {v['p50']:.1f}" for k, v in idle.items() if v) + "."]
    lines += ["", f"Stages: {r.get('stages_method')}.  ", f"End to end: {e2e.get('method')}."]
    if e2e.get("cross_process") is None:
        lines.append(f"Cross process skipped: {e2e.get('cross_process_skipped')}.")
    if r["inference_us"].get("skipped"):
        lines.append(f"Back-ends skipped: {r['inference_us']['skipped']}.")
    s = r["soak"]
    lines += ["", "## Load and soak", "",
              f"* CPU at 20 Hz: {r['cpu_percent_at_20hz']} % of one core (daemon threads); whole process incl. "
              f"the input feeder {r['cpu_percent_process_at_20hz']} %; RSS {r['rss_mb_at_20hz']:.1f} MB; per thread "
              f"{r['free_running']['cpu_percent_per_thread']} (busy-wait before each deadline: "
              f"{r['free_running']['spin_budget_percent']} % by design); tick compute at 20 Hz p50 "
              f"{r['free_running'].get('tick_compute_p50_us')} us, "
              f"p99 {r['free_running'].get('tick_compute_p99_us')} us; {_latency_note(r)}",
              f"* max tick rate: {r['max_tick_rate_hz']:.0f} ticks/s (with {s['frames_per_tick']} input frames "
              f"decoded per tick; {r.get('max_tick_rate_hz_per_cpu_s')} per CPU second); ticks alone: "
              f"{r['max_tick_rate_hz_tick_only']:.0f} ticks/s",
              _cost_line(r),
              f"* soak: {s['ticks']} ticks in {s['wall_s']} s, missed {s['missed_ticks']} "
              f"(no SAT_FRONT {s['missed_no_sat_front']}, over budget {s['missed_over_budget']}), RSS "
              f"{s['rss_mb_start']:.1f} -> {s['rss_mb_end']:.1f} MB (drift {s['rss_mb_drift']:+.2f} MB)", "",
              "## Targets", "", "| target | value | limit | met |", "|---|---:|---|---|"]
    for k, t in r["targets"].items():
        lines.append(f"| {k} | {t['value']} | {t['limit']} | {'yes' if t['met'] else 'NO'} |")
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())


def write_histogram(r: dict[str, Any], path: str | os.PathLike) -> None:
    """PNG histogram of the soak's tick compute times (us, log count) with p50/p99/p99.9 marked; needs the
    ``plots`` extra (:class:`~virtsensor.extras.MissingExtra` otherwise)."""
    from virtsensor import plotting

    comp = np.asarray(r.get("_samples", {}).get("tick_compute_us", []), dtype=float)
    fig = plotting.figure(8, 4.5, what="--histogram")
    ax = fig.subplots()
    if comp.size:
        hi = max(float(np.percentile(comp, 99.9)) * 1.5, 1.0)
        ax.hist(np.clip(comp, 0, hi), bins=120, log=True, color="tab:blue", alpha=0.8)
        for q, c in (("p50", "k"), ("p99", "tab:orange"), ("p999", "tab:red")):
            v = r["tick_compute_us"][q]
            ax.axvline(v, color=c, ls="--", lw=1, label=f"{q} {v:.0f} us")
    ax.set_xlabel("tick compute (us, tick start -> SAT_FRONT encoded)")
    ax.set_ylabel("ticks")
    ax.set_title(f"virtsensor tick compute, {comp.size} ticks (clipped at 1.5 x p99.9; max {comp.max():.0f} us)"
                 if comp.size else "virtsensor tick compute (no ticks)")
    ax.legend()
    plotting.save(fig, path)


def to_json(r: dict[str, Any]) -> str:
    """The bench result as indented JSON (keys starting with ``_`` left out; non-finite floats as null)."""
    from virtsensor.fileio import dumps

    return dumps({k: v for k, v in r.items() if not k.startswith("_")}) + "\n"
