"""The feature front-end shared by the trainer (offline) and the runtime (online).

Semantics, identical in both paths: the value of a signal at tick time ``t``
is the latest *usable* value received at or before ``t`` (sample and hold),
where

* usable = the frame's E2E status is OK or OKSOMELOST and the value
  is neither SNA nor outside the catalogue range (see
  :class:`virtsensor.canbus.codec.DecodedFrame`);
* "at or before" compares the frame timestamp with ``t + TIME_TOLERANCE_S``
  (1 us: the resolution of text log formats), with ties in timestamp resolved
  in favour of the frame that comes later in the input (stable time order);
* where a largest age is given for a signal (``max_age`` of :func:`to_table`; the CAN
  log reader gives each signal its message's timeout, as the daemon judges freshness),
  a value older than that at ``t`` is not held: the tick is NaN (stale).

Times are seconds in the clock of the frame timestamps. Values are SI in the
catalogue's units.

One recording is one run, and its time says so (:func:`time_problem`; a
:class:`~virtsensor.errors.UserError` otherwise, before any tick grid is built):

* no two consecutive frames (in input order) are more than :data:`MAX_GAP_S`
  (60 s) apart, forward or back. The matrix's slowest message is sent every
  second and the others every 10 to 50 ms, so a minute without a frame means
  the bus was off (the car parked between two drives) or the logger's clock
  jumped (one frame stamped in Unix time among frames counted from 0); sample
  and hold would fill the silence with 1200 ticks of stale values, and a clock
  jump with billions of them;
* in a log file, no frame is stamped more than :data:`MAX_BACK_S` (one 20 Hz
  tick) before the frame before it (the file readers check it:
  :func:`virtsensor.recordings.canlog.iter_log`). A logger that merges its
  channels may put frames a little out of time order, and the tables replay
  them in time order; a clock set back by more (an NTP step) or two logs
  joined end to end would interleave two stretches of driving tick by tick,
  and a replay would send the rest of the log late, in one burst;
* the first and the last frame are at most :data:`MAX_SPAN_S` (12 h) apart:
  longer than any one drive a logger records into one file, and at 20 Hz
  864,000 ticks, about 7 MB a column (100 MB for the canonical table's 15),
  far less than the some 25 million frames of 12 h take to read anyway.
  :func:`tick_times` refuses a longer grid whoever asks for it.

Two implementations:

* :class:`SampleHoldStore` — the online store, updated per frame and sampled
  per tick (:meth:`SampleHoldStore.sample`); the daemon keeps the same
  sample-and-hold semantics in plain lists written by its generated per-message
  receivers (:func:`virtsensor.canbus.codec.compile_receiver`; ``tests/test_fastdecode.py``
  checks those against a reference receive path built on ``CanMatrix.decode``,
  not against this class);
* :func:`to_table` — replays a whole log; the default vectorised path uses one
  ``np.searchsorted`` per signal, ``online=True`` drives the store frame by
  frame (the tests check both agree exactly).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import NamedTuple

import numpy as np

from virtsensor.canbus.e2e import USABLE
from virtsensor.errors import UserError

__all__ = [
    "MAX_BACK_S",
    "MAX_GAP_S",
    "MAX_SPAN_S",
    "TIME_TOLERANCE_S",
    "Collected",
    "SampleHoldStore",
    "TableBuild",
    "collect",
    "largest_step",
    "table_from_collected",
    "tick_times",
    "time_problem",
    "to_table",
]

#: Frames up to this much after a tick still count as "at" the tick (s).
TIME_TOLERANCE_S = 1e-6
#: The longest two consecutive frames of one run may lie apart, forward or back (s; see the module docstring).
MAX_GAP_S = 60.0
#: The longest one run may last, first frame to last (s): 12 h (see the module docstring).
MAX_SPAN_S = 12 * 3600.0
#: The most a log file's frame may be stamped before the one before it (s): one 20 Hz tick (see the module
#: docstring).
MAX_BACK_S = 0.05


class SampleHoldStore:
    """Latest usable value per catalogue signal with its receive time.

    Args:
        signals: the catalogue names to hold, in the order :meth:`sample` returns them.
    """

    __slots__ = ("signals", "_index", "_values", "_times", "updates")

    def __init__(self, signals: Sequence[str]) -> None:
        self.signals = tuple(signals)
        if len(set(self.signals)) != len(self.signals):
            raise ValueError("duplicate signal names in the front-end order")
        self._index = {n: i for i, n in enumerate(self.signals)}
        self._values = np.full(len(self.signals), np.nan)
        self._times = np.full(len(self.signals), -np.inf)
        #: number of values stored so far
        self.updates = 0

    def reset(self) -> None:
        """Forget everything (values nan, times -inf)."""
        self._values.fill(np.nan)
        self._times.fill(-np.inf)
        self.updates = 0

    def update(self, frame) -> int:
        """Store the values of a decoded frame if it is usable; returns how many were stored."""
        if frame is None or frame.status not in USABLE:
            return 0
        idx = self._index
        vals, times, t = self._values, self._times, frame.timestamp
        n = 0
        for name, v in frame.values.items():
            i = idx.get(name)
            if i is not None:
                vals[i] = v
                times[i] = t
                n += 1
        self.updates += n
        return n

    def put(self, name: str, value: float, t: float) -> None:
        """Store one value of signal ``name`` received at ``t`` (s)."""
        i = self._index[name]
        self._values[i] = value
        self._times[i] = t
        self.updates += 1

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(values, ages) at time ``t`` in the store's signal order.

        ``ages[i] = t - receive time`` in seconds (inf if never received;
        negative if a value newer than ``t`` was already stored). Both are new
        arrays.
        """
        return self._values.copy(), t - self._times

    @property
    def complete(self) -> bool:
        """Every signal has been received at least once."""
        return bool(np.isfinite(self._times).all())


