"""The real-time virtual-sensor daemon: CAN in, 20 Hz ``SAT_FRONT`` + ``VS_Health`` out.

:class:`VirtualSensor` composes the parts of :mod:`virtsensor.daemon`: the input layout read from the model
card and the DBC (:mod:`~virtsensor.daemon.layout`), the receive path (:mod:`~virtsensor.daemon.receive`:
generated per-message receivers, frame order, clock mapping), the validity contract
(:mod:`~virtsensor.daemon.validity`), the feature builder (:class:`~virtsensor.features.FeatureBuilder`, the
numbers the trainer's ``FeatureSpec.transform`` gives on the 20 Hz table), the ONNX model
(:meth:`~virtsensor.model.onnx.OnnxModel.predict_one`, one thread, no spinning), the output frames
(:mod:`~virtsensor.daemon.publish`) and the threads (:mod:`~virtsensor.daemon.runner`).

Clocks. Free-running (default), the tick thread wakes on absolute deadlines ``t0 + k * 50 ms`` of
``time.monotonic_ns``, drains every frame the bus has queued (no wake-up per frame), ages each by its
interface timestamp mapped onto ``time.monotonic`` (:class:`~virtsensor.daemon.receive.ClockMap`; the read
time for frames without one), then ticks at the time the drain ended. In sync mode (``sync_id``), a receive
thread reads frame by frame and every ``sync_every``-th sync frame ticks, right after the frames received
before it, at tick time = the sync frame's timestamp (frame times are the bus's own): replaying a log with a
sync frame just after each 20 Hz grid instant gives, tick for tick, the offline table of
:func:`virtsensor.recordings.canlog.read_log`.

Real-time hygiene: every array and list the tick touches is allocated at start-up and reused, except the
feature vector (a list the generated builder makes per tick) and the model's two outputs as a list; numpy
is called only to hand the features to onnxruntime and take its outputs back (every numpy call is dear on
caches gone cold between 20 Hz ticks: README, "Where the CPU at 20 Hz goes"). After start-up the heap is
``gc.freeze()``-d and the cyclic GC is off during the tick.

Logs are JSON lines on stderr (:func:`~virtsensor.daemon.jsonlog.configure_logging`): ``started``,
``config``, ``bus_error``, ``reconnect``, ``status_change``, ``envelope_exit``/``envelope_return`` (once per
excursion outside the model card's validity envelope), ``shutdown``...
"""

from __future__ import annotations

import gc
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Mapping
from functools import partial
from typing import Any

from virtsensor.canbus.codec import STATUS_KEYS, CanMatrix
from virtsensor.canbus.e2e import E2EStatus
from virtsensor.daemon.buslink import BusLink
from virtsensor.daemon.config import RuntimeConfig, load_config
from virtsensor.daemon.jsonlog import event, log
from virtsensor.daemon.layout import InputLayout
from virtsensor.daemon.pressure import PressureFallback
from virtsensor.daemon.publish import Publisher
from virtsensor.daemon.receive import ReceivePath, StageHook
from virtsensor.daemon.runner import TICK_NS, Runner
from virtsensor.daemon.stats import TickStats
from virtsensor.daemon.tickrate import MAX_TICK_GAP_S, MIN_TICK_GAP_S, TickRate
from virtsensor.daemon.validity import (
    INIT,
    INVALID,
    STATUS_NAMES,
    EnvelopeMemory,
    EnvelopeRules,
    Plausibility,
    ValidityState,
    assess_inputs,
    envelope_status,
    outside_envelope,
    restart_recovery,
    wheel_status,
)
from virtsensor.errors import UserError
from virtsensor.features import FeatureBuilder
from virtsensor.signals import INPUT_TIMEOUT_CYCLES

__all__ = ["VirtualSensor", "STAGES"]

#: Stage names a ``stage_hook`` sees: per input frame ``decode`` (DLC, CRC, E2E, decode, store); per tick
#: ``plausibility`` (the redundancy checks), ``validity`` (input status and health bitmap), ``feature_vector``,
#: ``inference``, ``envelope`` (the card's envelope test; only with an envelope and finite features), ``encode``
#: (SAT_FRONT), ``grip`` (the VS_Grip estimate and its encoding) and ``send`` (SAT_FRONT).
STAGES = ("decode", "plausibility", "validity", "feature_vector", "inference", "envelope", "encode", "grip", "send")

