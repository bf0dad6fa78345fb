"""The ticks' spacing, judged against the one tick the features are built on (``TABLE_TICK_S``, 50 ms).

The features' rates and lags, the grip filters and the plausibility checks' per-tick steps all take the rows
they read as one tick apart. A tick that comes too soon or too late after the one before it
(:data:`MIN_TICK_GAP_S`, :data:`MAX_TICK_GAP_S`: half a tick early or late) breaks that for the rows around
it; sync frames that come at another rate (a sync id whose cycle times ``sync_every`` is not 50 ms, a gateway
that forwards them every 40 ms) break it for every row, although each gap on its own looks like a tick. So, in
sync mode (free-running, the daemon's deadlines keep the rate), the latest :data:`WINDOW` ticks (judged once
:data:`MIN_GAPS` gaps are known) must span their number of ticks to within :data:`RATE_TOLERANCE`: a sync frame's
jitter counts only at the window's two ends (+-4 ms: 0.8 % of a full window), one step of its time base once
(20 ms: 2 %), while 48 ms ticks (4 % fast) fail by the 10th gap. A gap too short is kept in the window (a sync twice
as fast as the tick fails both ways); one too long starts a new window (the gap itself is the failure, and the
ticks after it are regular). Either failure is a gap in the inputs' histories for the daemon
(:func:`virtsensor.daemon.validity.restart_recovery`): no estimate is VALID until the ticks are regular again and
the histories hold rows of regular ticks only.
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
#: Ticks whose span is judged (1 s at 20 Hz).
WINDOW = 20
#: Gaps known before the span is judged.
MIN_GAPS = 10
#: The largest relative error of the ticks' span (a sync source's clock errs by parts per million; its jitter and a
#: step of its time base move the span by a few ms; a sync 4 % fast or slow is out by the 10th gap).
RATE_TOLERANCE = 0.03


class TickRate:
    """The latest :data:`WINDOW` tick times (a preallocated ring) and the verdict on each new one (no allocation)."""

    __slots__ = ("_k", "_n", "_times", "mean_gap_s")

    def __init__(self) -> None:
        self._times = [0.0] * WINDOW
        self._k = 0  # where the next time goes
        self._n = 0  # times held since the latest restart
        #: the mean spacing (s) of the latest judged window (nan before one is)
        self.mean_gap_s = float("nan")

    def restart(self, t: float) -> None:
        """Forget the ticks before ``t`` (s), the first of a new window (after a gap too long, or the first tick)."""
        self._n = self._k = 0
        self._add(t)

    def regular(self, t: float) -> bool:
        """Add the tick at ``t`` (s, not later than :data:`MAX_TICK_GAP_S` after the previous one); False when the
        latest ticks span their number of ticks off by more than :data:`RATE_TOLERANCE` (``mean_gap_s`` tells
        their mean spacing)."""
        held = self._n if self._n < WINDOW else WINDOW  # (gaps from the oldest time held to t)
        oldest = self._times[self._k] if self._n >= WINDOW else self._times[0]
        self._add(t)
        if held < MIN_GAPS:
            return True
        self.mean_gap_s = mean = (t - oldest) / held
        return abs(mean - TABLE_TICK_S) <= RATE_TOLERANCE * TABLE_TICK_S

    def _add(self, t: float) -> None:
        self._times[self._k] = t
        self._k = (self._k + 1) % WINDOW
        self._n += 1
