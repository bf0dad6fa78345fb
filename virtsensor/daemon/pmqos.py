"""A Linux PM QoS CPU-latency request: keep the CPUs out of idle states slower to leave than a bound.

While a process holds ``/dev/cpu_dma_latency`` open with a 32-bit value written to it, the kernel's cpuidle
governor picks no idle state whose exit latency exceeds that many microseconds, on every CPU; closing the file
(or the process ending, however it ends) withdraws the request. It is what real-time test tools (``cyclictest``)
and tuned's ``latency-performance`` profile do.

Why the daemon may ask for it: it sleeps about 50 ms between 20 Hz ticks. In a deep idle state (or, in a KVM
guest, a halted vCPU whose physical core the host gives to others) the core's caches and TLBs lose the daemon's
code and data, so every tick runs cold: both the wake-up latency and the CPU time of each tick grow
(``virtsensor bench`` measures the daemon with and without the request). The price is power: idle cores poll or
stay in shallow states instead of sleeping deeply, and in a VM an idle vCPU keeps its host core busy. Ask for it
on a dedicated ECU or gateway, not on a laptop.

Needs write access to ``/dev/cpu_dma_latency`` (root, or a udev rule for the daemon's group); Linux only.
"""

from __future__ import annotations

import os
import struct
import sys

__all__ = ["DEVICE", "CpuLatencyRequest", "current_limit_us"]

#: the PM QoS CPU-latency device
DEVICE = "/dev/cpu_dma_latency"


class CpuLatencyRequest:
    """One PM QoS CPU-latency request, held from :meth:`acquire` to :meth:`release` (idempotent both).

    Attributes:
        us: the requested bound (microseconds, >= 0; 0: no idle state with any exit latency).
        held: whether the request is in force. error: why :meth:`acquire` failed (None when held or not tried).
    """

    def __init__(self, us: int) -> None:
        if isinstance(us, bool) or not isinstance(us, int) or not 0 <= us <= 2_000_000_000:
            raise ValueError(f"CPU latency bound must be an integer of microseconds in 0..2e9, got {us!r}")
        self.us = us
        self._fd: int | None = None
        self.error: str | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> bool:
        """Open the device and write the bound; True when the request is in force (else :attr:`error` says why)."""
        if self._fd is not None:
            return True
        if not sys.platform.startswith("linux"):
            self.error = f"PM QoS ({DEVICE}) is Linux only"
            return False
        try:
            fd = os.open(DEVICE, os.O_WRONLY | os.O_CLOEXEC)
        except OSError as exc:
            self.error = f"{DEVICE}: {exc.strerror or exc}"
            return False
        try:
            os.write(fd, struct.pack("=i", self.us))
        except OSError as exc:
            os.close(fd)
            self.error = f"{DEVICE}: {exc.strerror or exc}"
            return False
        self._fd, self.error = fd, None
        return True

    def release(self) -> None:
        """Withdraw the request (close the device)."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)


def current_limit_us() -> int | None:
    """The CPU-latency bound now in force on this machine (the strictest request, microseconds), or None where
    the device cannot be read."""
    try:
        with open(DEVICE, "rb") as f:
            raw = f.read(4)
    except OSError:
        return None
    return struct.unpack("=i", raw)[0] if len(raw) == 4 else None