#: the daemon's own frames (a sync id may not be one of them)
_OWN_MESSAGES = ("SAT_FRONT", "VS_Health", "VS_Grip")
_COUNTERS = ("frames", "input_frames", "other_frames", "unknown_ids", "error_frames", "remote_frames", "sync_frames",
             "crc_errors", "dlc_errors", "sna_values", "implausible_values",
             *(STATUS_KEYS[s] for s in E2EStatus if s is not E2EStatus.NODATA),
             "future_stamped", "time_step_back", "implausible_checks", "drained_frames",
             "ticks", "overruns", "tick_errors", "sent", "send_errors", "unsent", "recv_errors", "reconnects",
             "reconnect_failures", "status_changes", "envelope_exits", "envelope_ticks", "tick_gaps", "tick_rate_off",
             "clock_unconfirmed_ticks", "unstamped_frames")


class VirtualSensor:
    """The daemon. Build it with :meth:`from_config`, or directly from an open bus, model and matrix.

    Args:
        bus: an open ``can.BusABC`` (any interface); the sensor owns it (shuts it down in :meth:`stop`).
        model: a loaded :class:`~virtsensor.model.onnx.OnnxModel` (read through ``card``, ``input_names``,
            ``outputs``, ``card_path``, ``predict_one``).
        matrix: a :class:`~virtsensor.canbus.codec.CanMatrix` (its tables are shared; the sensor keeps its own
            E2E state with ``timeout_cycles``).
        sync_id, sync_every, timeout_cycles, model_id, cpu, realtime, rt_priority, cpu_latency_us: see
            :class:`RuntimeConfig`.
        bus_factory: opens a new bus after a bus error (None: the sensor keeps retrying the same bus).
        freeze_gc: ``gc.freeze()`` after start-up and no cyclic GC during the tick.
        reconnect_backoff_s, reconnect_max_s: first and largest wait before re-opening the bus.
        stage_hook: ``hook(stage, fn) -> fn`` called once per stage callable at construction (names in
            :data:`STAGES`); the returned callable is used instead (e.g. to time it). None: no wrapping.

    Raises:
        UserError: the model card lacks a usable ``feature_spec``, or names inputs the DBC lacks,
            or the DBC lacks SAT_FRONT/VS_Health, or ``sync_id`` is one of the daemon's own ids.

    Driving it by hand (tests, simulations): :meth:`process` feeds one received ``can.Message``,
    :meth:`tick` runs one tick at a given time (in sync mode, call both from one thread: the receive thread
    once started); :meth:`start`/:meth:`stop` run the threads; :meth:`run` also handles SIGTERM/SIGINT.
    :attr:`counters`, :attr:`tick_stats` and :meth:`stats` report.
    """

    def __init__(self, bus: Any, model: Any, matrix: CanMatrix, *, sync_id: int | None = None,
                 sync_every: int = 1, timeout_cycles: float = INPUT_TIMEOUT_CYCLES, model_id: int | None = None,
                 bus_factory: Callable[[], Any] | None = None, cpu: int | None = None, realtime: bool = False,
                 rt_priority: int = 50, cpu_latency_us: int | None = None, freeze_gc: bool = True,
                 reconnect_backoff_s: float = 0.05,
                 reconnect_max_s: float = 2.0, stage_hook: StageHook | None = None) -> None:

        if timeout_cycles < 1:
            raise ValueError("timeout_cycles must be >= 1")
        if sync_every < 1:
            raise ValueError("sync_every must be >= 1")
        self.model = model
        self.timeout_cycles = float(timeout_cycles)
        # own E2E state, with our timeout (a frame after a longer gap is WRONGSEQUENCE)
        self.matrix = CanMatrix(matrix.db, matrix.messages, matrix.source, max_delta=matrix.max_delta,
                                timeout_cycles=self.timeout_cycles)
        self.layout = lay = InputLayout.from_model(model, self.matrix, self.timeout_cycles, model_id)
        self.spec, self.signals, self.critical = lay.spec, lay.signals, lay.critical
        self.input_messages, self.bitmap_bits, self.model_id = lay.input_messages, lay.bitmap_bits, lay.model_id
        _check_sync(self.matrix, sync_id, int(sync_every))
        self.sync_id = sync_id
        self.sync_every = int(sync_every)
        self._freeze_gc = freeze_gc
        #: event counters (frames, E2E outcomes, frame order, ticks, bus errors, reconnects, ...)
        self.counters: dict[str, int] = dict.fromkeys(_COUNTERS, 0)
        hook = stage_hook or (lambda name, fn: fn)
        #: the receive path (sample-and-hold lists, frame order, clock map)
        self.inputs = ReceivePath(lay, self.matrix, self.counters, stage_hook, sync_id)
        self.inputs.on_sync = self._on_sync
        self.process = self.inputs.handle  # type: ignore[method-assign]  # (see process)
        self._out = Publisher(lay, self.matrix, stage_hook)
        self._stop = threading.Event()
        self._link = BusLink(bus, bus_factory, self.counters, self._stop, reconnect_backoff_s, reconnect_max_s)
        self._push = hook("feature_vector", FeatureBuilder(lay.spec).push)
        self._tick_t = -math.inf  # (the previous tick's time)
        self._rate = TickRate()
        self._predict = hook("inference", model.predict_one)
        self.fallback, self._predict_fb, self._inputs_complete = _fallback_parts(model, lay, hook, self._predict)
        self._send_sat = hook("send", self._link.send)
        self._rules = lay.rules()
        self._state = ValidityState(len(lay.decoded))
        self._plaus = Plausibility(lay.plausibility_rules(), len(lay.decoded))
        self._plaus_update = hook("plausibility", self._plaus.update)
        self._assess = hook("validity", assess_inputs)
        self._outside = hook("envelope", outside_envelope)
        self._fill_grip = hook("grip", self._out.grip.fill_tick)
        self.envelope = _card_envelope(model)
        self._env_rules = None if self.envelope is None else EnvelopeRules.from_envelope(self.envelope, lay.signals)
        self._env_memory = EnvelopeMemory(max(self._rules.sig_hist, default=0))  # (the rows the features read)
        #: the latest tick's inputs were outside the model card's validity envelope
        self.outside_envelope = False
        self._msg_err = [False] * len(lay.input_messages)  # the tick's E2E errors (for the logs)
        self._complete = False
        self._sync_count = 0
        #: rings of tick latency, compute time and wake-up lateness
        self.tick_stats = TickStats()
        self._wheels = tuple((w.output, w.estimate, w.status, w.lo, w.hi) for w in lay.wheels)
        self._statuses: list[float] = [INIT] * len(lay.wheels)  # of the latest tick
        self._last_bitmap = -1  # of the latest logged change (-1: log the first tick)
        self.last_statuses: tuple[int, ...] = (INIT,) * len(lay.wheels)
        self.last_bitmap = 0
        self._runner = Runner(self, self._link, self._stop, cpu=cpu, realtime=realtime, rt_priority=rt_priority,
                              freeze_gc=freeze_gc, cpu_latency_us=cpu_latency_us)
        self.cpu, self.realtime, self.rt_priority = cpu, bool(realtime), int(rt_priority)
        #: the configuration it was built from (set by :meth:`from_config`)
        self.config: RuntimeConfig | None = None

    @classmethod
    def from_config(cls, config: RuntimeConfig | Mapping[str, Any] | str | os.PathLike, *, bus: Any = None,
                    bus_factory: Callable[[], Any] | None = None, **kwargs: Any) -> VirtualSensor:
        """Load the model (sha256 checked against its card) and the DBC, check them, open the bus.

        Args:
            config: a :class:`RuntimeConfig`, a mapping of its fields, or a TOML file path.
            bus: an already open bus (default: open ``interface``/``channel`` with python-can).
            bus_factory: re-opens the bus after errors (default: the same python-can call as at start,
                or None when ``bus`` is given).
            kwargs: passed to the constructor (e.g. ``freeze_gc``).

        Raises:
            UserError: unreadable/invalid config, model or DBC; model inputs not in the DBC; bus not openable.
        """
        return _from_config(cls, config, bus, bus_factory, kwargs)

    @property
    def bus(self) -> Any:
        """The bus in use (None while re-opening it)."""
        return self._link.bus

    @property
    def mode(self) -> str:
        return "free-running" if self.sync_id is None else f"sync 0x{self.sync_id:X}/{self.sync_every}"

    @property
    def threads(self) -> tuple[threading.Thread, ...]:
        """The daemon's running threads (tick and supervisor when free-running; receive in sync mode)."""
        return self._runner.threads

    @property
    def cpu_latency(self) -> Any:
        """The PM QoS CPU-latency request (:class:`~virtsensor.daemon.pmqos.CpuLatencyRequest`: ``us``, ``held``,
        ``error``) held while running, or None when none was asked for."""
        return self._runner.cpu_latency

    # ------------------------------------------------------------------------------------------ receive path
    def process(self, msg: Any, rx_time: float | None = None) -> None:
        """Handle one received python-can ``Message`` (decode, E2E, store; a sync frame then ticks).

        ``rx_time``: its time (s) on the daemon's clock when free-running (default ``time.monotonic()``);
        sync mode uses ``msg.timestamp``. (Each instance binds this name straight to its receive path's
        :meth:`~virtsensor.daemon.receive.ReceivePath.handle`, one call less per frame.)
        """
        self.inputs.handle(msg, rx_time)

    def _on_sync(self, msg: Any) -> None:
        self.counters["sync_frames"] += 1
        k = self._sync_count
        self._sync_count = k + 1
        if k % self.sync_every == 0:
            self._safe_tick(float(msg.timestamp), time.monotonic_ns())

    def drain(self) -> int:
        """Handle every frame the bus has queued (free-running, at each tick); returns how many. A receive
        error is counted and hands the bus to the reconnect."""
        link = self._link
        if link.needs_reconnect.is_set():
            return 0
        with link.lock:
            bus = link.bus
            if bus is None:
                return 0
            try:
                n = self.inputs.drain(bus)
            except Exception as exc:  # noqa: BLE001 - any interface error: count, reconnect
                n = 0
                if not self._stop.is_set():
                    link.recv_failed(exc)
        self.counters["drained_frames"] += n
        return n

    # ------------------------------------------------------------------------------------------ the tick
    def tick(self, t: float | None = None) -> tuple[int, ...]:
        """Run one tick at time ``t`` (s, the daemon's clock; default now) and publish; returns the statuses."""
        self._safe_tick(time.monotonic() if t is None else t, time.monotonic_ns())
        return self.last_statuses

    def _safe_tick(self, t: float, start_ns: int) -> None:
        try:
            self._tick(t, start_ns)
        except Exception:  # noqa: BLE001 - a bug must not kill the daemon; consumers see SAT_FRONT time out
            self.counters["tick_errors"] += 1
            n = self.counters["tick_errors"]
            if n <= 3 or n % 100 == 0:
                log.exception("tick_error", extra={"fields": {"tick_errors": n}})

    def _tick(self, t: float, start_ns: int) -> None:
        gc_off = self._freeze_gc and gc.isenabled()
        if gc_off:
            gc.disable()
        try:
            rx = self.inputs
            ta = _assess_time(self, t)
            order = rx.order
            n_future = order.tick(t)
            if n_future:
                self.counters["future_stamped"] += n_future
            if not self._complete:
                self._complete = self._inputs_complete(rx.times)
            plaus = self._plaus
            if self._plaus_update(rx.values, self._state.stale):  # (stale: the previous tick's verdicts)
                _log_implausible(self, t)
            status, bitmap = self._assess(ta, rx.times, rx.flags, rx.last_ok, rx.errors, order.in_order,
                                           self._rules, self._state, plaus.implausible)
            self._msg_err[:] = rx.errors
            rx.clear_errors()
            outside = self._estimate(status)
            crossed = _count_envelope(self, outside)
            self._publish(start_ns, bitmap)
        finally:
            if gc_off:
                gc.enable()
        if crossed:  # (logged after the frames are out)
            _log_envelope(self, t, outside)
        sv, cur = self._out.sat_values, self._statuses
        changed = bitmap != self._last_bitmap
        for k, w in enumerate(self._wheels):
            s = sv[w[2]]
            if s != cur[k]:
                cur[k] = s
                changed = True
        self.last_bitmap = bitmap
        if changed:  # (a new tuple and a log line only when something changed)
            self._last_bitmap = bitmap
            self.last_statuses = tuple(int(s) for s in cur)
            _log_change(self, t, self.last_statuses, bitmap, status)

    def _estimate(self, status: int) -> bool:
        """Features, model and per-wheel status into the SAT_FRONT values; returns whether the inputs are
        outside the model's validity envelope (False without features or without an envelope)."""
        sv = self._out.sat_values
        x = self._push(self.inputs.values) if self._complete else None
        if x is None:
            for _, est, st, _, _ in self._wheels:
                sv[est] = math.nan
                sv[st] = INIT
            return False
        x, predict = _model_inputs(self, x)  # (the pressure-free fallback while the pressures are unknown)
        total = sum(x)
        x_ok = total - total == 0.0  # every feature finite (a nan or an inf makes the sum's difference nan)
        y = predict(x).tolist() if x_ok else None
        rules = self._env_rules
        outside = self._env_memory.update(x_ok and rules is not None and self._outside(self.inputs.values, rules))
        for k, est, st, lo, hi in self._wheels:
            v = y[k] if (y is not None and k >= 0) else math.nan
            s = envelope_status(wheel_status(status, v, lo, hi), outside)
            sv[est] = math.nan if s == INVALID else v  # nan -> SNA on the bus
            sv[st] = s
        return outside

    def _publish(self, start_ns: int, bitmap: int) -> None:
        out = self._out
        m = out.fill_sat()
        self._fill_grip(out.sat_values, self.inputs.values, self._state.bad, self.outside_envelope)  # (VS_Grip)
        compute_us = (time.monotonic_ns() - start_ns) // 1000
        self._send_sat(m)
        lat_us = (time.monotonic_ns() - start_ns) // 1000  # (to SAT_FRONT handed to the bus, as VS_TickLatency says)
        out.grip.send(self._link.send)
        c = self.counters
        self._link.send(out.fill_health(c["overruns"], lat_us, bitmap, self.outside_envelope, c["envelope_exits"]))
        self.tick_stats.record_tick(lat_us, compute_us)
        c["ticks"] += 1
        if self.sync_id is not None and lat_us * 1000 > TICK_NS:
            c["overruns"] += 1

    # ------------------------------------------------------------------------------------------ threads
    def start(self) -> None:
        """Apply CPU affinity/SCHED_FIFO (if asked), start the threads, freeze the start-up heap."""
        self._runner.start()

    def request_stop(self) -> None:
        """Ask the threads to stop (thread-safe; :meth:`stop` then joins them)."""
        self._runner.request_stop()

    def stop(self, timeout: float = 1.0) -> dict[str, Any]:
        """Stop the threads, shut the bus down, log ``shutdown`` with the counters; returns :meth:`stats`."""
        return self._runner.stop(timeout)

    def run(self, duration: float | None = None) -> int:
        """Start, serve until SIGTERM/SIGINT (handlers installed when called from the main thread) or
        ``duration`` seconds, stop. Returns 0 on a clean stop, 1 when a worker thread died."""
        return self._runner.run(duration)

    def stats(self) -> dict[str, Any]:
        """Counters plus percentiles of the tick latency (us, tick start to SAT_FRONT sent), of the compute
        time (us, tick start to SAT_FRONT encoded: no bus I/O) and of the wake-up lateness (free-running)."""
        out: dict[str, Any] = dict(self.counters)
        out.update(self.tick_stats.summary())
        out["statuses"] = [STATUS_NAMES[s] for s in self.last_statuses]
        return out

    def __enter__(self) -> VirtualSensor:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()


