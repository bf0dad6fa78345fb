"""Play CAN frames (a log file or in-memory frames) onto any python-can bus with their original timing.

Timing (``rate`` > 0): frame ``k`` is due at the absolute deadline
``t_send_k = t_start + (ts_k - ts_0) / rate`` on the monotonic
``time.perf_counter`` clock; the player sleeps until ``SPIN_S`` before the
deadline, then busy-spins on the clock (for less than the interpreter's
GIL switch interval, so other threads are not starved) until it. Deadlines
never depend on when earlier frames actually went out, so errors never
accumulate; a late frame is sent at once. With ``loop`` the next pass starts
one mean frame interval after the last frame of the previous pass, again on
the same absolute time line. ``rate=None``/``"max"`` sends as fast as the bus
accepts.

A log file is read through once before its first frame is sent
(:func:`check_log`: a frame at a time, so memory does not grow with the log):
a log that is bad anywhere (a garbage line in the middle, a cut ``.gz``) is
refused with nothing sent, never after part of it went onto the bus.

Frames are sent unchanged (including those not in the DBC, which are only
counted). The timing error of a frame is ``perf_counter()`` just before
``bus.send`` minus its deadline.
"""

from __future__ import annotations

import gc
import math
import os
import sys
import time
from array import array
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import interrupt
from virtsensor.canbus.codec import CanMatrix
from virtsensor.errors import UserError

__all__ = ["SPIN_S", "CheckedLog", "ReplaySummary", "check_log", "replay", "parse_rate", "open_bus",
           "simulated_frames"]

#: Sleep until this long before a deadline, then spin (s).
SPIN_S = 0.0015
#: Keep at most this many timing errors for the statistics.
_MAX_ERRORS = 5_000_000


@dataclass
class ReplaySummary:
    """Outcome of :func:`replay`.

    Attributes:
        frames_sent: frames put on the bus (all passes).
        unknown_frames: of those, frames whose id is not in the DBC (passed through).
        duration_s: wall time from the start to the last send (s).
        loops: passes over the frames completed or started.
        rate: playback rate (None: as fast as possible).
        timing_error_p50_ms, timing_error_p99_ms, timing_error_max_ms: send time
            minus deadline (ms; None in max mode or without frames).
        interrupted: stopped by Ctrl-C or ``stop``.
    """

    frames_sent: int
    unknown_frames: int
    duration_s: float
    loops: int
    rate: float | None
    timing_error_p50_ms: float | None
    timing_error_p99_ms: float | None
    timing_error_max_ms: float | None
    interrupted: bool = False

    @property
    def frames_per_s(self) -> float:
        """Average frames per second of wall time."""
        return self.frames_sent / self.duration_s if self.duration_s > 0 else 0.0

    def format(self) -> str:
        """Human-readable one-paragraph summary."""
        rate = "max" if self.rate is None else f"{self.rate:g}x"
        timing = (
            "n/a (max rate)"
            if self.timing_error_p50_ms is None
            else f"p50 {self.timing_error_p50_ms:.3f} ms, p99 {self.timing_error_p99_ms:.3f} ms, "
            f"max {self.timing_error_max_ms:.3f} ms"
        )
        return (
            f"frames sent: {self.frames_sent} ({self.unknown_frames} unknown, passed through)\n"
            f"duration: {self.duration_s:.3f} s at rate {rate}, {self.loops} pass(es)"
            f"{' (interrupted)' if self.interrupted else ''}\n"
            f"frames per second: {self.frames_per_s:.0f}\n"
            f"timing error: {timing}"
        )


def parse_rate(text: str | float | None) -> float | None:
    """``"max"`` -> None (as fast as possible), else a positive float; UserError otherwise."""
    if text is None:
        return None
    if isinstance(text, str) and text.strip().lower() == "max":
        return None
    try:
        r = float(text)
    except (TypeError, ValueError):
        raise UserError(f"--rate: {text!r} is neither a positive number nor 'max'") from None
    if not (r > 0 and math.isfinite(r)):
        if r == math.inf:
            return None
        raise UserError(f"--rate: {text!r} must be > 0 (or 'max')")
    return r


