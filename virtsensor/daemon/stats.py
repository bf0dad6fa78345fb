"""Rings of the daemon's per-tick timings, read by :meth:`VirtualSensor.stats` and by ``virtsensor bench``."""

from __future__ import annotations

from array import array
from typing import Any

import numpy as np

__all__ = ["TickStats"]


class TickStats:
    """Preallocated rings (``size`` entries, the newest overwrite the oldest) of, per tick: the latency (us,
    tick start -> SAT_FRONT handed to the bus) and the compute time (us, tick start -> SAT_FRONT encoded, no
    bus I/O); per free-running wake-up: its lateness against the deadline (us).

    Attributes:
        ticks: ticks recorded so far. wakes: wake-ups recorded so far.
    """

    def __init__(self, size: int = 8192) -> None:
        # stdlib arrays: a store per tick is one small C call (a numpy item store costs several times more
        # on caches gone cold between 20 Hz ticks); the readers view them as numpy arrays
        self._lat = array("d", bytes(8 * size))
        self._cmp = array("d", bytes(8 * size))
        self._jit = array("d", bytes(8 * size))
        self._size = size
        self.ticks = 0
        self.wakes = 0

    def record_tick(self, latency_us: float, compute_us: float) -> None:
        k = self.ticks
        i = k % self._size
        self._lat[i] = latency_us
        self._cmp[i] = compute_us
        self.ticks = k + 1

    def record_wake(self, late_us: float) -> None:
        j = self.wakes
        self._jit[j % self._size] = late_us
        self.wakes = j + 1

    @staticmethod
    def _window(ring: array, start: int, stop: int) -> np.ndarray:
        size = len(ring)
        start = max(start, stop - size, 0)
        return np.array([ring[i % size] for i in range(start, stop)], dtype=float)

    def compute_us(self, start: int = 0) -> np.ndarray:
        """Compute times (us) of ticks ``start``.. (those still in the ring), oldest first (a copy)."""
        return self._window(self._cmp, start, self.ticks)

    def latency_us(self, start: int = 0) -> np.ndarray:
        """Latencies (us) of ticks ``start``.. still in the ring, oldest first (a copy)."""
        return self._window(self._lat, start, self.ticks)

    def wake_late_us(self, start: int = 0) -> np.ndarray:
        """Wake-up lateness (us) of wake-ups ``start``.. still in the ring, oldest first (a copy)."""
        return self._window(self._jit, start, self.wakes)

    def summary(self) -> dict[str, float]:
        """p50/p99/max of the latencies, p50/p99 of the compute times and wake-up lateness in the rings."""
        out: dict[str, Any] = {}
        n = min(self.ticks, self._size)
        if n:
            lat, cmp_ = np.frombuffer(self._lat, count=n), np.frombuffer(self._cmp, count=n)
            out.update(latency_p50_us=float(np.percentile(lat, 50)), latency_p99_us=float(np.percentile(lat, 99)),
                       latency_max_us=float(lat.max()), compute_p50_us=float(np.percentile(cmp_, 50)),
                       compute_p99_us=float(np.percentile(cmp_, 99)))
        m = min(self.wakes, self._size)
        if m:
            jit = np.frombuffer(self._jit, count=m)
            out.update(wake_late_p50_us=float(np.percentile(jit, 50)), wake_late_p99_us=float(np.percentile(jit, 99)),
                       wake_late_max_us=float(jit.max()))
        return out