def _from_config(cls: type[VirtualSensor], config: RuntimeConfig | Mapping[str, Any] | str | os.PathLike,
                 bus: Any, bus_factory: Callable[[], Any] | None, kwargs: dict[str, Any]) -> VirtualSensor:
    """The body of :meth:`VirtualSensor.from_config`."""
    from virtsensor.model.onnx import OnnxModel
    from virtsensor.recordings.replay import open_bus

    if isinstance(config, (str, os.PathLike)):
        cfg = load_config(config)
    else:
        cfg = config if isinstance(config, RuntimeConfig) else load_config(None, config)
    model = OnnxModel.load(str(cfg.model))  # (load_config checked model, interface, channel are set)
    matrix = CanMatrix.load(cfg.dbc)
    try:
        _check_sync(matrix, cfg.sync_id, cfg.sync_every)
    except UserError as exc:
        raise UserError(f"{cfg.where('sync_id')}: {exc}") from None
    def configured(fold_notes: bool) -> Callable[[], Any]:
        """The configured bus's opener; ``fold_notes``: python-can's notes into a failure's one line (only where
        no other thread runs: a reconnect, beside the tick thread, leaves python-can's logging as it is)."""
        return bus_factory or partial(open_bus, str(cfg.interface), str(cfg.channel), cfg.bitrate,
                                      fold_notes=fold_notes)

    opener = configured(False) if bus is None else bus_factory
    sensor = cls(bus, model, matrix, sync_id=cfg.sync_id, sync_every=cfg.sync_every,
                 timeout_cycles=cfg.timeout_cycles, model_id=cfg.model_id, bus_factory=opener,
                 cpu=cfg.cpu, realtime=cfg.realtime, rt_priority=cfg.rt_priority,
                 cpu_latency_us=cfg.cpu_latency_us, **kwargs)
    if bus is None:  # everything checked: now open the bus (UserError if it cannot; no thread runs yet)
        sensor._link.bus = configured(True)()
    sensor.config = cfg
    return sensor


