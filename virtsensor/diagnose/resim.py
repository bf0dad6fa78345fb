"""Re-simulate measured runs from their driver inputs, under hypotheses.

A hypothesis is the nominal car, or the car with one candidate effect of
:mod:`sim.effects` at one value. Each gap-free segment of a measured run is
re-simulated from its recorded steering-wheel angle and traction-motor torque, open loop
(:func:`sim.manoeuvres.from_recording`, :data:`LONGITUDINAL`), and the car's signals are predicted
at the measured ticks: the sensor model without its random noise (latency,
update rate, quantisation and the hypothesis' sensor error kept), read as a
receiver on the bus reads it (a held frame is on average half a cycle old). Open loop, each
segment's re-simulated speed is re-anchored on the car's three speed sensors (:func:`reanchor`).

A sensor effect on a signal that drives the re-simulation (steering angle,
speed, motor torque) also corrects the drive: if the car's sensor reads ``y = g x(t - d) + o``,
the re-simulation is driven by ``x(t) = (y(t + d) - o) / g``.

All hypotheses' segments advance together in vectorised batches, spread over
joblib workers (``n_jobs``).
"""

from __future__ import annotations

import copy
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim.effects import DRIVE_SIGNALS, effect_overrides
from sim.params import apply_overrides
from virtsensor import signals as cat
from virtsensor.recordings.measured import MeasuredRun
from virtsensor.signals import TABLE_TICK_S as TICK_S

#: the re-simulation starts from straight-line running: its first seconds are not compared
SETTLE_S = 1.5
#: how the re-simulation's speed is driven (see :func:`sim.manoeuvres.from_recording`): by the recorded motor
#: torque, open loop (through the hypothesised sensor model inverted, :func:`drive_table`), so that the speed,
#: the longitudinal acceleration and the wheel speeds are re-simulated quantities that a torque error shows in.
#: With a speed controller instead (``"speed"``) the re-simulated motor torque is the recorded one plus the
#: loop's correction: a torque gain or delay changes it by a fraction only, and the loop's own tracking error
#: looked like one (dev seeds 950-951: the true motor-torque gain's evidence 2450 with the loop, 15700 open loop;
#: the control day's speed residual 0.021 and 0.029 m/s). The friction brakes are not recorded: a run that
#: brakes is not reproduced open loop.
LONGITUDINAL = "torque"
#: the sensors of the car's forward speed: the speed and the front wheel speeds (:func:`reanchor`)
SPEED_SENSORS = ("vx_mps", "wheel_speed_fl_radps", "wheel_speed_fr_radps")
#: truth channels kept at the ticks (for the residuals' dependence on the operating point)
TRUTH_AT_TICKS = ("alpha_fl", "alpha_fr", "fz_fl", "fz_fr", "sat_fl", "sat_fr")


@dataclass(frozen=True)
class Hypothesis:
    """The nominal car (``cause is None``), or one effect at ``value`` and possibly more on top (``also``:
    ``(cause, value, signal)`` each); ``runs`` sets per-run condition values (``(run, quantity, value)``,
    quantities of :mod:`virtsensor.diagnose.conditions`) over the day's; ``only`` re-simulates only those
    runs (the others' items are left empty)."""

    cause: str | None = None
    value: float = 0.0
    signal: str | None = None
    also: tuple[tuple[str, float, str | None], ...] = ()
    runs: tuple[tuple[int, str, float], ...] = ()
    only: tuple[int, ...] | None = None

    def effects(self) -> list[tuple[str, float, str | None]]:
        """Every effect of the hypothesis, ``(cause, value, signal)``."""
        first = [(self.cause, self.value, self.signal)] if self.cause is not None else []
        return first + list(self.also)

    def conditions(self, run: int, day: Mapping[str, float]) -> dict[str, float]:
        """The condition values of run ``run``: the day's (``day``), with this hypothesis' overrides."""
        out = dict(day)
        out.update({q: v for r, q, v in self.runs if r == run})
        return out


NOMINAL = Hypothesis()


def compared_signals(runs: Sequence[MeasuredRun]) -> tuple[str, ...]:
    """Signals compared: the 12 inputs, the reference SATs and the TPMS pressures
    when every run carries them; not the motor torque when it drives the re-simulation open loop
    (:data:`LONGITUDINAL`): its re-simulated reading is the recording echoed, and carries no evidence."""
    tpms = (n for n, s in cat.SIGNALS.items() if s.message == "TPMS_Pressures")
    extra = tuple(s for s in tpms if all(s in r.table for r in runs))
    inputs = tuple(n for n in cat.INPUTS if not (LONGITUDINAL == "torque" and n == "motor_torque_nm"))
    return (*inputs, *cat.OUTPUTS, *extra)


