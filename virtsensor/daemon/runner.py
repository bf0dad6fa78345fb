"""The daemon's threads: start, the tick and receive loops, reconnects, stop on signals, shutdown.

* **Free-running** (default): a *tick thread* sleeps on the stop event to each absolute deadline
  ``t0 + k * TICK_NS`` of ``time.monotonic_ns`` (``SPIN_S`` = 0: no busy-wait; timer slack 1 ns where Linux
  allows it), then drains the bus and ticks (:meth:`VirtualSensor.drain`): no thread wakes per frame. A tick
  that ends after the next deadline is an *overrun*; deadlines more than one period late are skipped (never
  bunched). A *supervisor thread* sleeps until a bus error asks for a reconnect (or a stop).
* **Sync mode**: a *receive thread* owns the bus (``bus.recv(RECV_TIMEOUT_S)`` frame by frame: the frames
  are the clock), and the ticks run inside :meth:`VirtualSensor.process`; it also does the reconnects.

Worker threads block SIGTERM/SIGINT, so the kernel delivers them to the main thread, whose handler (installed
by :meth:`Runner.run`) sets the stop event; every wait is on that event, so a stop is seen at once.
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import sys
import threading
import time
from typing import Any

from virtsensor.daemon.buslink import BusLink
from virtsensor.daemon.jsonlog import event
from virtsensor.daemon.pmqos import CpuLatencyRequest
from virtsensor.signals import TABLE_TICK_S

__all__ = ["TICK_NS", "SPIN_S", "TIMER_SLACK_NS", "RECV_TIMEOUT_S", "Runner", "set_timer_slack"]

#: Tick period (ns): the canonical table's tick.
TICK_NS = round(TABLE_TICK_S * 1e9)
#: Sleep until this long before a deadline, then spin (s). 0: sleep to the deadline. Spinning buys punctuality
#: with CPU: it busy-waits SPIN_S of every tick (``virtsensor bench`` reports it as
#: ``free_running.spin_budget_percent``), whereas a sleep wakes late only by the timer slack plus the
#: scheduler's wake-up latency, which ``virtsensor bench`` measures as ``jitter_us``.
SPIN_S = 0.0
#: Timer slack of the tick thread (ns, Linux ``PR_SET_TIMERSLACK``; the default 50 us lets the kernel wake a
#: sleeper up to 50 us late to batch timers). 1 ns asks for (next to) no such slack.
TIMER_SLACK_NS = 1
#: ``bus.recv`` timeout of the sync-mode receive thread (s): bounds its shutdown time.
RECV_TIMEOUT_S = 0.02


def set_timer_slack(ns: int) -> bool:
    """Best effort: the calling thread's timer slack (Linux ``prctl(PR_SET_TIMERSLACK)``); False elsewhere."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(29, ctypes.c_ulong(ns), 0, 0, 0) == 0  # 29 = PR_SET_TIMERSLACK
    except (OSError, AttributeError):
        return False