def open_bus(interface: str, channel: str, bitrate: int | None = None, *, fold_notes: bool = True, **kwargs):
    """Open a python-can bus, validating ``interface`` against ``can.interfaces.VALID_INTERFACES``.

    ``fold_notes``: what python-can logs or warns while the bus is opened is held back and, if it cannot be opened,
    folded into the one error line (:func:`_bus_notes`). It switches the process's ``can`` logger and warnings
    filters for that moment, so a caller with other threads running (the daemon's reconnects) passes False.

    Raises:
        UserError: unknown interface (listing the valid ones) or a bus that cannot be opened.
    """
    import can

    valid = sorted(can.interfaces.VALID_INTERFACES)
    if interface not in can.interfaces.VALID_INTERFACES:
        raise UserError(f"--interface: unknown interface {interface!r}; valid: {', '.join(valid)}")
    if bitrate is not None:
        kwargs["bitrate"] = bitrate
    with _bus_notes() if fold_notes else nullcontext(list) as notes:
        try:
            return can.Bus(interface=interface, channel=channel, **kwargs)
        except Exception as exc:  # noqa: BLE001 - interfaces raise CanError, OSError, ImportError, ...
            failure = " ".join(str(exc).split()) or type(exc).__name__
        if fold_notes:
            gc.collect()  # (a half-made bus says at its collection that it was not shut down: part of this failure)
        said = [n for n in notes() if "not properly shut down" not in n and n not in failure]
        why = f" (python-can: {'; '.join(said)})" if said else ""
        raise UserError(f"cannot open {interface} channel {channel!r}: {failure}{why}")


@contextmanager
def _bus_notes() -> Iterator[Callable[[], list[str]]]:
    """While opening a bus: what python-can's interfaces log (WARNING and above) and warn, held back; yields a
    function returning those messages, one line each. When the block ends without an exception (the bus opened),
    they are handed on as they would have been; when it raises (the bus did not open), the caller has folded them
    into its one error line, and they are dropped."""
    import logging
    import warnings

    from virtsensor.heldlog import held_records

    with held_records("can", logging.WARNING) as records, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")

        def notes() -> list[str]:
            texts = [r.getMessage() for r in records] + [str(w.message) for w in caught]
            return [" ".join(t.split()) for t in texts if t.strip()]

        yield notes
    for w in caught:  # (reached only when the bus opened)
        warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    for r in records:
        logging.getLogger(r.name).handle(r)


def simulated_frames(
    manoeuvre: str, *, speed_kmh: float, mu: float, seed: int = 0, overrides: Sequence[str] = (),
    matrix: CanMatrix | None = None,
) -> list:
    """Frames of a simulated manoeuvre (``replay --manoeuvre``): the simulator's sensor
    streams (:func:`sim.api.simulate_streams`) encoded as a car sends them.

    Raises:
        UserError: the simulator package cannot be imported, or the request is invalid (a ``circuit`` needs its
            track, which ``replay`` does not take: simulate it into a log, then replay that).
    """
    from virtsensor.extras import as_user_error

    if manoeuvre == "circuit":
        raise UserError("--manoeuvre circuit needs a track, which replay does not take: simulate it into a log "
                        "(virtsensor simulate circuit --track T --speed S --mu M --out run.blf), then replay run.blf")

    try:
        from sim.api import simulate_streams  # lazy: the runtime never needs the simulator
        from sim.manoeuvres import ManoeuvreError
        from sim.params import ParamError
        from sim.tir import TirError
    except ImportError as exc:
        missing = as_user_error(exc, "replay --manoeuvre") if isinstance(exc, ModuleNotFoundError) else None
        raise missing or UserError(f"the simulator is not available ({exc})") from None
    from virtsensor.recordings.canlog import iter_frames

    try:
        time_s, signals = simulate_streams(manoeuvre, speed_kmh=speed_kmh, mu=mu, seed=seed, overrides=overrides)
    except (ManoeuvreError, ParamError, TirError) as exc:
        raise UserError(str(exc)) from None
    return list(iter_frames(time_s, signals, matrix=matrix))


@dataclass(frozen=True)
class CheckedLog:
    """A CAN log that :func:`check_log` read through whole: every frame readable, ``frames`` of them."""

    path: Path
    frames: int