def noise_free(params: Mapping[str, Any]) -> dict[str, Any]:
    """``params`` with every sensor's white noise off (the expected reading)."""
    tree = copy.deepcopy(dict(params))
    for spec in tree["sensors"].values():
        spec["noise"] = 0.0
    return tree


def car_for(base: Mapping[str, Any], hyp: Hypothesis, conditions: Mapping[str, float] | None = None
            ) -> dict[str, Any]:
    """The car of a hypothesis (noise-free sensors) in a run's known ``conditions`` (they win over an effect
    on the same parameter: what the engineer measured on the day is a fact)."""
    from virtsensor.diagnose.conditions import run_overrides

    tree = noise_free(base)
    for cause, value, signal in hyp.effects():
        tree = apply_overrides(tree, effect_overrides(cause, value, tree, signal))
    if conditions:
        over = run_overrides(conditions, tree)
        if over:
            tree = apply_overrides(tree, over)
    return tree


def measurement_age(params: Mapping[str, Any], name: str) -> float:
    """Mean age (s) of a signal's value in the 20 Hz table: the sensor's latency, half
    its update period and half its CAN message's cycle (a held frame)."""
    from sim.sensors import SOURCES

    spec = params["sensors"][SOURCES[name][0]]
    sig = cat.SIGNALS[name]
    return float(spec["latency_s"] + 0.5 / spec["rate_hz"] + 0.5 * cat.MESSAGES[sig.message].cycle_s)


def drive_table(seg: Mapping[str, np.ndarray], hyp: Hypothesis,
                params: Mapping[str, Any] | None = None) -> dict[str, np.ndarray]:
    """The drive inputs of a segment, corrected for a hypothesised error of a drive sensor.

    The recorded values are measurements of some age (:func:`measurement_age`);
    the drive is advanced by that age so that the re-simulated car steers when
    the real one did, not when its sensor reported it.
    """
    t = seg["time_s"] - seg["time_s"][0]
    out = {"time_s": t}
    for name in DRIVE_SIGNALS:
        if name not in seg:
            continue
        y = np.asarray(seg[name], dtype=float)
        lead = measurement_age(params, name) if params is not None else 0.0
        if name == "motor_torque_nm" and params is not None:
            lead += params["powertrain"]["torque_time_constant_s"]  # the motor's own response
        out[name] = np.interp(t + lead, t, y) if lead > 0 else y
    for cause, value, signal in hyp.effects():
        if not (cause.startswith("sensor_") and signal in DRIVE_SIGNALS and signal in out):
            continue
        y = out[signal]
        if cause == "sensor_delay":
            x = np.interp(t + value, t, y)  # the last value is held beyond the end
        elif cause == "sensor_offset":
            x = y - value
        else:
            x = y / value
        out[signal] = x
    return out


@dataclass
class Job:
    """One segment of one run under one hypothesis."""

    hyp: int
    run: int
    seg: int
    plan: Any
    tree: dict[str, Any]
    times: np.ndarray  # segment ticks on the re-simulation's clock (s)
    keep_streams: bool


def _sample(t: np.ndarray, stream: np.ndarray, times: np.ndarray, name: str, shift: float = 0.0) -> np.ndarray:
    """A stream read at ``times - shift`` (linear between its samples), quantised to the
    signal's resolution: ``shift`` is the reading's age (see :func:`align`)."""
    sig = cat.SIGNALS[name]
    y = np.interp(times - shift, t, stream)
    if sig.resolution > 0:
        y = np.round(y / sig.resolution) * sig.resolution
    return y


def predicted(t: np.ndarray, streams: Mapping[str, np.ndarray], times: np.ndarray,
              names: Sequence[str], shifts: Mapping[str, float] | None = None) -> dict[str, np.ndarray]:
    """The signals ``names`` at ``times`` from sensor streams on the grid ``t``;
    ``shifts`` maps a CAN message to the age of its readings (s)."""
    shifts = shifts or {}
    return {n: _sample(t, streams[n], times, n, shifts.get(str(cat.SIGNALS[n].message), 0.0)) for n in names}