class Runner:
    """Threads and lifecycle of one :class:`~virtsensor.daemon.sensor.VirtualSensor` (see the module doc)."""

    def __init__(self, sensor: Any, link: BusLink, stop: threading.Event, *, cpu: int | None, realtime: bool,
                 rt_priority: int, freeze_gc: bool, cpu_latency_us: int | None = None) -> None:
        self._sensor = sensor
        self._link = link
        self._stop = stop
        self.cpu, self.realtime, self.rt_priority = cpu, bool(realtime), int(rt_priority)
        self._freeze_gc = freeze_gc
        #: the PM QoS CPU-latency request held from start to stop (None: not asked for)
        self.cpu_latency = None if cpu_latency_us is None else CpuLatencyRequest(cpu_latency_us)
        self.threads: tuple[threading.Thread, ...] = ()
        self._started = self._stopped = self._frozen = False
        self._signal_ns: int | None = None
        self._signal_name: str | None = None
        self._loop_exit_ns: int | None = None

    def start(self) -> None:
        if self._started:
            raise RuntimeError("VirtualSensor.start() called twice")
        if self._stopped:  # (its bus is shut down and its stop event set: it would run no tick, and say it started)
            raise RuntimeError("VirtualSensor.start() after stop(): a stopped sensor does not start again; build a "
                               "new one")
        self._started = True
        self._tune_os()
        vs = self._sensor
        targets: tuple[tuple[Any, str], ...]
        if vs.sync_id is None:
            targets = ((self._tick_loop, "virtsensor-tick"), (self._supervise_loop, "virtsensor-bus"))
            if self._link.bus is None:
                self._link.needs_reconnect.set()
        else:
            targets = ((self._rx_loop, "virtsensor-rx"),)
        main = threading.current_thread() is threading.main_thread()
        sigs = {signal.SIGTERM, signal.SIGINT}
        if main:  # worker threads block the stop signals, so the kernel delivers them to the main thread
            old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
        try:
            self.threads = tuple(threading.Thread(target=fn, name=name, daemon=True) for fn, name in targets)
            for th in self.threads:
                th.start()
        finally:
            if main:
                signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
        if self._freeze_gc:
            gc.collect()
            gc.freeze()
            self._frozen = True
        lay = vs.layout
        event(logging.INFO, "started", mode=vs.mode, tick_hz=1e9 / TICK_NS, timeout_cycles=vs.timeout_cycles,
              inputs=list(lay.signals), critical=[s for s, c in zip(lay.signals, lay.critical, strict=True) if c],
              check_inputs=list(lay.check_signals),
              grip_inputs=list(lay.grip_signals), input_messages=list(lay.input_messages), model_id=lay.model_id,
              validity_envelope=vs.envelope is not None,
              bus=str(getattr(self._link.bus, "channel_info", self._link.bus)))

    def _tune_os(self) -> None:
        if self.cpu is not None:
            try:
                os.sched_setaffinity(0, {self.cpu})
                event(logging.INFO, "affinity", cpu=self.cpu, ok=True)
            except (OSError, AttributeError, ValueError) as exc:
                event(logging.WARNING, "affinity", cpu=self.cpu, ok=False, error=str(exc))
        if self.realtime:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.rt_priority))
                event(logging.INFO, "realtime", policy="SCHED_FIFO", priority=self.rt_priority, ok=True)
            except (OSError, AttributeError) as exc:
                event(logging.WARNING, "realtime", policy="SCHED_FIFO", priority=self.rt_priority, ok=False,
                      error=str(exc))
        req = self.cpu_latency
        if req is not None:
            if req.acquire():
                event(logging.INFO, "cpu_latency", us=req.us, ok=True)
            else:
                event(logging.WARNING, "cpu_latency", us=req.us, ok=False, error=req.error)

    def _tick_loop(self) -> None:
        set_timer_slack(TIMER_SLACK_NS)
        mono = time.monotonic_ns
        stop = self._stop
        vs = self._sensor
        stats = vs.tick_stats
        period = TICK_NS
        spin = int(SPIN_S * 1e9)
        t0 = mono() + period
        k = 0
        try:
            while True:
                deadline = t0 + k * period
                rem = deadline - mono()
                if rem > spin:  # sleep on the stop event (a stop wakes it at once) to the deadline (- SPIN_S)
                    if stop.wait((rem - spin) * 1e-9):
                        break
                elif stop.is_set():
                    break
                now = mono()
                while now < deadline:  # the SPIN_S margin, if any, or a rare early wake-up
                    now = mono()
                if stop.is_set():
                    break
                stats.record_wake((now - deadline) * 1e-3)
                vs.drain()
                vs._safe_tick(time.monotonic(), now)  # tick time: the drain's end (no input is stamped later)
                k += 1
                end = mono()
                nxt = t0 + k * period
                if end > nxt:  # deadline missed: count it; skip deadlines already a full period gone
                    vs.counters["overruns"] += 1
                    k += (end - nxt) // period
        finally:
            self._loop_exit_ns = mono()

    def _supervise_loop(self) -> None:
        """Free-running: sleep until a bus error asks for a reconnect (or a stop), then reconnect."""
        link, stop = self._link, self._stop
        while True:
            link.needs_reconnect.wait()
            if stop.is_set():
                return
            link.reconnect()

    def _rx_loop(self) -> None:
        stop, link, vs = self._stop, self._link, self._sensor
        try:
            while not stop.is_set():
                bus = link.bus
                if link.needs_reconnect.is_set() or bus is None:
                    link.reconnect()
                    continue
                try:
                    msg = bus.recv(RECV_TIMEOUT_S)
                except Exception as exc:  # noqa: BLE001 - any interface error: count, reconnect
                    if stop.is_set():
                        break
                    link.recv_failed(exc)
                    continue
                if msg is not None:
                    vs.process(msg)
        finally:
            self._loop_exit_ns = time.monotonic_ns()

    def _on_signal(self, signum: int, frame: Any) -> None:
        if self._signal_ns is None:
            self._signal_ns = time.monotonic_ns()
            self._signal_name = signal.Signals(signum).name
        self.request_stop()

    def request_stop(self) -> None:
        self._stop.set()
        self._link.needs_reconnect.set()  # wakes the supervisor, which then sees the stop

    def stop(self, timeout: float = 1.0) -> dict[str, Any]:
        vs = self._sensor
        if self._stopped:
            return vs.stats()
        self._stopped = True
        self.request_stop()
        for th in self.threads:
            th.join(timeout)
        joined_ns = time.monotonic_ns()
        self._link.close()
        if self.cpu_latency is not None:
            self.cpu_latency.release()
        if self._frozen:
            gc.unfreeze()
            self._frozen = False
        st = vs.stats()
        extra: dict[str, Any] = {}
        if self._signal_ns is not None:
            extra["signal"] = self._signal_name
            if self._loop_exit_ns is not None:
                extra["signal_to_loop_exit_ms"] = round(max(self._loop_exit_ns - self._signal_ns, 0) / 1e6, 3)
            extra["signal_to_stopped_ms"] = round((time.monotonic_ns() - self._signal_ns) / 1e6, 3)
            extra["signal_to_joined_ms"] = round((joined_ns - self._signal_ns) / 1e6, 3)
        event(logging.INFO, "shutdown", **extra, **st)
        return st

    def run(self, duration: float | None = None) -> int:
        if self._started or self._stopped:
            self.start()  # (raises: started twice, or a stopped sensor, which does not start again)
        old: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():  # (before start: a signal meanwhile stops it)
            for s in (signal.SIGTERM, signal.SIGINT):
                old[s] = signal.signal(s, self._on_signal)
        rc = 0
        try:
            self.start()
            end = None if duration is None else time.monotonic() + duration
            waiter = self.threads[0]
            while not self._stop.is_set():
                timeout = 0.5 if end is None else min(0.5, end - time.monotonic())
                if timeout <= 0:
                    break
                waiter.join(timeout)  # a signal interrupts this wait; the handler sets the stop event
                if not waiter.is_alive() and not self._stop.is_set():
                    event(logging.ERROR, "fatal", error=f"thread {waiter.name} ended unexpectedly")
                    rc = 1
                    break
        finally:
            self.stop()
            for signum, handler in old.items():
                signal.signal(signum, handler)
        return rc