def _check_sync(matrix: CanMatrix, sync_id: int | None, sync_every: int) -> None:
    """Refuse a sync id that is one of the daemon's own messages, or a message of the DBC whose cycle time times
    ``sync_every`` is not the 50 ms tick the features are built on (a sync frame outside the DBC is judged by its
    spacing as it comes: :mod:`virtsensor.daemon.tickrate`).

    Raises:
        UserError: naming the message, its cycle and the ``sync_every`` that would fit, if any.
    """
    if sync_id is None:
        return
    m = matrix.by_id.get(sync_id)
    if m is None:
        return
    if m.name in _OWN_MESSAGES:
        raise UserError(f"sync id 0x{sync_id:X} is the daemon's own {m.name} ({', '.join(_OWN_MESSAGES)} are sent, "
                        "not received)")
    period = m.cycle_s * sync_every
    if m.cycle_s > 0.0 and abs(period - TICK_NS * 1e-9) > 1e-9:
        fit = TICK_NS * 1e-9 / m.cycle_s
        hint = (f"; --sync-every {round(fit)} fits" if abs(fit - round(fit)) < 1e-9 and round(fit) >= 1 else
                "; no --sync-every fits: give a sync frame of a 50 ms multiple's divisor, or run free")
        raise UserError(f"sync id 0x{sync_id:X} is {m.name}, sent every {m.cycle_s * 1e3:g} ms: a tick on every "
                        f"{sync_every} of its frames comes every {period * 1e3:g} ms, not the 50 ms tick the model's "
                        f"features are built on{hint}")


