"""Fault-injection soak of the daemon: replayed bus time with random faults, every tick checked by an oracle.

Simulated runs (the bundled demo's random steer, a fishhook and a braking-in-turn on μ 0.3, ...) are turned into
their CAN frames and laid end to end for ``--minutes`` of bus time, the alive counters made continuous across the
joins (so a clean stream has no E2E error). Faults drawn from the fault matrix (``FAULTS``) are then injected
one after another at random times (seeded), and :class:`virtsensor.daemon.VirtualSensor` with the shipped model
is driven by hand, as fast as it goes: every frame through ``process`` (its stamp as its receive time), a
``tick`` at each 20 Hz instant.

The oracle knows, at every tick, which input messages are dead or implausible, from the injection alone:

* *dead*: no frame of the message whose content is genuine (not corrupted, not counter-faulted, not a
  duplicate, not SNA or out of range) has arrived with a true time within the message's timeout
  (``timeout_cycles`` cycles) before the tick; or the latest frame that arrived carries an SNA or out-of-range
  value of an input;
* *implausible*: the vehicle speed on the bus is falsified, and over the last ``debounce + 2`` ticks the held
  values put the speed outside 1.2 times the catalogue's tolerance of the front wheel speeds while the
  check's conditions held with a margin (|ax| <= 0.8 m/s^2, |motor torque| <= 25 Nm, steady wheels).

A VALID tick (either wheel) on a dead or implausible input is a violation. Also counted: tick errors (the
daemon's ``tick_errors``) and crashes (an exception out of ``process`` or ``tick``). The daemon may be
stricter than the oracle (INVALID after a fault's end while it recovers): that is not checked.

The faults also hit the checks' references (signals the daemon reads for its plausibility checks alone, such as
the rear wheel speeds): a dead reference is not a dead input (the estimate may stay VALID, its checks are then not
judged), and the figures give the VALID share of the ticks on which only a reference's message is faulted.

    python tools/fault_soak.py --minutes 30 --seed 1 --json soak.json
    python tools/fault_soak.py --tables data/paper      # the checks over simulated runs: how often each trips
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from virtsensor import signals as cat  # noqa: E402
from virtsensor.canbus.codec import CanMatrix  # noqa: E402
from virtsensor.canbus.e2e import CRC8_TABLE, counter_sequence, crc8_register  # noqa: E402

TICK_S = 1.0 / cat.TABLE_RATE_HZ
#: The runs laid end to end (manoeuvre, km/h, mu, seed); the first is the bundled demo recording's run.
POOL = (("random-steer", 70.0, 0.7, 4), ("fishhook", 80.0, 0.3, 1), ("braking-in-turn", 80.0, 0.3, 2),
        ("double-lane-change", 60.0, 0.5, 3), ("steady-state-circular", 60.0, 1.0, 5),
        ("brake-accel", 100.0, 0.2, 6), ("sine-with-dwell", 80.0, 1.0, 7))
#: The bundled demo recording (the first run of POOL, as a CAN log).
DEMO_LOG = ROOT / "sim" / "data" / "recordings" / "random-steer_70kmh_mu0.7_seed4.blf"
#: fault kind -> (what is done to the frames, what the daemon must show); the fault matrix of docs/reliability.md
FAULTS = {
    "silence": "a message's frames stop for 0.05-3 s",
    "crc": "every frame of a message in 0.05-1.5 s has one bit flipped",
    "dlc": "every frame of a message in 0.05-1.5 s is one byte short",
    "counter_jump": "one frame's alive counter jumps by 5-13 (WRONGSEQUENCE)",
    "counter_repeat": "one frame is sent twice (REPEATED)",
    "future_stamp": "one frame stamped 0.5-30 s ahead, then the message is silent for 0-2 s",
    "step_back": "every frame's stamp steps back by 0.02-10 s for 0.5-3 s, and one message is silent then",
    "sna": "an input carries its SNA code in every frame for 0.05-2 s",
    "out_of_range": "an input carries a raw value beyond its catalogue range for 0.05-2 s",
    "implausible_vx": "the ESC speed reads 20 m/s above the truth (at most 89 m/s) for 1-6 s",
    "burst": "the interface holds every frame for 0.2-2 s, then releases them at once (stamped when sent)",
}


@dataclass
class Stream:
    """The frames, in arrival order once :meth:`order` ran. ``true_t``: when sent; ``arrival``: when the
    daemon gets it; ``stamp``: its timestamp; ``alive``: genuine, intact content; ``flagged``: an SNA or
    out-of-range input (not a check reference's, which leaves the message's inputs alive); ``vx_fault``:
    falsified vehicle speed."""

    true_t: np.ndarray
    arrival: np.ndarray
    stamp: np.ndarray
    fid: np.ndarray
    data: np.ndarray
    dlc: np.ndarray
    alive: np.ndarray = field(init=False)
    flagged: np.ndarray = field(init=False)
    vx_fault: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        n = self.true_t.size
        self.alive = np.ones(n, bool)
        self.flagged = np.zeros(n, bool)
        self.vx_fault = np.zeros(n, bool)

    def append(self, rows: np.ndarray, arrival: np.ndarray, stamp: np.ndarray, alive: bool) -> None:
        """Add copies of frames ``rows`` (duplicates) with their own arrival and stamp."""
        for name in ("true_t", "fid", "data", "dlc", "flagged", "vx_fault"):
            setattr(self, name, np.concatenate([getattr(self, name), getattr(self, name)[rows]]))
        self.arrival = np.concatenate([self.arrival, arrival])
        self.stamp = np.concatenate([self.stamp, stamp])
        self.alive = np.concatenate([self.alive, np.full(rows.size, alive)])

    def order(self) -> None:
        o = np.argsort(self.arrival, kind="stable")
        for name in ("true_t", "arrival", "stamp", "fid", "data", "dlc", "alive", "flagged", "vx_fault"):
            setattr(self, name, getattr(self, name)[o])


def _protect(matrix: CanMatrix, data: np.ndarray, fid: np.ndarray, counters: dict[int, int] | None = None) -> None:
    """Re-write the alive counters (continuous from ``counters``, per message; None: keep them) and CRCs."""
    table = np.frombuffer(CRC8_TABLE, np.uint8)
    for mc in matrix.messages.values():
        rows = np.flatnonzero(fid == mc.frame_id)
        if rows.size == 0:
            continue
        if counters is not None:
            start = counters.get(mc.frame_id, 0)
            seq = counter_sequence(start, rows.size)
            data[rows, 1] = (data[rows, 1] & 0xF0) | seq.astype(np.uint8)
            counters[mc.frame_id] = int((seq[-1] + 1) % 15)
        state = np.full(rows.size, mc.seed, np.uint8)
        crc = crc8_register(state, [data[rows, b] for b in range(1, mc.length)], table)
        data[rows, 0] = crc


def _log_frames(path: Path, matrix: CanMatrix) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A CAN log's frames of the matrix's messages as arrays (times from 0)."""
    from virtsensor.recordings.canlog import iter_log

    ts, ids, rows = [], [], []
    for m in iter_log(path):
        if not m.is_extended_id and m.arbitration_id in matrix.by_id and len(m.data) == 8:
            ts.append(float(m.timestamp))
            ids.append(m.arbitration_id)
            rows.append(np.frombuffer(bytes(m.data), np.uint8))
    t = np.asarray(ts)
    return t - t[0], np.asarray(ids, np.int64), np.stack(rows)