class TableBuild(NamedTuple):
    """Result of :func:`to_table`.

    Attributes:
        table: ``time_s`` (tick times, s) then one SI array per requested signal.
        dropped_ticks: ticks at the start removed because some signal had not been seen yet.
        ticks: total ticks on the grid (kept + dropped).
    """

    table: dict[str, np.ndarray]
    dropped_ticks: int
    ticks: int


def tick_times(t_first: float, t_last: float, rate_hz: float, t0: float | None = None) -> np.ndarray:
    """Tick grid ``t0 + k / rate_hz`` for ``k = 0..`` while ``<= t_last`` (s).

    Default ``t0``: the last multiple of ``1/rate_hz`` at or before ``t_first``.

    Raises:
        UserError: a grid longer than one run (:data:`MAX_SPAN_S`), or not finite: it is never
            allocated. (Readers refuse such a recording first, naming it: :func:`time_problem`.)
    """
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
    if t0 is None:
        t0 = np.floor(t_first * rate_hz + 1e-9) / rate_hz
    span = t_last - t0
    if not span <= MAX_SPAN_S + 1.0 / rate_hz:
        raise UserError(f"a tick grid from {t0:.6f} s to {t_last:.6f} s spans {span:.6g} s, longer than one run "
                        f"({MAX_SPAN_S / 3600:g} h)")
    n = int(np.floor(span * rate_hz + 1e-9)) + 1
    return t0 + np.arange(max(n, 0)) / rate_hz


def time_problem(t_first: float, t_last: float, jump: tuple[float, float], what: str = "frames") -> str | None:
    """Why a recording's time cannot be one run's, or None (see the module docstring).

    Args:
        t_first, t_last: its first and last timestamp (s).
        jump: the two consecutive timestamps (s) furthest apart, in input order (NaN: fewer than two).
        what: what the timestamps stamp, for the message ("frames", "samples").

    Returns:
        What is wrong and where (the time of the jump, or the span), to follow the file's name.
    """
    a, b = jump
    if abs(b - a) > MAX_GAP_S:
        return (f"its time jumps {'forward' if b > a else 'back'} by {abs(b - a):.6g} s, from {a:.6f} s to "
                f"{b:.6f} s, between consecutive {what} (one run has no gap over {MAX_GAP_S:g} s: two runs, or a "
                f"clock that jumped?)")
    span = t_last - t_first
    if not span <= MAX_SPAN_S:
        return (f"its {what} span {span:.6g} s (from {t_first:.6f} s to {t_last:.6f} s); one run lasts at most "
                f"{MAX_SPAN_S / 3600:g} h")
    return None