def _fallback_parts(model: Any, lay: InputLayout, hook: Any, predict: Any) -> tuple[Any, Any, Any]:
    """A TPMS model's pressure-free fallback (:class:`~virtsensor.daemon.pressure.PressureFallback`, None when
    the card names none), its timed inference, and the test "every required input was received once" (a TPMS
    model does not wait for the slow, optional TPMS)."""
    fb = PressureFallback.for_model(model, lay.signals)
    if fb is None:  # (the check references after the model's inputs are not waited for)
        n = len(lay.signals)
        return None, predict, lambda times: all(times[i] > -math.inf for i in range(n))
    return fb, hook("inference", fb.predict_one), fb.complete


def _model_inputs(self: VirtualSensor, x: list[float]) -> tuple[list[float], Any]:
    """This tick's ``(features, inference)``: the model's, or, while a front pressure is bad (stale, SNA, E2E
    error, out of order), the pressure-free fallback's on the first features (the status is DEGRADED then)."""
    fb = self.fallback
    if fb is not None and fb.active(self._state.bad):
        return x[: fb.n], self._predict_fb
    return x, self._predict


def _assess_time(self: VirtualSensor, t: float) -> float:
    """The time the tick at ``t`` judges its inputs at: ``t``, or inf (no input fresh) while the free-running
    clock mapping is not confirmed (:class:`~virtsensor.daemon.receive.ClockMap`: the first drains). A tick too
    soon or too late after the previous one, or, in sync mode, one of sync ticks whose mean spacing is off 50 ms,
    restarts the inputs' histories (:mod:`virtsensor.daemon.tickrate`; free-running, the ticks are on absolute
    deadlines of the daemon's own clock: a wake-up's lateness moves single gaps, never their rate)."""
    gap = t - self._tick_t
    self._tick_t = t
    if gap == math.inf or gap > MAX_TICK_GAP_S:  # (the first tick, or one after a gap: a new window of ticks)
        self._rate.restart(t)
        if gap != math.inf:
            _restart_history(self, t, gap)
    elif self.sync_id is not None and not self._rate.regular(t):  # (free-running, the ticks keep their own clock)
        _restart_history(self, t, gap, mean=self._rate.mean_gap_s)
    elif gap < MIN_TICK_GAP_S:
        _restart_history(self, t, gap)
    if self.inputs.clock.confirmed:
        return t
    self.counters["clock_unconfirmed_ticks"] += 1
    return math.inf