def build_stream(matrix: CanMatrix, minutes: float, pool: tuple = POOL, log=print) -> tuple[Stream, float]:
    """The runs' frames end to end for ``minutes`` of bus time; returns the stream and its end (s). A pool
    entry is ``(manoeuvre, km/h, mu, seed)`` (simulated now) or the path of a simulated CAN log."""
    from sim.api import simulate_streams
    from virtsensor.recordings.canlog import frame_arrays

    runs = []
    for entry in pool:
        t0 = time.perf_counter()
        if isinstance(entry, (str, Path)):
            runs.append(_log_frames(Path(entry), matrix))
            log(f"read {Path(entry).name}: {runs[-1][0][-1]:.1f} s")
        else:
            manoeuvre, kmh, mu, seed = entry
            t, sig = simulate_streams(manoeuvre, speed_kmh=kmh, mu=mu, seed=seed)
            runs.append(frame_arrays(t, sig, matrix=matrix)[:3])
            took = time.perf_counter() - t0
            log(f"simulated {manoeuvre} {kmh:g} km/h mu {mu:g}: {t[-1] - t[0]:.1f} s ({took:.1f} s)")
        if sum(float(r[0][-1]) for r in runs) > minutes * 60.0:
            break
    end, k = minutes * 60.0, 0
    parts, offset = [], 0.0
    while offset < end:
        ts, ids, data = runs[k % len(runs)]
        keep = offset + ts < end
        parts.append((offset + ts[keep], ids[keep], data[keep]))
        offset = math.ceil((offset + float(ts[-1]) + TICK_S) / TICK_S) * TICK_S
        k += 1
    ts = np.concatenate([p[0] for p in parts])
    fid = np.concatenate([p[1] for p in parts])
    data = np.concatenate([p[2] for p in parts]).copy()
    _protect(matrix, data, fid, counters={})
    dlc = np.array([matrix.by_id[int(i)].length for i in fid])
    return Stream(ts, ts.copy(), ts.copy(), fid, data, dlc), end