def align(runs: Sequence[MeasuredRun], nominal: Sequence[Sequence[Mapping[str, Any]]],
          names: Sequence[str], masks: Mapping[str, Sequence[Sequence[np.ndarray]]] | None = None
          ) -> dict[str, float]:
    """Each CAN message's reading age (s): when a receiver samples a held frame at a
    tick, the value it reads is up to one cycle old, by a phase that depends on the
    bus schedule and is unknown for measured data. It is estimated per message, for the
    whole day (one age for every run, whatever its speed), on a re-simulation ``nominal``
    (all the message's signals together), within +-1 cycle: far less than the sensor delays
    the diagnosis looks for. ``masks``: the rows compared per signal, run and segment
    (default: :func:`segment_mask`). The diagnosis estimates them again on each whole-day
    hypothesis of the car's physics (:func:`virtsensor.diagnose.identify.own_ages`): ages fixed
    on the nominal car absorb part of a physical lag (a relaxation length's, sigma / v) and
    then count against the hypothesis that explains it."""
    out: dict[str, float] = {}
    by_msg: dict[str, list[str]] = {}
    for n in names:
        by_msg.setdefault(str(cat.SIGNALS[n].message), []).append(n)
    for msg, sigs in by_msg.items():
        cyc = cat.MESSAGES[msg].cycle_s
        grid = np.arange(-cyc, cyc + 1e-9, 0.0025)
        cost = np.zeros(len(grid))
        for n in sigs:
            per = np.zeros(len(grid))
            for r, run in enumerate(runs):
                for s, seg in enumerate(run.segments):
                    item = nominal[r][s]
                    if not item:
                        continue
                    y = run.table[n][seg.start:seg.stop]
                    times = np.arange(seg.n) / cat.TABLE_RATE_HZ
                    m = masks[n][r][s] if masks is not None else segment_mask(run, s, n)
                    e = y[m][None, :] - np.interp(times[m][None, :] - grid[:, None], item["t"], item["streams"][n])
                    per += np.sum(e * e, axis=1)
            cost += per / max(per[np.argmin(np.abs(grid))], 1e-300)
        out[msg] = float(grid[int(np.argmin(cost))])
    return out


def _run_jobs(jobs: Sequence[Job], names: tuple[str, ...], shifts: Mapping[str, float] | None
              ) -> list[dict[str, Any]]:
    """Simulate a group of jobs in one batch; per job the predicted signals (and the
    streams and truth at the ticks when asked)."""
    from sim.engine import simulate_batch
    from sim.sensors import make_streams

    res = simulate_batch([j.plan for j in jobs], [j.tree for j in jobs])
    out = []
    for i, job in enumerate(jobs):
        truth = res.run(i)
        streams = make_streams(truth, job.tree, seed=0)
        t = truth["time_s"]
        item: dict[str, Any] = {"pred": predicted(t, streams, job.times, names, shifts),
                                "complete": bool(t[-1] >= job.times[-1] - 0.02)}
        if job.keep_streams:
            item["t"] = t
            item["streams"] = {n: streams[n] for n in names}
            item["truth"] = {k: np.interp(job.times, t, truth[k]) for k in TRUTH_AT_TICKS}
        out.append(item)
    return out


