"""The daemon's hold on its bus: send with error counting, re-open after errors with back-off, shutdown."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from virtsensor.daemon.jsonlog import event

__all__ = ["BusLink", "shutdown_bus"]


def shutdown_bus(bus: Any) -> None:
    """Shut a bus down (None: nothing to do); a failure is logged, never raised."""
    if bus is None:
        return
    try:
        bus.shutdown()
    except Exception as exc:  # noqa: BLE001
        event(logging.WARNING, "bus_error", where="shutdown", error=f"{type(exc).__name__}: {exc}")


class BusLink:
    """Owns a ``can.BusABC`` (any interface): thread-safe send, error accounting, reconnect.

    Args:
        bus: the open bus (None: open one with ``factory`` first).
        factory: opens a new bus after an error (None: keep retrying the same bus).
        counters: the daemon's counters (``sent``, ``send_errors``, ``unsent``, ``recv_errors``, ``reconnects``,
            ``reconnect_failures`` are written here).
        stop: the daemon's stop event (interrupts the back-off waits).
        backoff_s, backoff_max_s: first and largest wait before re-opening; a reconnect within 5 s of the
            previous one doubles the wait.
    """

    def __init__(self, bus: Any, factory: Callable[[], Any] | None, counters: dict[str, int], stop: threading.Event,
                 backoff_s: float = 0.05, backoff_max_s: float = 2.0) -> None:
        self.bus = bus
        self.lock = threading.Lock()
        self.needs_reconnect = threading.Event()
        self._factory = factory
        self._counters = counters
        self._stop = stop
        self._backoff0, self._backoff_max = float(backoff_s), float(backoff_max_s)
        self._backoff = self._backoff0
        self._last_reconnect_ns = 0

    def send(self, msg: Any) -> None:
        """Send ``msg`` (stamped with the wall clock); a failure is counted, logged (rate-limited) and
        flags a reconnect; without a bus the frame is counted as ``unsent``."""
        with self.lock:
            bus = self.bus
            if bus is None:
                self._counters["unsent"] += 1
                return
            try:
                msg.timestamp = time.time()
                bus.send(msg, timeout=0.005)
                self._counters["sent"] += 1
                return
            except Exception as exc:  # noqa: BLE001 - any interface error: count, reconnect
                self._counters["send_errors"] += 1
                err = exc
        self.needs_reconnect.set()
        n = self._counters["send_errors"]
        if n <= 5 or n % 100 == 0:
            event(logging.WARNING, "bus_error", where="send", error=f"{type(err).__name__}: {err}",
                  send_errors=n, frame_id=f"0x{msg.arbitration_id:X}")

    def recv_failed(self, exc: BaseException) -> None:
        """Count and log a receive error; flag a reconnect."""
        self._counters["recv_errors"] += 1
        event(logging.WARNING, "bus_error", where="recv", error=f"{type(exc).__name__}: {exc}",
              recv_errors=self._counters["recv_errors"])
        self.needs_reconnect.set()

    def reconnect(self) -> None:
        """Close the bus, back off (interruptible by stop), re-open it with the factory (retrying, slower)."""
        c = self._counters
        now = time.monotonic_ns()
        self._backoff = (min(self._backoff * 2, self._backoff_max)
                         if now - self._last_reconnect_ns < 5e9 else self._backoff0)
        if self._factory is not None:
            with self.lock:
                old, self.bus = self.bus, None
            shutdown_bus(old)
        delay = self._backoff
        while not self._stop.is_set():
            if self._stop.wait(delay):
                return
            new = None
            if self._factory is not None:
                try:
                    new = self._factory()
                except Exception as exc:  # noqa: BLE001 - keep trying, slower
                    c["reconnect_failures"] += 1
                    event(logging.WARNING, "reconnect", ok=False, error=f"{type(exc).__name__}: {exc}",
                          delay_s=delay, failures=c["reconnect_failures"])
                    delay = min(delay * 2, self._backoff_max)
                    continue
                with self.lock:
                    self.bus = new
            self.needs_reconnect.clear()
            c["reconnects"] += 1
            self._last_reconnect_ns = time.monotonic_ns()
            if new is not None:
                event(logging.WARNING, "reconnect", ok=True, reopened=True, delay_s=delay, reconnects=c["reconnects"])
            else:  # (no factory: the same bus is tried again; whether it works, its next receive or send tells)
                event(logging.WARNING, "bus_retry", delay_s=delay, reconnects=c["reconnects"],
                      note="no bus factory: the same bus is used again")
            return

    def close(self) -> None:
        """Take the bus away and shut it down."""
        with self.lock:
            bus, self.bus = self.bus, None
        shutdown_bus(bus)