def _set_raw(data: np.ndarray, row: int, sig: Any, raw: int) -> None:
    v = int.from_bytes(data[row].tobytes(), "little")
    v = (v & ~(sig.mask << sig.start)) | ((raw & sig.mask) << sig.start)
    data[row] = np.frombuffer(v.to_bytes(8, "little"), np.uint8)


def _get_raw(data: np.ndarray, row: int, sig: Any) -> int:
    raw = (int.from_bytes(data[row].tobytes(), "little") >> sig.start) & sig.mask
    return raw - (1 << sig.length) if sig.signed and raw >> (sig.length - 1) else raw


class Injector:
    """Draws and applies the faults of :data:`FAULTS` one after another (seeded) to the messages of the model's
    ``inputs`` and of the checks' references ``refs``; ``log`` lists them."""

    def __init__(self, s: Stream, matrix: CanMatrix, inputs: tuple[str, ...], rng: np.random.Generator,
                 refs: tuple[str, ...] = ()) -> None:
        self.s, self.matrix, self.rng = s, matrix, rng
        self.inputs = inputs  # model input signals
        self.refs = refs  # the check references (read by the plausibility checks alone)
        self.messages = sorted({matrix.messages[matrix.message_of(x)].frame_id for x in inputs + refs})
        self.log: list[dict[str, Any]] = []

    def rows(self, fid: int | None, a: float, b: float) -> np.ndarray:
        s = self.s
        sel = (s.true_t >= a) & (s.true_t < b)
        if fid is not None:
            sel &= s.fid == fid
        return np.flatnonzero(sel)

    def apply(self, kind: str, a: float) -> float:
        """Inject one fault of ``kind`` from time ``a``; returns when it (and its aftermath) ends."""
        rng, s, mx = self.rng, self.s, self.matrix
        fid = int(rng.choice(self.messages))
        mc = mx.by_id[fid]
        end = a
        if kind in ("silence", "crc", "dlc"):
            d = float(rng.uniform(0.05, 3.0 if kind == "silence" else 1.5))
            r, end = self.rows(fid, a, a + d), a + d
            s.alive[r] = False
            if kind == "silence":
                s.arrival[r] = np.inf
            elif kind == "crc":
                for i in r:
                    s.data[i, int(rng.integers(0, mc.length))] ^= np.uint8(1 << int(rng.integers(0, 8)))
            else:
                s.dlc[r] = mc.length - 1
        elif kind in ("counter_jump", "counter_repeat"):
            r = self.rows(fid, a, a + 1.0)[:1]
            s.alive[r] = False
            if kind == "counter_jump":
                s.data[r, 1] = (s.data[r, 1] & 0xF0) | ((s.data[r, 1] & 0x0F) + int(rng.integers(4, 13))) % 15
                self._recrc(r)
            else:
                s.append(r, s.arrival[r] + 1e-4, s.stamp[r] + 1e-4, alive=False)
            end = a + 0.1
        elif kind == "future_stamp":
            r = self.rows(fid, a, a + 1.0)[:1]
            s.stamp[r] += float(rng.uniform(0.5, 30.0))
            d = float(rng.uniform(0.0, 2.0))
            t0 = float(s.true_t[r[0]]) + 1e-6
            quiet = self.rows(fid, t0, t0 + d)
            s.alive[quiet] = False
            s.arrival[quiet] = np.inf
            end = t0 + d
        elif kind == "step_back":
            d, back = float(rng.uniform(0.5, 3.0)), float(np.exp(rng.uniform(np.log(0.02), np.log(10.0))))
            r = np.flatnonzero((s.true_t >= a) & (s.true_t < a + d) & np.isin(s.fid, self.messages))
            s.stamp[r] -= back
            quiet = self.rows(fid, a, a + d)
            s.alive[quiet] = False
            s.arrival[quiet] = np.inf
            end = a + d
        elif kind in ("sna", "out_of_range"):
            end = self._bad_value(kind, a)
        elif kind == "implausible_vx":
            end = self._implausible_vx(a)
        elif kind == "burst":
            d = float(rng.uniform(0.2, 2.0))
            r = np.flatnonzero((s.true_t >= a) & (s.true_t < a + d) & np.isfinite(s.arrival))
            s.arrival[r] = a + d + 1e-6 * np.arange(1, r.size + 1)
            end = a + d
        self.log.append({"kind": kind, "t": round(a, 3), "end": round(end, 3), "message": mc.name})
        return end

    def _bad_value(self, kind: str, a: float) -> float:
        rng, s, mx = self.rng, self.s, self.matrix
        name = str(rng.choice(self.inputs + self.refs))
        mc = mx.messages[mx.message_of(name)]
        sig = next(x for x in mc.signals if x.catalogue == name)
        d = float(rng.uniform(0.05, 2.0))
        r = self.rows(mc.frame_id, a, a + d)
        raw = sig.sna if kind == "sna" else sig.raw_hi + 1
        for i in r:
            _set_raw(s.data, int(i), sig, int(raw))
        self._recrc(r)
        if name in self.inputs:  # (a check reference's bad value leaves the message's inputs alive)
            s.alive[r] = False
            s.flagged[r] = True
        return a + d

    def _recrc(self, r: np.ndarray) -> None:
        """Re-compute the CRCs of frames ``r`` (their counters kept)."""
        if r.size == 0:
            return
        block = self.s.data[r].copy()
        _protect(self.matrix, block, self.s.fid[r])
        self.s.data[r] = block

    def _implausible_vx(self, a: float) -> float:
        s, mx = self.s, self.matrix
        mc = mx.messages[mx.message_of("vx_mps")]
        sig = next(x for x in mc.signals if x.catalogue == "vx_mps")
        d = float(self.rng.uniform(1.0, 6.0))
        r = self.rows(mc.frame_id, a, a + d)
        step = round(20.0 / sig.scale)
        cap = round((89.0 - sig.offset) / sig.scale)
        for i in r:
            _set_raw(s.data, int(i), sig, min(_get_raw(s.data, int(i), sig) + step, cap))
        self._recrc(r)
        s.vx_fault[r] = True
        return a + d