def largest_step(ts: np.ndarray) -> tuple[float, float]:
    """The two consecutive values of ``ts`` furthest apart, in its order (NaN, NaN for fewer than two)."""
    if ts.size < 2:
        return math.nan, math.nan
    i = int(np.argmax(np.abs(np.diff(ts))))
    return float(ts[i]), float(ts[i + 1])


class Collected(NamedTuple):
    """Usable values per signal from a pass over the frames (see :func:`collect`).

    Attributes:
        times, values: signal -> lists of receive times (s) and SI values, in input order.
        t_first, t_last: first and last frame timestamps over *all* frames (inf/-inf if none).
        frames: number of frames seen.
        jump: the timestamps of the two consecutive frames (in input order, over all frames) furthest
            apart, forward or back (NaN, NaN: fewer than two frames); see :func:`time_problem`.
    """

    times: dict[str, list[float]]
    values: dict[str, list[float]]
    t_first: float
    t_last: float
    frames: int
    jump: tuple[float, float] = (math.nan, math.nan)


def collect(frames: Iterable, signals: Sequence[str]) -> Collected:
    """One streaming pass over decoded frames keeping the usable values of ``signals`` (and, in constant
    memory, the first and last timestamps and the largest step between consecutive frames:
    :attr:`Collected.jump`)."""
    wanted = set(signals)
    times: dict[str, list[float]] = {s: [] for s in signals}
    values: dict[str, list[float]] = {s: [] for s in signals}
    t_first, t_last = math.inf, -math.inf
    prev, step, jump = math.nan, -1.0, (math.nan, math.nan)
    n = 0
    for f in frames:
        if f is None:
            continue
        n += 1
        t = f.timestamp
        if t < t_first:
            t_first = t
        if t > t_last:
            t_last = t
        d = abs(t - prev)  # (nan at the first frame: never the largest)
        if d > step:
            step, jump = d, (prev, t)
        prev = t
        if f.status not in USABLE:
            continue
        for name, v in f.values.items():
            if name in wanted:
                times[name].append(t)
                values[name].append(v)
    return Collected(times, values, float(t_first), float(t_last), n, jump)


def _oldest(signals: Sequence[str], max_age: Mapping[str, float] | None) -> np.ndarray:
    """Per signal the oldest age (s) a tick may hold (``max_age``, plus :data:`TIME_TOLERANCE_S`); inf: no limit."""
    ages = max_age or {}
    return np.array([ages.get(s, math.inf) + TIME_TOLERANCE_S for s in signals], dtype=np.float64)


def table_from_collected(
    col: Collected, signals: Sequence[str], rate_hz: float = 20.0, t0: float | None = None, *, source: str = "frames",
    max_age: Mapping[str, float] | None = None,
) -> TableBuild:
    """The vectorised half of :func:`to_table`: one ``np.searchsorted`` per signal (``max_age``: see there).

    Raises:
        UserError: ``source`` (a file's name, in the message) is not one run's time (:func:`time_problem`).
    """
    signals = tuple(signals)
    if not np.isfinite(col.t_first):
        return _empty(signals, 0)
    why = time_problem(col.t_first, col.t_last, col.jump)
    if why is not None:
        raise UserError(f"{source}: {why}")
    ticks = tick_times(col.t_first, col.t_last, rate_hz, t0)
    probe = ticks + TIME_TOLERANCE_S
    cols: dict[str, np.ndarray] = {}
    first_ok = 0
    for s, oldest in zip(signals, _oldest(signals, max_age), strict=True):
        t = np.asarray(col.times[s], dtype=np.float64)
        v = np.asarray(col.values[s], dtype=np.float64)
        if t.size == 0:
            return _empty(signals, len(ticks))
        order = np.argsort(t, kind="stable")
        t, v = t[order], v[order]
        idx = np.searchsorted(t, probe, side="right") - 1
        first_ok = max(first_ok, int(np.searchsorted(idx, 0, side="left")))
        at = np.maximum(idx, 0)
        cols[s] = v[at] if oldest == math.inf else np.where(ticks - t[at] > oldest, np.nan, v[at])
    table = {"time_s": ticks[first_ok:]}
    for s in signals:
        table[s] = cols[s][first_ok:]
    return TableBuild(table, first_ok, len(ticks))