def check_log(path: str | os.PathLike) -> CheckedLog:
    """Read a CAN log through once, a frame at a time (memory does not grow with the log), so that a bad log is
    refused before anything is sent and a bad line in the middle never leaves part of the log on the bus.

    A recorded silence is replayed as it was (a daemon's timeouts are tested so), but not a log whose frames span
    more than :data:`~virtsensor.frontend.MAX_SPAN_S` (12 h: a frame on another clock, a replay that would wait
    for years).

    Raises:
        UserError: what :func:`virtsensor.recordings.canlog.iter_log` refuses (a missing, unsupported, empty,
            binary, cut, corrupt or gzip-damaged log, or an unparsable frame, naming the file and where), a log
            without frames, or one that spans more than 12 h.
    """
    from virtsensor.frontend import MAX_SPAN_S
    from virtsensor.recordings.canlog import iter_log

    path = Path(path)
    n = 0
    lo, hi = math.inf, -math.inf
    for m in iter_log(path):
        n += 1
        t = float(m.timestamp)
        lo, hi = min(lo, t), max(hi, t)
    if n == 0:
        raise UserError(f"{path}: no CAN frames to replay (an empty log)")
    if not hi - lo <= MAX_SPAN_S:
        raise UserError(f"{path}: its frames span {hi - lo:.3g} s, from {lo:.6f} s to {hi:.6f} s; a replay covers "
                        f"at most {MAX_SPAN_S / 3600:.0f} h (a frame stamped on another clock?)")
    return CheckedLog(path, n)


def _sources(frames_or_path, loop: bool):
    """(factory returning a fresh iterator per pass, total frames per pass or None, label). A log not checked
    yet is checked whole first (:func:`check_log`)."""
    if isinstance(frames_or_path, (str, os.PathLike)):
        frames_or_path = check_log(frames_or_path)
    if isinstance(frames_or_path, CheckedLog):
        from virtsensor.recordings.canlog import iter_log

        log = frames_or_path
        return (lambda: iter_log(log.path)), log.frames, str(log.path)
    if isinstance(frames_or_path, Sequence):
        seq = frames_or_path
    elif loop:
        seq = list(frames_or_path)
    else:
        it = iter(frames_or_path)
        return (lambda: it), None, "frames"
    return (lambda: iter(seq)), len(seq), "frames"


class _NoBar:
    """What replay needs of a progress bar, doing nothing (no tqdm, or no progress asked for)."""

    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def _progress_bar(progress: bool, total: int | None, label: str) -> Any:
    """A tqdm bar on stderr when asked for and tqdm is installed, else a :class:`_NoBar`."""
    if not progress:
        return _NoBar()
    try:
        from tqdm import tqdm
    except ImportError:
        return _NoBar()
    return tqdm(total=total, unit="frame", file=sys.stderr, mininterval=0.5, desc=label, leave=False)


def _checked_rate(rate: float | str | None) -> float | None:
    """``rate`` as a float > 0, or None (as fast as possible); UserError otherwise."""
    rate_f = parse_rate(rate) if isinstance(rate, str) else (None if rate is None else float(rate))
    if rate_f is not None and not (rate_f > 0 and math.isfinite(rate_f)):
        raise UserError(f"rate must be > 0, got {rate!r}")
    return rate_f


@dataclass
class _Pass:
    """One pass over the frames: how many were sent, the stamps of its first and last frame (s)."""

    n: int
    ts0: float | None
    ts_last: float | None


@dataclass
class _Player:
    """The sending state of one :func:`replay` call: counters kept across passes (and up to a Ctrl-C)."""

    bus: Any
    can: Any  # the python-can module (its CanOperationError)
    known: frozenset[int]  # ids of the DBC
    rate_f: float | None
    spin_s: float
    stop: Any  # threading.Event or None
    bar: Any  # tqdm or _NoBar
    clock: Callable[[], float]
    sleep: Callable[[float], None]
    errors: array = field(default_factory=lambda: array("d"))  # send time minus deadline (s)
    sent: int = 0
    unknown: int = 0
    pending: int = 0  # sent frames not yet counted on the bar
    interrupted: bool = False

    def stopped(self) -> bool:
        return self.stop is not None and self.stop.is_set()

    def wait_until(self, deadline: float) -> None:
        """Sleep until ``spin_s`` before ``deadline``, spin up to it, record the timing error."""
        clock = self.clock
        rem = deadline - clock()
        if rem > self.spin_s:
            self.sleep(rem - self.spin_s)
        now = clock()
        while now < deadline:  # spin (holds the GIL for < spin_s, below the switch interval)
            now = clock()
        if len(self.errors) < _MAX_ERRORS:
            self.errors.append(now - deadline)

    def play_pass(self, frames: Iterable, t_pass: float) -> _Pass:
        """Send ``frames``, the first at ``t_pass`` (timed mode); ends early (``interrupted``) when ``stop`` is
        set, checked every 200 frames."""
        ts0 = ts_last = None
        n_pass = 0
        for msg in frames:
            ts = msg.timestamp
            if ts0 is None:
                ts0 = ts
            ts_last = ts
            if self.rate_f is not None:
                self.wait_until(t_pass + (ts - ts0) / self.rate_f)
            _send(self.bus, msg, self.can, self.sent)
            self.sent += 1
            n_pass += 1
            if msg.arbitration_id not in self.known or msg.is_extended_id:
                self.unknown += 1
            self.pending += 1
            if self.pending >= 200:
                self.bar.update(self.pending)
                self.pending = 0
                if self.stopped():
                    self.interrupted = True
                    break
        return _Pass(n_pass, ts0, ts_last)

    def next_pass_start(self, t_pass: float, done: _Pass) -> float:
        """When the pass after ``done`` (started at ``t_pass``) starts: one mean frame interval after its last
        frame on the same time line (timed mode), else now."""
        if self.rate_f is not None and done.ts0 is not None and done.ts_last is not None:
            gap = (done.ts_last - done.ts0) / (done.n - 1) if done.n > 1 else 0.01
            return t_pass + (done.ts_last - done.ts0 + gap) / self.rate_f
        return self.clock()