def inject_faults(s: Stream, matrix: CanMatrix, inputs: tuple[str, ...], end: float, seed: int,
                  warmup_s: float = 5.0, refs: tuple[str, ...] = ()) -> list[dict[str, Any]]:
    """Faults of random kinds, one after another from ``warmup_s`` with 1-5 s between them, on the messages of
    ``inputs`` and of the check references ``refs``; the log of them."""
    rng = np.random.default_rng(seed)
    inj = Injector(s, matrix, inputs, rng, refs)
    kinds = sorted(FAULTS)
    t = warmup_s
    while True:
        kind = kinds[int(rng.integers(0, len(kinds)))]
        if t + 8.0 > end:
            break
        t = inj.apply(kind, t) + float(rng.uniform(1.0, 5.0))
    s.order()
    return inj.log


def _held(s: Stream, fid: int, ticks: np.ndarray) -> np.ndarray:
    """Per tick, the index (into the stream) of the latest frame of ``fid`` that arrived by then (-1: none)."""
    rows = np.flatnonzero((s.fid == fid) & np.isfinite(s.arrival))
    k = np.searchsorted(s.arrival[rows], ticks, side="right") - 1
    return np.where(k >= 0, rows[np.maximum(k, 0)], -1)


def _values(s: Stream, matrix: CanMatrix, name: str, frames: np.ndarray) -> np.ndarray:
    """The SI value of input ``name`` in stream frames ``frames`` (nan where -1)."""
    mc = matrix.messages[matrix.message_of(name)]
    sig = next(x for x in mc.signals if x.catalogue == name)
    v = s.data[np.maximum(frames, 0)].copy().view("<u8")[:, 0]
    raw = ((v >> np.uint64(sig.start)) & np.uint64(sig.mask)).astype(np.int64)
    if sig.signed:
        raw = np.where(raw >> (sig.length - 1), raw - (1 << sig.length), raw)
    return np.where(frames >= 0, (raw * sig.scale + sig.offset) / sig.si_factor, np.nan)