def to_table(
    frames: Iterable,
    signals: Sequence[str],
    rate_hz: float = 20.0,
    t0: float | None = None,
    *,
    online: bool = False,
    source: str = "frames",
    max_age: Mapping[str, float] | None = None,
) -> TableBuild:
    """Sample-and-hold table of decoded frames on the tick grid ``t0 + k / rate_hz``.

    Args:
        frames: :class:`~virtsensor.canbus.codec.DecodedFrame` objects (None entries ignored),
            in any order (they are replayed in stable time order) as long as no two consecutive
            ones are more than :data:`MAX_GAP_S` apart.
        signals: catalogue names of the columns.
        rate_hz: tick rate (Hz); the canonical table is 20 Hz.
        t0: first tick (s, the frames' clock); default: see :func:`tick_times`.
            Ticks run up to the last frame's timestamp.
        online: build through :class:`SampleHoldStore` frame by frame (the
            daemon's path) instead of the vectorised ``searchsorted`` path.
        source: what the frames come from, for messages.
        max_age: signal -> the oldest value (s) a tick may hold, the daemon's freshness rule (its message's
            timeout, :data:`~virtsensor.signals.INPUT_TIMEOUT_CYCLES` times its cycle time, as
            :func:`~virtsensor.recordings.canlog.decode_recording` passes it):
            a tick whose latest usable value is older is NaN (stale), as the daemon gives no estimate from it.
            Signals not named, or None: held however old.

    Returns:
        :class:`TableBuild`; leading ticks where some signal has not been seen
        are dropped and counted.

    Raises:
        UserError: the frames' time is not one run's (:func:`time_problem`).
    """
    signals = tuple(signals)
    if online:
        return _to_table_online(list(frames), signals, rate_hz, t0, source, max_age)
    return table_from_collected(collect(frames, signals), signals, rate_hz, t0, source=source, max_age=max_age)


def _empty(signals: Sequence[str], n_ticks: int) -> TableBuild:
    table = {"time_s": np.empty(0)}
    for s in signals:
        table[s] = np.empty(0)
    return TableBuild(table, n_ticks, n_ticks)


def _to_table_online(
    frames: list, signals: tuple[str, ...], rate_hz: float, t0: float | None, source: str,
    max_age: Mapping[str, float] | None = None,
) -> TableBuild:
    frames = [f for f in frames if f is not None]
    if not frames:
        return _empty(signals, 0)
    stamps = np.array([f.timestamp for f in frames], dtype=np.float64)
    order = np.argsort(stamps, kind="stable")
    t_first, t_last = frames[order[0]].timestamp, frames[order[-1]].timestamp
    why = time_problem(t_first, t_last, largest_step(stamps))
    if why is not None:
        raise UserError(f"{source}: {why}")
    ticks = tick_times(t_first, t_last, rate_hz, t0)
    store = SampleHoldStore(signals)
    oldest = _oldest(signals, max_age)
    rows: list[np.ndarray] = []
    kept_ticks: list[float] = []
    dropped = 0
    j, n = 0, len(order)
    for tk in ticks:
        limit = tk + TIME_TOLERANCE_S
        while j < n and frames[order[j]].timestamp <= limit:
            store.update(frames[order[j]])
            j += 1
        if not rows and not store.complete:
            dropped += 1
            continue
        vals, ages = store.sample(tk)
        vals[ages > oldest] = np.nan  # (stale: older than its message's timeout)
        rows.append(vals)
        kept_ticks.append(tk)
    if not rows:
        return _empty(signals, len(ticks))
    mat = np.vstack(rows)
    table = {"time_s": np.asarray(kept_ticks, dtype=np.float64)}
    for i, s in enumerate(signals):
        table[s] = mat[:, i].copy()
    return TableBuild(table, dropped, len(ticks))