def simulate_hypotheses(runs: Sequence[MeasuredRun], hyps: Sequence[Hypothesis], base: Mapping[str, Any],
                        conds: float | Sequence[Mapping[str, float]], names: tuple[str, ...], *, n_jobs: int = 1,
                        keep_streams: Sequence[bool] | None = None, shifts: Mapping[str, float] | None = None,
                        backend: str = "loky") -> list[list[list[dict[str, Any]]]]:
    """Re-simulate every segment of every run under every hypothesis.

    ``conds`` is each run's condition values (``mu`` and any of the car's quantities of
    :mod:`virtsensor.diagnose.conditions`), or one road friction for all runs.

    Returns ``out[h][r][s]``: dict with ``pred`` (signal -> values at the segment's
    ticks) and ``complete`` (False if the re-simulation ended early: the car spun
    or stopped); with ``t``, ``streams`` and ``truth`` for hypotheses whose
    ``keep_streams`` is set; an empty dict for runs a hypothesis leaves out (``only``).
    Batches run on joblib workers (``backend``: ``loky``, or ``ray`` for a Ray cluster,
    see :func:`virtsensor.diagnose.parallel.run_parallel`).
    """
    from sim.manoeuvres import from_recording
    from virtsensor.diagnose.parallel import run_parallel

    day = [{"mu": float(conds)} for _ in runs] if isinstance(conds, (int, float)) else [dict(c) for c in conds]
    keep = list(keep_streams) if keep_streams is not None else [False] * len(hyps)
    jobs: list[Job] = []
    for h, hyp in enumerate(hyps):
        for r, run in enumerate(runs):
            if hyp.only is not None and r not in hyp.only:
                continue
            cond = hyp.conditions(r, day[r])
            tree = car_for(base, hyp, cond)
            for s, seg in enumerate(run.segments):
                table = run.segment_table(seg)
                drive = drive_table(table, hyp, base)
                plan = from_recording(drive, cond["mu"], name=f"{run.name}#{s}", longitudinal=LONGITUDINAL)
                jobs.append(Job(h, r, s, plan, tree, drive["time_s"], keep[h]))
    # batches of similar length (little padding), a few per worker
    order = np.argsort([len(j.times) for j in jobs], kind="stable")[::-1]
    workers = max(1, n_jobs if n_jobs > 0 else os.cpu_count() or 1)
    n_groups = max(workers, int(np.ceil(len(jobs) / 40)))
    groups = [list(map(int, g)) for g in np.array_split(order, n_groups) if len(g)]
    results = run_parallel(_run_jobs, [([jobs[i] for i in g], names, shifts) for g in groups],
                           n_jobs=workers, backend=backend)
    out: list[list[list[dict[str, Any]]]] = [[[{} for _ in run.segments] for run in runs] for _ in hyps]
    for g, items in zip(groups, results, strict=True):
        for i, item in zip(g, items, strict=True):
            j = jobs[i]
            if LONGITUDINAL == "torque":
                reanchor(runs[j.run], j.seg, item)
            out[j.hyp][j.run][j.seg] = item
    return out


def reanchor(run: MeasuredRun, seg_index: int, item: dict[str, Any]) -> float:
    """Re-anchor a segment's re-simulated forward speed on the car's, in place; returns the correction (m/s).

    Driven open loop by the motor torque (:data:`LONGITUDINAL`), the re-simulation starts from one recorded
    speed sample, whose error (the speed sensor's white noise, 0.02 m/s, its quantisation, the acceleration at
    the start) nothing pulls back: drag and rolling resistance take a speed error out over a minute or more, so
    it stays as an offset of the whole segment in the speed and both wheel speeds. A hypothesis that moves that
    sample (a delay of the speed sensor reads another one) moved the whole re-simulated speed, and soaked up the
    offset on control days. The car's speed in the segment is instead re-anchored on what its three speed
    sensors say: each one's mean residual over the compared rows (measured - re-simulated; a wheel speed's
    scaled to m/s by the re-simulation's speed over it), and of the three the median (one faulty sensor, an
    offset or gain of its own, does not move it: it keeps its evidence, against the other two). The correction
    is added to the three predictions (and streams, when kept), the wheel speeds' scaled back. A physical
    effect that moves the car's speed keeps its evidence in how the speed evolves (a torque gain: a ramp, less
    its mean) and in the longitudinal acceleration; what a one-sample start cannot tell is not evidence."""
    if not item or any(n not in item["pred"] or n not in run.table for n in SPEED_SENSORS):
        return 0.0
    seg = run.segments[seg_index]
    pv = item["pred"]["vx_mps"]
    means, scales = [], {}
    for n in SPEED_SENSORS:
        m = segment_mask(run, seg_index, n)
        p = item["pred"][n]
        if m.sum() < 2:
            return 0.0
        scales[n] = float(np.mean(pv[m])) / max(float(np.mean(p[m])), 1e-6)
        if not (np.isfinite(scales[n]) and scales[n] > 0.0):
            return 0.0  # a re-simulated car that does not roll forward: no speed to re-anchor
        means.append(scales[n] * float(np.mean(run.table[n][seg.start:seg.stop][m] - p[m])))
    d = float(np.median(means))
    if not np.isfinite(d):
        return 0.0
    for n in SPEED_SENSORS:
        res = cat.SIGNALS[n].resolution
        y = item["pred"][n] + d / scales[n]
        item["pred"][n] = np.round(y / res) * res if res > 0 else y
        if "streams" in item:
            item["streams"][n] = item["streams"][n] + d / scales[n]
    item["speed_anchor_mps"] = d
    return d


def segment_mask(run: MeasuredRun, seg_index: int, name: str) -> np.ndarray:
    """Rows of a segment that are compared for ``name``: finite, after the settling time."""
    seg = run.segments[seg_index]
    y = run.table[name][seg.start:seg.stop]
    t = np.arange(seg.n) * TICK_S
    return np.isfinite(y) & (t >= SETTLE_S)