def _dead(s: Stream, matrix: CanMatrix, fids: list[int], ticks: np.ndarray, timeout_cycles: float,
          flagged: np.ndarray) -> np.ndarray:
    """Per tick: one of messages ``fids`` has had no genuine frame within its timeout, or its latest frame is
    ``flagged``."""
    dead = np.zeros(ticks.size, bool)
    for fid in fids:
        mc = matrix.by_id[fid]
        rows = np.flatnonzero((s.fid == fid) & np.isfinite(s.arrival))
        alive_t = np.maximum.accumulate(np.where(s.alive[rows], s.true_t[rows], -np.inf))
        k = np.searchsorted(s.arrival[rows], ticks, side="right") - 1
        latest = np.where(k >= 0, alive_t[np.maximum(k, 0)], -np.inf)
        dead |= latest < ticks - timeout_cycles * mc.cycle_s - 1e-4
        dead |= (k >= 0) & flagged[rows[np.maximum(k, 0)]]
    return dead


def oracle(s: Stream, matrix: CanMatrix, inputs: tuple[str, ...], ticks: np.ndarray,
           timeout_cycles: float) -> tuple[np.ndarray, np.ndarray]:
    """Per tick: some input message is dead; the vehicle speed is implausible (see the module docstring)."""
    fids = sorted({matrix.messages[matrix.message_of(x)].frame_id for x in inputs})
    dead = _dead(s, matrix, fids, ticks, timeout_cycles, s.flagged)
    rule = next(r for r in cat.REDUNDANCIES if r.name == "vx_vs_front_wheel_speed")
    vx_frames = _held(s, matrix.messages[matrix.message_of("vx_mps")].frame_id, ticks)
    faulty = (vx_frames >= 0) & s.vx_fault[np.maximum(vx_frames, 0)]
    implausible = np.zeros(ticks.size, bool)
    if not faulty.any():
        return dead, implausible
    held = {n: _values(s, matrix, n, _held(s, matrix.messages[matrix.message_of(n)].frame_id, ticks))
            for n in ("vx_mps", "ax_mps2", "motor_torque_nm", "wheel_speed_fl_radps", "wheel_speed_fr_radps")}
    wheels = (held["wheel_speed_fl_radps"] + held["wheel_speed_fr_radps"]) / 2.0
    step = np.abs(np.diff(np.stack([held["wheel_speed_fl_radps"], held["wheel_speed_fr_radps"]]), prepend=np.nan))
    steady = np.all(step <= 0.8 * (2.0 / cat.ROLLING_RADIUS_M) / cat.TABLE_RATE_HZ, axis=0)
    gate = (np.abs(held["ax_mps2"]) <= 0.8) & (np.abs(held["motor_torque_nm"]) <= 25.0) & steady
    vx = held["vx_mps"]
    off = np.abs(vx - rule.scale * wheels) > 1.2 * (rule.tolerance_abs + rule.tolerance_rel * np.abs(vx))
    bad = faulty & gate & off
    run = rule.debounce_ticks + 2
    csum = np.concatenate([[0], np.cumsum(bad)])
    implausible[run - 1:] = (csum[run:] - csum[:-run]) == run
    return dead, implausible


class _NullBus:
    """Takes the daemon's frames and forgets them."""

    def send(self, msg: Any, timeout: float | None = None) -> None:
        pass

    def shutdown(self) -> None:
        pass