def _timing_stats(errors: array) -> tuple[float | None, float | None, float | None]:
    """p50, p99 and max of the timing errors (ms); all None when there is none (max rate)."""
    if not errors:
        return None, None, None
    e = np.frombuffer(errors, dtype=np.float64) * 1e3
    return float(np.percentile(e, 50)), float(np.percentile(e, 99)), float(e.max())


def replay(
    frames_or_path: str | os.PathLike | CheckedLog | Iterable,
    bus,
    rate: float | str | None = 1.0,
    loop: bool = False,
    *,
    matrix: CanMatrix | None = None,
    progress: bool = False,
    max_loops: int | None = None,
    stop=None,
    spin_s: float = SPIN_S,
) -> ReplaySummary:
    """Send frames onto ``bus`` with their original timing (or as fast as possible).

    Args:
        frames_or_path: a log file (any format :func:`virtsensor.recordings.canlog.iter_log`
            reads; read through whole by :func:`check_log` before any frame is sent, unless it is
            the :class:`CheckedLog` that :func:`check_log` returned) or python-can ``Message``
            objects in time order.
        bus: an open python-can bus (not shut down here).
        rate: time scale (2.0 = twice as fast); ``None``/``"max"``: no timing.
        loop: start over at the end (until Ctrl-C, ``stop`` or ``max_loops``).
        matrix: CAN matrix used to recognise known ids (default: bundled).
        progress: a progress bar on stderr (tqdm, where installed: it is not part of the base install).
        max_loops: stop after this many passes (with ``loop``).
        stop: optional ``threading.Event``; set it to end the replay.
        spin_s: sleep/spin split before each deadline (s).

    Returns:
        :class:`ReplaySummary`.

    Raises:
        UserError: unreadable or empty log (no frame; nothing is sent), or the bus refusing frames.
    """
    import can

    rate_f = _checked_rate(rate)
    matrix = matrix or CanMatrix.load()
    factory, total, label = _sources(frames_or_path, loop)
    clock = time.perf_counter
    bar = _progress_bar(progress, total if not loop else None, label[-40:])
    player = _Player(bus, can, frozenset(matrix.by_id), rate_f, spin_s, stop, bar, clock, time.sleep)
    passes = 0
    t_start = clock()
    t_pass = t_start
    t_last_send = t_start
    try:
        while True:
            passes += 1
            done = player.play_pass(factory(), t_pass)
            t_last_send = clock()
            if player.interrupted or not loop or done.n == 0:
                break
            if max_loops is not None and passes >= max_loops:
                break
            if player.stopped():
                player.interrupted = True
                break
            t_pass = player.next_pass_start(t_pass, done)
    except KeyboardInterrupt:
        player.interrupted = True
        interrupt.handled()  # (a replay stopped by Ctrl-C reports what it sent)
        t_last_send = clock()
    finally:
        bar.update(player.pending)
        bar.close()
    p50, p99, mx = _timing_stats(player.errors)
    return ReplaySummary(player.sent, player.unknown, t_last_send - t_start, passes, rate_f, p50, p99, mx,
                         player.interrupted)


def _send(bus, msg, can, index: int) -> None:
    """bus.send with a short retry on a full transmit queue (e.g. SocketCAN ENOBUFS at max rate)."""
    for attempt in range(200):
        try:
            bus.send(msg)
            return
        except can.CanOperationError as exc:
            if attempt == 199:
                what = f"the bus refused frame {index} (id 0x{msg.arbitration_id:X})"
                raise UserError(f"{what}: {exc}") from None
            time.sleep(0.0005)