def _restart_history(self: VirtualSensor, t: float, gap: float, mean: float | None = None) -> None:
    """After a tick too soon or too late (``mean`` None), or one of sync ticks whose ``mean`` spacing (s) over the
    window is off the tick (:mod:`virtsensor.daemon.tickrate`): every input with a history recovers as after a
    stale tick, and the grip estimate's filters restart (they too take their rows one tick apart); count and log it
    (the first 3, then every 100th, of each kind)."""
    restart_recovery(self._rules, self._state)
    self._out.grip.restart()
    key = "tick_gaps" if mean is None else "tick_rate_off"
    n = self.counters[key] = self.counters[key] + 1
    if n <= 3 or n % 100 == 0:
        more = {} if mean is None else {"mean_gap_ms": round(mean * 1e3, 3)}
        event(logging.WARNING, "tick_gap" if mean is None else "tick_rate", t=round(t, 6), gap_ms=round(gap * 1e3, 3),
              **more, **{key: n})


def _log_implausible(self: VirtualSensor, t: float) -> None:
    """Count and log the checks that just failed (their names, the values they compared)."""
    plaus, vals, sig = self._plaus, self.inputs.values, self.layout.decoded
    for k, r in enumerate(plaus.rules):
        if plaus.new[k]:
            self.counters["implausible_checks"] += 1
            minus = {} if r.minus < 0 else {"minus": sig[r.minus], "minus_value": vals[r.minus]}
            event(logging.WARNING, "implausible", t=round(t, 6), check=r.name, subject=sig[r.subject],
                  value=vals[r.subject], **minus, references={sig[i]: vals[i] for i in r.refs},
                  implausible_checks=self.counters["implausible_checks"])

