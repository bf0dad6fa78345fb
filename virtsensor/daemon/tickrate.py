"""The ticks' spacing, judged against the one tick the features are built on (``TABLE_TICK_S``, 50 ms).

The features' rates and lags, the grip filters and the plausibility checks' per-tick steps all take the rows
they read as one tick apart. A tick that comes too soon or too late after the one before it
(:data:`MIN_TICK_GAP_S`, :data:`MAX_TICK_GAP_S`: half a tick early or late) breaks that for the rows around
it; sync frames that come at another rate (a sync id whose cycle times ``sync_every`` is not 50 ms, a gateway
that forwards them every 40 ms) break it for every row, although each gap on its own looks like a tick. So, in
sync mode (free-running, the daemon's deadlines keep the rate), the median of the latest :data:`WINDOW` gaps
(judged once :data:`MIN_GAPS` are known) must lie within :data:`RATE_TOLERANCE` of the tick: 48 ms ticks (4 %
fast) fail by the 10th, while a sync frame's jitter, or one step of its time base, moves single gaps and not
their median. A gap too short is kept in the window (a sync twice as fast as the tick fails both ways); one too
long starts a new window (the gap itself is the failure, and the ticks after it are regular). Either failure is
a gap in the inputs' histories for the daemon (:func:`virtsensor.daemon.validity.restart_recovery`): no estimate
is VALID until the ticks are regular again and the histories hold rows of regular ticks only.
"""

from __future__ import annotations

from virtsensor.signals import TABLE_TICK_S

__all__ = ["MAX_TICK_GAP_S", "MIN_GAPS", "MIN_TICK_GAP_S", "RATE_TOLERANCE", "WINDOW", "TickRate"]

#: The longest time between two ticks (s) over which the feature history still holds rows one tick apart: half a
#: tick late at most. After a longer gap (a skipped deadline, lost sync frames, a stalled thread) the features
#: would read rows from before it as if 50 ms old.
MAX_TICK_GAP_S = 1.5 * TABLE_TICK_S
#: The shortest (s): half a tick early at most (a tick time that does not advance is one too).
MIN_TICK_GAP_S = 0.5 * TABLE_TICK_S
#: Gaps whose median is judged (1 s at 20 Hz).
WINDOW = 20
#: Gaps known before their median is judged.
MIN_GAPS = 10
#: The largest relative error of the median gap (1.5 ms: a sync source's jitter moves the median of 20 gaps far
#: less; a 4 % fast one is out).
RATE_TOLERANCE = 0.03


class TickRate:
    """The latest :data:`WINDOW` gaps between ticks (a preallocated ring) and the verdict on each new one."""

    __slots__ = ("_gaps", "_k", "_n", "_sorted", "median_gap_s")

    def __init__(self) -> None:
        self._gaps = [0.0] * WINDOW
        self._sorted = [0.0] * WINDOW  # (sorted in place: once the ring is full, the tick allocates nothing)
        self._k = 0  # where the next gap goes
        self._n = 0  # gaps held since the latest restart
        #: the median gap (s) of the latest judged window (nan before one is)
        self.median_gap_s = float("nan")

    def restart(self) -> None:
        """Forget the gaps so far (after a gap too long, or at the first tick)."""
        self._n = self._k = 0

    def regular(self, gap: float) -> bool:
        """Add a ``gap`` (s, not longer than :data:`MAX_TICK_GAP_S`); False when the median of the latest gaps
        is off the tick by more than :data:`RATE_TOLERANCE` (``median_gap_s`` tells it)."""
        self._gaps[self._k] = gap
        self._k = (self._k + 1) % WINDOW
        self._n += 1
        n = self._n if self._n < WINDOW else WINDOW
        if n < MIN_GAPS:
            return True
        if n < WINDOW:  # (the ring's first n slots hold its gaps until it wraps: a new list for the first second)
            part = sorted(self._gaps[:n])
        else:
            part = self._sorted
            part[:] = self._gaps
            part.sort()
        mid = n // 2
        self.median_gap_s = med = part[mid] if n % 2 else 0.5 * (part[mid - 1] + part[mid])
        return abs(med - TABLE_TICK_S) <= RATE_TOLERANCE * TABLE_TICK_S