class _Events(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.counts: Counter[str] = Counter()

    def emit(self, record: logging.LogRecord) -> None:
        self.counts[record.getMessage()] += 1


def drive(s: Stream, sensor: Any, ticks: np.ndarray, marks: dict[int, list[int]]) -> dict[str, Any]:
    """Feed every delivered frame (in arrival order, its stamp as receive time) and tick at ``ticks``.

    Returns the per-tick statuses (ticks, wheels), the crashes (exceptions out of the daemon) and the
    counters snapshotted at the ticks in ``marks`` (tick -> fault indices)."""
    import can

    n = int(np.isfinite(s.arrival).sum())  # (never-delivered frames sort last)
    arrival, stamp, fid, dlc = s.arrival.tolist(), s.stamp.tolist(), s.fid.tolist(), s.dlc.tolist()
    data = s.data
    statuses = np.zeros((ticks.size, len(sensor.last_statuses)), np.int8)
    snaps: dict[int, dict[str, int]] = {}
    crashes, first_crash = 0, None
    i = 0
    process, tick, Message = sensor.process, sensor.tick, can.Message
    for k, t in enumerate(ticks.tolist()):
        while i < n and arrival[i] <= t:
            m = Message(timestamp=stamp[i], arbitration_id=fid[i], is_extended_id=False, dlc=dlc[i],
                        data=data[i, :dlc[i]].tobytes(), check=False)
            try:
                process(m, stamp[i])
            except Exception as exc:  # noqa: BLE001 - counted: a crash of the daemon's receive path
                crashes += 1
                first_crash = first_crash or repr(exc)
            i += 1
        try:
            statuses[k] = tick(t)
        except Exception as exc:  # noqa: BLE001 - counted: a crash of the tick
            crashes += 1
            first_crash = first_crash or repr(exc)
        if k in marks:
            snaps[k] = dict(sensor.counters)
    return {"statuses": statuses, "crashes": crashes, "first_crash": first_crash, "snapshots": snaps}


#: counters that move on every tick or frame (left out of the observed fault matrix)
_ALWAYS = ("frames", "input_frames", "other_frames", "ticks", "drained_frames", "sent", "e2e_ok", "status_changes")


def _observed_matrix(faults: list[dict[str, Any]], ticks: np.ndarray, statuses: np.ndarray,
                     snaps: dict[int, dict[str, int]], forbidden: np.ndarray) -> dict[str, Any]:
    """Per fault kind: how many were injected, the daemon's statuses while they lasted (+1 s), the counters
    that moved then (in how many of them), and the forbidden ticks among them."""
    from virtsensor.daemon import STATUS_NAMES

    out: dict[str, Any] = {}
    for f in faults:
        k0, k1 = f["_ticks"]
        e = out.setdefault(f["kind"], {"injected": 0, "statuses": Counter(), "counters": Counter(),
                                       "forbidden_ticks": 0})
        e["injected"] += 1
        for st in statuses[k0:k1].min(axis=1).tolist():
            e["statuses"][STATUS_NAMES[st]] += 1
        e["forbidden_ticks"] += int(forbidden[k0:k1].sum())
        a, b = snaps.get(max(k0 - 1, 0), {}), snaps.get(min(k1, len(ticks) - 1), {})
        for key, v in b.items():
            if key not in _ALWAYS and v > a.get(key, 0):
                e["counters"][key] += 1
    return {k: {**v, "statuses": dict(v["statuses"]), "counters": dict(v["counters"])} for k, v in sorted(out.items())}


def _reference_fault_ticks(faults: list[dict[str, Any]], matrix: CanMatrix, inputs: tuple[str, ...],
                           refs: tuple[str, ...], n: int) -> np.ndarray:
    """Per tick: a fault of a message that carries only check references lasts (+1 s), and no other fault does
    (the kinds that hit one message; a step back, a burst or a falsified speed hit others too)."""
    model = {matrix.message_of(x) for x in inputs}
    own = {matrix.message_of(x) for x in refs} - model
    solo, other = np.zeros(n, bool), np.zeros(n, bool)
    for f in faults:
        k0, k1 = f["_ticks"]
        if f["message"] in own and f["kind"] not in ("step_back", "burst", "implausible_vx"):
            solo[k0:k1] = True
        else:
            other[k0:k1] = True
    return solo & ~other


def soak(minutes: float, seed: int, model_path: Path = ROOT / "models" / "improved.onnx",
         pool: tuple = POOL, log=print) -> dict[str, Any]:
    """Build, inject, drive, check; the figures (see :func:`main`)."""
    from virtsensor.daemon import VALID, VirtualSensor
    from virtsensor.model.onnx import OnnxModel

    matrix = CanMatrix.load()
    model = OnnxModel.load(str(model_path))
    sensor = VirtualSensor(_NullBus(), model, matrix, freeze_gc=False)
    inputs, refs = tuple(sensor.layout.signals), tuple(sensor.layout.check_signals)
    s, end = build_stream(matrix, minutes, pool, log)
    faults = inject_faults(s, matrix, inputs, end, seed, refs=refs)
    ticks = np.arange(1, int(round(end / TICK_S)) + 1) * TICK_S + 1e-6
    for f in faults:
        f["_ticks"] = (int(np.searchsorted(ticks, f["t"])), int(np.searchsorted(ticks, f["end"] + 1.0)))
    marks: dict[int, list[int]] = {}
    for j, f in enumerate(faults):
        for k in f["_ticks"]:
            marks.setdefault(min(k, ticks.size - 1), []).append(j)
            marks.setdefault(max(k - 1, 0), []).append(j)
    dead, implausible = oracle(s, matrix, inputs, ticks, sensor.timeout_cycles)
    ref_only = _reference_fault_ticks(faults, matrix, inputs, refs, ticks.size)
    logger = logging.getLogger("virtsensor.daemon")
    events, old = _Events(), (logger.level, logger.propagate)
    logger.addHandler(events)
    logger.setLevel(logging.INFO)
    logger.propagate = False
    t0 = time.perf_counter()
    try:
        res = drive(s, sensor, ticks, marks)
    finally:
        logger.removeHandler(events)
        logger.setLevel(old[0])
        logger.propagate = old[1]
    wall = time.perf_counter() - t0
    st = res["statuses"]
    valid = (st == VALID).any(axis=1)
    forbidden = dead | implausible
    bad = np.flatnonzero(valid & forbidden)
    clean = ~forbidden
    return {
        "seed": seed, "bus_time_s": round(end, 3), "ticks": int(ticks.size),
        "frames": int(np.isfinite(s.arrival).sum()),
        "faults": len(faults), "faults_by_kind": dict(Counter(f["kind"] for f in faults)),
        "dead_ticks": int(dead.sum()), "implausible_ticks": int(implausible.sum()),
        "valid_on_dead_or_implausible": int(bad.size),
        "first_violations": [{"t": round(float(ticks[k]), 3), "statuses": st[k].tolist(),
                              "dead": bool(dead[k]), "implausible": bool(implausible[k])} for k in bad[:5]],
        "tick_errors": int(sensor.counters["tick_errors"]), "crashes": res["crashes"],
        "first_crash": res["first_crash"],
        "valid_share_of_other_ticks": round(float(valid[clean].mean()), 4) if clean.any() else None,
        "check_references": list(refs),
        "reference_fault_ticks": int((ref_only & clean).sum()),
        "valid_share_of_reference_fault_ticks": (round(float(valid[ref_only & clean].mean()), 4)
                                                 if (ref_only & clean).any() else None),
        "counters": {k: v for k, v in sensor.counters.items() if v}, "log_events": dict(events.counts),
        "drive_wall_s": round(wall, 2),
        "fault_matrix": _observed_matrix(faults, ticks, st, res["snapshots"], forbidden),
    }


def _table_with_references(path: Path, refs: tuple[str, ...]) -> tuple[dict[str, np.ndarray], tuple[str, ...]]:
    """A recording's 20 Hz table with the inputs and those of the check references ``refs`` it has (a CAN log
    decoded with them; a table's own columns); the references it lacks."""
    from virtsensor.errors import UserError
    from virtsensor.recordings.canlog import read_log
    from virtsensor.recordings.files import LOG_SUFFIXES, read_table

    if path.suffix.lower() in LOG_SUFFIXES:
        try:
            return dict(read_log(path, signals=cat.INPUTS + refs).table), ()
        except UserError as exc:  # (a log without them: read as the daemon reads it, the checks unjudged)
            if "never received" not in str(exc):
                raise
    table = read_table(path)
    return table, tuple(n for n in refs if n not in table)


def plausibility_trips(paths: list[Path]) -> dict[str, Any]:
    """The catalogue's plausibility checks, as the daemon runs them (:class:`Plausibility` on the 12 inputs and
    the checks' references, one 20 Hz row per tick; a reference that is NaN, or missing from a recording, is
    stale there: its checks are not judged), over the 20 Hz tables of recordings: how often each check failed,
    and where; per check, its judged ticks and its largest residual against its tolerance, and per check
    debounced on its last judged ticks, the most failures one of its windows held."""
    from virtsensor.daemon.layout import check_references, plausibility_rules
    from virtsensor.daemon.validity import Plausibility, judge
    from virtsensor.recordings.files import recording_files

    refs = check_references(cat.INPUTS, CanMatrix.load())
    names = cat.INPUTS + refs
    rules = plausibility_rules(names)
    trips: Counter[str] = Counter()
    where: list[str] = []
    judged = [0] * len(rules)
    worst: list[dict[str, Any]] = [{"residual": 0.0, "tolerance": math.nan, "ratio": 0.0, "at": None} for _ in rules]
    lacking: Counter[str] = Counter()
    crowded = [0] * len(rules)  # windowed checks: the most failures any window held
    runs = rows = 0
    for src in recording_files(paths):
        table, missing = _table_with_references(src.path, refs)
        lacking.update(missing)
        cols = [np.asarray(table[n], np.float64) if n in table else np.full(len(table["time_s"]), np.nan)
                for n in names]
        values = np.column_stack(cols)
        stale_rows = np.isnan(values) & (np.arange(len(names)) >= len(cat.INPUTS))
        p = Plausibility(rules, len(names))
        prev = [math.nan] * len(names)
        for k, (row, stale) in enumerate(zip(values.tolist(), stale_rows.tolist(), strict=True)):
            for c, r in enumerate(rules):
                ok, res, tol = judge(r, row, prev, stale)
                judged[c] += ok
                if ok and res / tol > worst[c]["ratio"]:
                    worst[c] = {"residual": round(res, 4), "tolerance": round(tol, 4), "ratio": round(res / tol, 3),
                                "at": f"{src.path.name} t={float(table['time_s'][k]):.2f}"}
            prev = row
            n_new = p.update(row, stale)
            counts = p.counts
            for c, r in enumerate(rules):
                if r.window and counts[c] > crowded[c]:
                    crowded[c] = counts[c]
            if n_new:
                for c, r in enumerate(rules):
                    if p.new[c]:
                        trips[r.name] += 1
                        where.append(f"{src.path.name}: {r.name}")
        runs += 1
        rows += len(table["time_s"])
    return {"runs": runs, "rows": rows, "trips": {r.name: trips[r.name] for r in rules}, "where": where[:20],
            "judged_ticks": {r.name: judged[c] for c, r in enumerate(rules)},
            "largest_residual": {r.name: worst[c] for c, r in enumerate(rules)},
            "most_failures_in_a_window": {r.name: f"{crowded[c]} of {r.window}" for c, r in enumerate(rules)
                                          if r.window},
            "runs_lacking_reference": dict(lacking)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=30.0, help="replayed bus time (default 30)")
    p.add_argument("--seed", type=int, default=1, help="seed of the faults (default 1)")
    p.add_argument("--json", type=Path, help="write the figures here")
    p.add_argument("--tables", type=Path, nargs="+", metavar="PATH",
                   help="instead: run the plausibility checks over these recordings (files or directories) and "
                        "count how often each failed")
    a = p.parse_args(argv)
    if a.tables:
        from virtsensor.errors import UserError

        try:
            res = plausibility_trips(a.tables)
        except UserError as exc:
            print(f"fault_soak: error: {exc}", file=sys.stderr)
            return 2
        print(json.dumps(res))
        return 0 if not any(res["trips"].values()) else 1
    t0 = time.perf_counter()
    out = soak(a.minutes, a.seed, log=lambda m: print(m, file=sys.stderr))
    out["total_wall_s"] = round(time.perf_counter() - t0, 1)
    text = json.dumps(out, indent=1)
    if a.json:
        a.json.write_text(text + "\n")
    print(json.dumps({k: v for k, v in out.items() if k not in ("fault_matrix", "counters", "log_events")}))
    ok = out["valid_on_dead_or_implausible"] == 0 and out["tick_errors"] == 0 and out["crashes"] == 0
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
