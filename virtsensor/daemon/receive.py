"""The daemon's receive path: frame accounting, the generated per-message receivers, frame order, and the
mapping of interface timestamps onto the daemon's clock when frames are drained at the tick.

The sample-and-hold store (the semantics of :class:`~virtsensor.frontend.SampleHoldStore`) is a set of
plain lists written per frame by receivers generated from the DBC (:func:`virtsensor.canbus.codec.
compile_receiver`: DLC, CRC, E2E check, decode; a list item store avoids numpy's per-scalar conversion).
Everything here runs in one thread (the daemon's tick thread, or its receive thread in sync mode).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

from virtsensor.canbus.codec import CanMatrix, compile_receiver
from virtsensor.daemon.jsonlog import event
from virtsensor.daemon.layout import InputLayout
from virtsensor.daemon.validity import FrameOrder

__all__ = ["CONFIRM_S", "ClockMap", "ReceivePath", "StageHook", "polling_read"]

#: ``hook(stage, fn) -> fn``: wraps one of the daemon's stage callables (e.g. to time it); see VirtualSensor.
StageHook = Callable[[str, Callable[..., Any]], Callable[..., Any]]

_INF = math.inf


def polling_read(bus: Any) -> Callable[[float], tuple[Any, bool]]:
    """``read(timeout) -> (Message | None, filtered)`` for ``bus``, None only when nothing is queued.

    When its ``recv`` is python-can's ``BusABC.recv``: its backend hook ``_recv_internal`` itself without a
    software filter (what ``BusABC.recv`` returns for a zero timeout, at about a third less cost per frame);
    with one, the hook's frames that the bus's filters pass (``BusABC.recv`` at a zero timeout would return
    None at the first frame that does not match, leaving the rest queued for a later tick). Else its own
    ``recv`` wrapped into the same shape (``bus`` None: reads nothing)."""
    import can

    if bus is None:
        return _nothing
    internal = getattr(bus, "_recv_internal", None)
    if type(bus).recv is can.BusABC.recv and callable(internal):
        if not getattr(bus, "_filters", None):
            return internal  # type: ignore[no-any-return]
        matches = bus._matches_filters

        def read_filtered(timeout: float) -> tuple[Any, bool]:
            while True:
                msg, done = internal(timeout)
                if msg is None or done or matches(msg):
                    return msg, True

        return read_filtered
    recv = bus.recv

    def read(timeout: float) -> tuple[Any, bool]:
        return recv(timeout), True

    return read


def _count_unstamped(counters: dict[str, int], n: int) -> None:
    """Count drained frames without an interface timestamp; log the first drain that has any."""
    before = counters.get("unstamped_frames", 0)
    if not before:
        event(logging.WARNING, "unstamped_frames", frames=n,
              why="the interface gives no timestamps: frames are aged from the drain that reads them, so a message "
                  "whose E2E timeout is shorter than the tick (the 10 ms ones: 30 ms) fails the gap check at every "
                  "drain; use an interface with timestamps, or sync mode")
    counters["unstamped_frames"] = before + n


def _nothing(timeout: float) -> tuple[Any, bool]:
    return None, True


#: how far apart (s) the smallest ``read_time - timestamp`` of two consecutive drains with frames may be for the
#: clock mapping to count as confirmed (:class:`ClockMap`): live frames are read within a few ms of their
#: arrival at every drain; a backlog read out over several drains is not
CONFIRM_S = 0.025
#: How far below the offset in force (s) one frame's bound may pull it within a drain (:meth:`ReceivePath.drain`):
#: a frame stamped further in the future (an interface that stamped one frame wrong) leaves the offset alone
OUTLIER_S = 1.0


class ClockMap:
    """Maps an interface's frame timestamps (s, any clock) onto the daemon's ``time.monotonic`` clock.

    A frame cannot be read before it arrived, so ``read_time - timestamp`` bounds the clock offset from
    above for every frame; the offset is the smallest such bound over the last ``window`` drains that got
    frames (drains without frames leave it alone, so an interface that stalls and then releases a
    backlog has the backlog aged by its own timestamps). A drain's bound is its second smallest where it got
    two stamped frames or more (:meth:`ReceivePath.drain`), so that one frame stamped wrong, seconds ahead,
    does not pull every other frame's time back with it for ``window`` drains (a drain whose only stamped frame
    lies more than :data:`OUTLIER_S` below the offset is not pushed). A time base that steps back is followed
    after ``window`` drains with frames; until then its frames look old (stale); one that steps forward, within
    the drain once two of its frames agree on the new offset (within :data:`CONFIRM_S`). Mapped times are never
    later than the time the frame was read, but for a frame whose bound lies more than :data:`OUTLIER_S` below the
    offset and that no second frame confirms (mapped into the future: refused as future-stamped).

    The first drains cannot tell a backlog queued before the daemon started (frames long old, the sender
    silent since) from live frames: its newest frame would look just arrived. The mapping is *confirmed*
    (:attr:`confirmed`, for good) once two consecutive drains both got frames and their smallest bounds agree
    within :data:`CONFIRM_S`; until then the daemon counts no input fresh. Before any frame it maps nothing and
    is confirmed (frames handled at their read time, without a drain, need no mapping).
    """

    __slots__ = ("offset", "confirmed", "_ring", "_k", "_prev")

    def __init__(self, window: int = 20) -> None:
        if window < 1:
            raise ValueError("window must be >= 1")
        self._ring = [_INF] * window
        self._k = 0
        #: current offset estimate (s; inf before the first frame)
        self.offset = _INF
        #: the offset is confirmed by live frames (see the class doc)
        self.confirmed = True
        self._prev = _INF  # (the smallest bound of the previous drain, inf when it got no frame)

    def push(self, batch_min: float) -> None:
        """Close a drain whose smallest ``read_time - timestamp`` was ``batch_min``."""
        ring = self._ring
        if self.offset == _INF:
            self.confirmed = False  # (the first drain with frames)
        ring[self._k] = batch_min
        self._k = (self._k + 1) % len(ring)
        self.offset = min(ring)
        if not self.confirmed and abs(batch_min - self._prev) <= CONFIRM_S:
            self.confirmed = True
        self._prev = batch_min

    def idle(self) -> None:
        """Close a drain that got no frame (with a timestamp)."""
        self._prev = _INF


class ReceivePath:
    """Frame accounting and decoding into the sample-and-hold lists (one instance per daemon).

    Attributes (lists mutated in place, never rebound; ``i`` decoded signal, ``j`` input message):
        values, times, flags: latest usable value per decoded signal (the model's inputs, then the check
            references: :attr:`~virtsensor.daemon.layout.InputLayout.decoded`), its time (-inf: never),
            SNA/implausible flag.
        last_ok: per message, time of the latest usable frame. errors: E2E error since :meth:`clear_errors`.
        order: the messages' :class:`~virtsensor.daemon.validity.FrameOrder`. clock: the drain's ClockMap.
    """

    def __init__(self, layout: InputLayout, matrix: CanMatrix, counters: dict[str, int],
                 hook: StageHook | None = None, sync_id: int | None = None) -> None:
        n, m = len(layout.decoded), len(layout.input_messages)
        self.values: list[float] = [math.nan] * n
        self.times: list[float] = [-_INF] * n
        self.flags: list[bool] = [False] * n
        self.last_ok: list[float] = [-_INF] * m
        self.errors: list[bool] = [False] * m
        self._no_err = [False] * m
        self.order = FrameOrder(layout.cycles_s, layout.timeout_cycles)
        self._last_t = self.order.last_t
        self.clock = ClockMap()
        self._read_bus: Any = None
        self._read_filters: Any = None
        self._read: Callable[[float], tuple[Any, bool]] = polling_read(None)
        self.counters = counters
        self._e2e = [matrix.receivers[name] for name in layout.input_messages]
        self.by_id = matrix.by_id
        #: sync mode: frames with this id call :attr:`on_sync` (None: free-running)
        self.sync_id = sync_id
        self.on_sync: Callable[[Any], None] = lambda msg: None
        #: frame id -> (generated handler ``rx(data, t)``, message index)
        self.receivers: dict[int, tuple[Callable[[Any, float], None], int]] = {}
        for j, name in enumerate(layout.input_messages):
            mc = matrix.messages[name]
            slots = [(next(s for s in mc.signals if s.catalogue == layout.decoded[i]), i)
                     for i in layout.signal_slots(j)]
            rx = compile_receiver(mc, matrix.receivers[name], j, slots, self.values, self.times, self.flags,
                                  self.last_ok, self.errors, counters)
            self.receivers[mc.frame_id] = (hook("decode", rx) if hook is not None else rx, j)

    def handle(self, msg: Any, rx_time: float | None = None) -> None:
        """Count and decode one received frame. Its time (s, the daemon's clock) is ``msg.timestamp`` in
        sync mode (``sync_id`` set), else ``rx_time`` (default ``time.monotonic()``). A (standard, data)
        frame with the sync id then calls :attr:`on_sync` with it (after decoding it, if also an input)."""
        sync_id = self.sync_id
        if sync_id is not None:
            t = float(msg.timestamp)
        else:
            t = time.monotonic() if rx_time is None else rx_time
        c = self.counters
        c["frames"] += 1
        if msg.is_error_frame:
            c["error_frames"] += 1
            return
        if msg.is_remote_frame:
            c["remote_frames"] += 1
            return
        fid = msg.arbitration_id
        if msg.is_extended_id:
            c["unknown_ids"] += 1
            return
        entry = self.receivers.get(fid)
        if entry is not None:
            c["input_frames"] += 1
            rx, j = entry
            if t < self._last_t[j]:  # behind the message's previous frame (FrameOrder.frame, inlined)
                self.order.frame(j, t)
                c["time_step_back"] += 1
                self._e2e[j].reset()  # its alive-counter timeout must not be measured across the step
            else:
                self._last_t[j] = t
            rx(msg.data, t)
        elif fid == sync_id:
            pass
        elif fid in self.by_id:
            c["other_frames"] += 1
        else:
            c["unknown_ids"] += 1
        if fid == sync_id:
            self.on_sync(msg)

    def drain(self, bus: Any) -> int:
        """Read every frame ``bus`` has queued (``recv(0)`` until None) and handle it at its interface
        timestamp mapped by :attr:`clock` (the read time when the frame has no timestamp, ``<= 0``).
        Returns the number of frames read; interface errors propagate.

        A bus whose ``recv`` is python-can's own template method is read through its backend hook
        ``_recv_internal(0)`` (:func:`polling_read`): the frames its software filters (as set at this drain) pass,
        every one queued, without the template's per-frame timeout arithmetic and debug-log call."""
        filters = getattr(bus, "_filters", None)
        if bus is not self._read_bus or filters is not self._read_filters:  # (first drain, reconnect, new filters)
            self._read_bus, self._read_filters, self._read = bus, filters, polling_read(bus)
        read = self._read
        mono = time.monotonic
        handle = self.handle
        off = start = self.clock.offset
        b1 = b2 = _INF  # (the drain's two smallest bounds)
        far = _INF  # (a bound more than OUTLIER_S below the offset, waiting for a second frame to agree with it)
        n = unstamped = 0
        while True:
            msg = read(0.0)[0]
            if msg is None:
                break
            n += 1
            now = mono()
            ts = msg.timestamp
            if ts > 0.0:
                d = now - ts
                if d < b2:
                    if d < b1:
                        b1, b2 = d, b1
                    else:
                        b2 = d
                if d < off:
                    if off - d <= OUTLIER_S or off == _INF:  # (the first frame ever: any bound)
                        off = d
                    elif abs(d - far) <= CONFIRM_S:  # (two frames agree: the time base stepped forward)
                        off = min(d, far)
                    else:
                        far = d
                t = ts + off
            else:
                t = now
                unstamped += 1
            handle(msg, t)
        if unstamped:
            _count_unstamped(self.counters, unstamped)
        bound = b2 if b2 < _INF else b1
        if bound < _INF and (start - bound <= OUTLIER_S or start == _INF or b2 < _INF):
            self.clock.push(bound)
        else:  # (no stamped frame, or one alone stamped far ahead: nothing to go on)
            self.clock.idle()
        return n

    def clear_errors(self) -> None:
        """Start a new tick window of E2E errors (no allocation)."""
        self.errors[:] = self._no_err