def _card_envelope(model: Any) -> Any:
    """The model card's validity envelope (None: the card states none). Raises UserError if malformed."""
    from virtsensor.model.envelope import Envelope

    doc = model.card.get("envelope")
    return None if doc is None else Envelope.from_json(doc, str(getattr(model, "card_path", "model card")))


def _count_envelope(self: VirtualSensor, outside: bool) -> bool:
    """Count a tick outside the envelope, and an exit; set :attr:`VirtualSensor.outside_envelope`; returns
    whether it changed (an exit or a return)."""
    was = self.outside_envelope
    if outside:
        c = self.counters
        c["envelope_ticks"] += 1
        if not was:
            c["envelope_exits"] += 1
    self.outside_envelope = outside
    return outside != was


def _log_envelope(self: VirtualSensor, t: float, outside: bool) -> None:
    """Log an exit from the envelope (``envelope_exit``, with what is outside) or a return (``envelope_return``)."""
    if not outside:
        event(logging.INFO, "envelope_return", t=round(t, 6), envelope_ticks=self.counters["envelope_ticks"])
        return
    vals = dict(zip(self.layout.decoded, (float(v) for v in self.inputs.values), strict=True))
    event(logging.WARNING, "envelope_exit", t=round(t, 6), outside=self.envelope.reasons(vals),
          envelope_exits=self.counters["envelope_exits"])


def _log_change(self: VirtualSensor, t: float, statuses: tuple[int, ...], bitmap: int, in_status: int) -> None:
    """Count a status change; log it with its causes."""
    self.counters["status_changes"] += 1
    if not log.isEnabledFor(logging.INFO):
        return
    lay, st = self.layout, self._state
    order = self.inputs.order.in_order
    event(logging.INFO, "status_change", t=round(t, 6),
          **{w.estimate.lower(): STATUS_NAMES[s] for w, s in zip(lay.wheels, statuses, strict=True)},
          inputs=STATUS_NAMES[in_status], input_bitmap=f"0x{bitmap:02X}",
          bad_inputs=[s for i, s in enumerate(lay.decoded) if st.bad[i]],
          stale_inputs=[s for i, s in enumerate(lay.decoded) if st.stale[i]],
          e2e_error_messages=[m for j, m in enumerate(lay.input_messages) if self._msg_err[j]],
          implausible_checks=[r.name for k, r in enumerate(self._plaus.rules) if self._plaus.failing[k]],
          out_of_order_messages=[m for j, m in enumerate(lay.input_messages) if not order[j]],
          missing_messages=[m for m, b in lay.bitmap_bits.items() if not bitmap >> b & 1])
