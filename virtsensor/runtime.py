"""The real-time virtual-sensor daemon: CAN in, 20 Hz ``SAT_FRONT`` + ``VS_Health`` out.

:class:`VirtualSensor` listens to any python-can bus, decodes the model's input
signals (named by the model card's ``feature_spec``, never by code) with per-message
receivers generated from the DBC at start-up (:mod:`virtsensor.fastdecode`: the codec's
decoding and E2E checks, constants inlined), keeps the latest valid value per signal
(the semantics of :class:`~virtsensor.frontend.SampleHoldStore`), and at every tick builds the
feature vector with :class:`~virtsensor.features.FeatureBuilder` (the same
numbers the trainer's ``FeatureSpec.transform`` gives on the 20 Hz table),
runs the ONNX model (:meth:`~virtsensor.model.onnx.OnnxModel.predict_one`, one
thread) and publishes both front SATs with a status per wheel.

Threads and clocks
------------------
* A **receive thread** owns the bus: ``bus.recv(20 ms)`` in a loop, decoding
  each frame (generated per-message receivers, :mod:`virtsensor.fastdecode`) under a short lock when
  free-running (in sync mode the ticks run in that thread: frames and ticks must come from one thread).
  It also re-opens the bus after errors.
* **Free-running mode** (default): a **tick thread** runs on a drift-free
  schedule of absolute deadlines ``t0 + k * 50 ms`` on ``time.monotonic_ns``:
  it sleeps on the stop event until the deadline (``SPIN_S`` = 0; a positive ``SPIN_S`` would sleep until
  that long before it and spin the rest), with a 1 ns timer slack where Linux allows it.
  Receive times are the local ``time.monotonic()`` when the receive thread got
  the frame, so ages and timeouts are measured on one clock whatever the
  interface's timestamps are. A tick that ends after the next deadline is an
  *overrun*; deadlines more than one period late are skipped (never bunched).
* **Sync mode** (``sync_id``): every ``sync_every``-th frame with that CAN id
  triggers a tick in the receive thread, right after all frames received
  before it, at tick time = the sync frame's timestamp; frame timestamps are
  the bus's own. This makes replays deterministic: replaying a log with a sync
  frame just after each 20 Hz grid instant gives, tick for tick, the frames the
  offline table of :func:`virtsensor.recording.read_log` sees.

Validity (per tick, see ``docs/deployment.md``)
-----------------------------------------------
Each input signal is *bad* when it is stale (no usable value for longer than
``timeout_cycles`` (default 3) cycles of its message), was received as SNA or
implausible (outside the catalogue range) in the latest intact frame, is still
*recovering* (the first ``h`` fresh ticks after a stale period, where ``h`` is
the history the signal's rate/accel/lag features read: their values would
still mix held samples), or its message had an E2E error (CRC, DLC, repeated
or jumping counter) since the previous tick. Then per wheel:

* ``INIT`` (3) until the feature history is full (and before every input has
  been seen once); estimate SNA;
* ``INVALID`` (2) when a *critical* input is bad, the features are not finite,
  or the estimate is non-finite or outside the catalogue output range;
  estimate SNA;
* ``DEGRADED`` (1) when only non-critical inputs are bad (their last value is
  held); the estimate is sent; the bad inputs' messages have their bit cleared
  in ``VS_Health.VS_InputStatus``;
* ``VALID`` (0) otherwise.

Real-time hygiene: every array and list the tick touches is allocated at start-up and
reused (slice assignment, preallocated ``can.Message`` objects), with one small exception:
the snapshot ``self._vals[:] = self._rx_vals`` assigns the receivers' Python list of input
values to a numpy array, so numpy converts that list (one float per input signal) into a
temporary array each tick. After start-up the heap is ``gc.freeze()``-d and the cyclic GC
is disabled during the tick;
onnxruntime runs with one thread and no spinning. Optional CPU affinity
(``os.sched_setaffinity``) and ``SCHED_FIFO`` (``os.sched_setscheduler``) are
applied where permitted, logged and skipped otherwise.

Logs are JSON lines on stderr (:func:`configure_logging`): ``start``,
``config``, ``bus_error``, ``reconnect``, ``status_change``, ``shutdown``...
"""

from __future__ import annotations

import gc
import json
import logging
import math
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.canbus.codec import STATUS_KEYS, CanMatrix, compile_encoder, compile_receiver
from virtsensor.canbus.e2e import E2EStatus, next_counter
from virtsensor.errors import UserError
from virtsensor.features import TICK_S, FeatureBuilder, FeatureSpec

__all__ = [
    "VALID",
    "DEGRADED",
    "INVALID",
    "INIT",
    "STATUS_NAMES",
    "TICK_NS",
    "RuntimeConfig",
    "VirtualSensor",
    "JsonFormatter",
    "configure_logging",
    "load_config",
]

#: Per-wheel status codes of ``SAT_FRONT.SAT_xx_Status`` (DBC value table).
VALID, DEGRADED, INVALID, INIT = 0, 1, 2, 3
STATUS_NAMES = {VALID: "VALID", DEGRADED: "DEGRADED", INVALID: "INVALID", INIT: "INIT"}

#: Tick period (ns): the feature spec's 20 Hz.
TICK_NS = round(TICK_S * 1e9)
#: Sleep until this long before a deadline, then spin (s). 0: sleep to the deadline. Spinning buys punctuality
#: with CPU: it busy-waits SPIN_S of every 50 ms tick (by arithmetic, 1 ms would be 2 % of a core; the bench
#: reports it as ``free_running.spin_budget_percent``), whereas a sleep wakes late only by the timer slack plus
#: the scheduler's wake-up latency, which ``virtsensor bench`` measures as ``jitter_us``.
SPIN_S = 0.0
#: Timer slack of the tick thread (ns, Linux ``PR_SET_TIMERSLACK``; the default 50 us lets the kernel wake a
#: sleeper up to 50 us late to batch timers). 1 ns asks the kernel for (next to) no such slack, so the wake-up
#: lateness (``jitter_us`` of ``virtsensor bench``) is left with the scheduler's own latency.
TIMER_SLACK_NS = 1
#: ``bus.recv`` timeout of the receive thread (s): bounds the shutdown time.
RECV_TIMEOUT_S = 0.02
#: Catalogue output -> (estimate, status) signal of SAT_FRONT.
OUTPUT_SIGNALS = {"sat_fl_nm": ("SAT_FL", "SAT_FL_Status"), "sat_fr_nm": ("SAT_FR", "SAT_FR_Status")}

log = logging.getLogger("virtsensor.runtime")


# ---------------------------------------------------------------------------------------------------------------
# logging
# ---------------------------------------------------------------------------------------------------------------
class JsonFormatter(logging.Formatter):
    """One JSON object per line: ``ts`` (UTC ISO 8601, ms), ``level``, ``logger``, ``event`` and the
    record's ``fields`` (``logger.info("event", extra={"fields": {...}})``). Non-finite floats become null."""

    def format(self, record: logging.LogRecord) -> str:
        ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z"
        out: dict[str, Any] = {"ts": ts, "level": record.levelname.lower(), "logger": record.name,
                               "event": record.getMessage()}
        extra = getattr(record, "fields", None)
        if isinstance(extra, Mapping):
            out.update(extra)
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        return json.dumps(_json_safe(out), default=str, separators=(",", ":"))


def _json_safe(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        return _json_safe(obj.item())
    return obj


class _StderrHandler(logging.StreamHandler):
    """A stream handler that writes to whatever ``sys.stderr`` is at emit time."""

    @property  # type: ignore[override]
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ assigns it
        pass


LOG_LEVELS = ("debug", "info", "warning", "error")


def configure_logging(level: str = "info") -> None:
    """JSON-lines logs of the ``virtsensor`` loggers on stderr at ``level`` (replaces earlier set-ups)."""
    lv = str(level).lower()
    if lv not in LOG_LEVELS:
        raise UserError(f"log level {level!r} is not one of {', '.join(LOG_LEVELS)}")
    root = logging.getLogger("virtsensor")
    for h in list(root.handlers):
        if isinstance(h, _StderrHandler):
            root.removeHandler(h)
    handler = _StderrHandler()
    handler.setFormatter(JsonFormatter())
    root.addHandler(handler)
    root.setLevel(lv.upper())
    root.propagate = False


def _event(level: int, event: str, **data: Any) -> None:
    if log.isEnabledFor(level):
        log.log(level, event, extra={"fields": data})


# ---------------------------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------------------------
@dataclass
class RuntimeConfig:
    """Settings of ``virtsensor run`` (CLI options and TOML keys share these names, ``-`` or ``_``).

    Attributes:
        model: ONNX file (its card beside it). dbc: DBC file (None: bundled).
        interface, channel, bitrate: python-can bus.
        sync_id: CAN id whose frames trigger the ticks (None: free-running 20 Hz).
        sync_every: tick on every n-th sync frame (e.g. 5 for a 100 Hz frame), counted from the first.
        cpu: pin the daemon to this CPU. realtime: ask for SCHED_FIFO at ``rt_priority``.
        duration: stop after this many seconds (None: until SIGTERM/SIGINT).
        log_level: debug, info, warning or error.
        timeout_cycles: an input message is stale after this many of its cycles without a usable frame.
        model_id: the VS_ModelId byte (None: the card's ``model_id``, else the first byte of its sha256).
    """

    model: str | None = None
    dbc: str | None = None
    interface: str | None = None
    channel: str | None = None
    bitrate: int | None = None
    sync_id: int | None = None
    sync_every: int = 1
    cpu: int | None = None
    realtime: bool = False
    rt_priority: int = 50
    duration: float | None = None
    log_level: str = "info"
    timeout_cycles: float = 3.0
    model_id: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


_PATH_KEYS = ("model", "dbc")


def _coerce(key: str, value: Any, where: str) -> Any:
    """Check and convert one setting; ``where`` names its source in errors."""
    def bad(expect: str) -> UserError:
        return UserError(f"{where}: {key} must be {expect}, got {value!r}")

    if value is None:
        return None
    if key in ("model", "dbc", "interface", "channel", "log_level"):
        if not isinstance(value, (str, os.PathLike)) or not str(value):
            raise bad("a non-empty string")
        value = str(value)
        if key == "log_level" and value.lower() not in LOG_LEVELS:
            raise bad(f"one of {', '.join(LOG_LEVELS)}")
        return value.lower() if key == "log_level" else value
    if key == "sync_id":
        try:
            v = int(value, 0) if isinstance(value, str) else value
        except ValueError:
            raise bad("a CAN id such as 0x7F0") from None
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 0x7FF:
            raise bad("an 11-bit CAN id 0x000..0x7FF")
        return v
    if key in ("bitrate", "sync_every", "cpu", "rt_priority", "model_id"):
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("an integer")
        lo, hi = {"bitrate": (1, 10_000_000), "sync_every": (1, 1000), "cpu": (0, 4095),
                  "rt_priority": (1, 99), "model_id": (0, 255)}[key]
        if not lo <= value <= hi:
            raise bad(f"in {lo}..{hi}")
        return value
    if key == "realtime":
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if key in ("duration", "timeout_cycles"):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise bad("a positive number")
        if key == "timeout_cycles" and value < 1:
            raise bad("at least 1")
        return float(value)
    raise UserError(f"{where}: unknown setting {key!r}")  # pragma: no cover - keys are checked first


_KEYS = tuple(f.name for f in fields(RuntimeConfig))


def read_config_file(path: str | os.PathLike) -> dict[str, Any]:
    """The settings of a TOML config file (keys checked, paths relative to the file made absolute).

    Raises:
        UserError: unreadable file, invalid TOML, unknown key (named with the file) or a bad value.
    """
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]

    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise UserError(f"cannot read config file {path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise UserError(f"config file {path} is not UTF-8 text") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"config file {path} is not valid TOML: {exc}") from None
    out: dict[str, Any] = {}
    for raw_key, value in data.items():
        key = raw_key.replace("-", "_")
        if key not in _KEYS:
            raise UserError(f"{path}: unknown key {raw_key!r} (known: {', '.join(_KEYS)})")
        if key in out:
            raise UserError(f"{path}: key {raw_key!r} given twice")
        value = _coerce(key, value, str(path))
        if key in _PATH_KEYS and value is not None and not Path(value).is_absolute():
            value = str((path.parent / value).resolve())
        out[key] = value
    return out


def load_config(file: str | os.PathLike | None = None, overrides: Mapping[str, Any] | None = None) -> RuntimeConfig:
    """Merge a TOML file and overrides (e.g. CLI options; None values are ignored) into a checked config.

    Raises:
        UserError: see :func:`read_config_file`; a missing ``model``, ``interface`` or ``channel``.
    """
    merged: dict[str, Any] = read_config_file(file) if file is not None else {}
    for key, value in (overrides or {}).items():
        k = key.replace("-", "_")
        if k not in _KEYS:
            raise UserError(f"unknown setting {key!r}")
        if value is not None:
            merged[k] = _coerce(k, value, f"--{k.replace('_', '-')}")
    cfg = RuntimeConfig(**merged)
    missing = [k for k in ("model", "interface", "channel") if getattr(cfg, k) is None]
    if missing:
        src = f" (not in {file} either)" if file is not None else ""
        raise UserError(f"missing setting(s) {', '.join('--' + k for k in missing)}{src}")
    return cfg


# ---------------------------------------------------------------------------------------------------------------
# the sensor
# ---------------------------------------------------------------------------------------------------------------
class _Payload(bytearray):
    """The data of the daemon's preallocated output frames: a ``bytearray`` that deep-copies as one C call.

    python-can's ``virtual`` bus deep-copies every sent message once per receiving bus; a plain bytearray
    goes through the generic ``copy._reconstruct`` path. Other interfaces only read the bytes.
    """

    __slots__ = ()

    def __deepcopy__(self, memo: Any) -> bytearray:
        return bytearray(self)


def _set_timer_slack(ns: int) -> bool:
    """Best effort: the calling thread's timer slack (Linux ``prctl(PR_SET_TIMERSLACK)``); False elsewhere."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(29, ctypes.c_ulong(ns), 0, 0, 0) == 0  # 29 = PR_SET_TIMERSLACK
    except (OSError, AttributeError):
        return False


def _bitmap_order(matrix: CanMatrix) -> dict[str, int]:
    """Message -> bit of ``VS_Health.VS_InputStatus``, read from the signal's DBC comment ("bit 0 IMU_Motion, ...")."""
    try:
        comment = matrix.db.get_message_by_name("VS_Health").get_signal_by_name("VS_InputStatus").comment or ""
    except (KeyError, AttributeError):
        return {}
    return {name: int(bit) for bit, name in re.findall(r"\bbit\s+(\d+)\s+([A-Za-z_]\w*)", comment)
            if name in matrix.messages and int(bit) < 8}


def _shutdown_bus(bus: Any) -> None:
    """Shut a bus down (None: nothing to do); a failure is logged, never raised."""
    if bus is None:
        return
    try:
        bus.shutdown()
    except Exception as exc:  # noqa: BLE001
        _event(logging.WARNING, "bus_error", where="shutdown", error=f"{type(exc).__name__}: {exc}")


class VirtualSensor:
    """The daemon. Build it with :meth:`from_config`, or directly from an open bus, model and matrix.

    Args:
        bus: an open ``can.BusABC``; the sensor takes ownership (it shuts it down in :meth:`stop`).
        model: a loaded :class:`~virtsensor.model.onnx.OnnxModel`.
        matrix: a :class:`~virtsensor.can_codec.CanMatrix` (its compiled tables are shared; the sensor
            keeps its own E2E state with ``timeout_cycles``).
        sync_id, sync_every, timeout_cycles, model_id, cpu, realtime, rt_priority: see :class:`RuntimeConfig`.
        bus_factory: opens a new bus after a bus error (None: the sensor keeps retrying the same bus).
        freeze_gc: ``gc.freeze()`` after start-up and no cyclic GC during the tick.
        reconnect_backoff_s, reconnect_max_s: first and largest wait before re-opening the bus.

    Raises:
        UserError: the model card lacks a usable ``feature_spec``, or names inputs the DBC lacks,
            or the DBC lacks SAT_FRONT/VS_Health, or ``sync_id`` is one of the daemon's own ids.

    Driving it by hand (tests, simulations): :meth:`process` feeds one received ``can.Message``,
    :meth:`tick` runs one tick at a given time (in sync mode, call both from one thread: the receive thread
    once started); :meth:`start`/:meth:`stop` run the threads; :meth:`run` also handles SIGTERM/SIGINT.
    :attr:`counters` and :meth:`stats` report.
    """

    def __init__(
        self,
        bus: Any,
        model: Any,
        matrix: CanMatrix,
        *,
        sync_id: int | None = None,
        sync_every: int = 1,
        timeout_cycles: float = 3.0,
        model_id: int | None = None,
        bus_factory: Callable[[], Any] | None = None,
        cpu: int | None = None,
        realtime: bool = False,
        rt_priority: int = 50,
        freeze_gc: bool = True,
        reconnect_backoff_s: float = 0.05,
        reconnect_max_s: float = 2.0,
    ) -> None:
        import can

        self._can = can
        self.model = model
        card = model.card
        where = str(getattr(model, "card_path", "model card"))
        if not isinstance(card.get("feature_spec"), Mapping):
            raise UserError(f"{where}: the model card has no feature_spec (re-export the model with virtsensor train)")
        try:
            self.spec = FeatureSpec.from_json(card["feature_spec"])
        except (KeyError, TypeError, ValueError) as exc:
            raise UserError(f"{where}: invalid feature_spec: {exc}") from None
        if tuple(model.input_names) != self.spec.names:
            raise UserError(f"{where}: feature_names {list(model.input_names)} differ from the feature_spec's "
                            f"{list(self.spec.names)}")
        if timeout_cycles < 1:
            raise ValueError("timeout_cycles must be >= 1")
        self.timeout_cycles = float(timeout_cycles)
        # own E2E state, with our timeout (INITIAL after a gap of timeout_cycles cycles)
        self.matrix = CanMatrix(matrix.db, matrix.messages, matrix.source, max_delta=matrix.max_delta,
                                timeout_cycles=self.timeout_cycles)
        for name in ("SAT_FRONT", "VS_Health"):
            if name not in self.matrix.messages:
                raise UserError(f"{matrix.source}: the DBC has no {name} message, which the daemon sends")
        sat_names = {s.name for s in self.matrix.messages["SAT_FRONT"].signals}

        # ---- inputs (from the card) ------------------------------------------------------------------
        self.signals: tuple[str, ...] = self.spec.signals
        n = len(self.signals)
        sig_msg_names = []
        for s in self.signals:
            m = self.matrix.message_of(s)
            if m is None:
                home = cat.SIGNALS[s].message if s in cat.SIGNALS else None
                raise UserError(f"model input {s} (message {home}) is not in the DBC {matrix.source}")
            if not self.matrix.messages[m].cycle_s > 0:
                raise UserError(f"{matrix.source}: message {m} (carrying model input {s}) has no GenMsgCycleTime")
            sig_msg_names.append(m)
        critical = {}
        for entry in card.get("inputs") or ():
            if isinstance(entry, Mapping) and "critical" in entry:
                s = entry.get("signal", entry.get("name"))
                critical[s] = bool(entry["critical"]) or critical.get(s, False)
        self.critical = tuple(critical.get(s, cat.SIGNALS[s].critical) for s in self.signals)
        bit_of = _bitmap_order(self.matrix)
        if not bit_of:  # no documented order: the input messages by frame id
            ordered = sorted(set(sig_msg_names), key=lambda m: self.matrix.messages[m].frame_id)
            bit_of = {m: i for i, m in enumerate(ordered[:8])}
        # the messages we decode: those carrying model inputs and those of the health bitmap
        self.input_messages: tuple[str, ...] = tuple(
            sorted(set(sig_msg_names) | set(bit_of), key=lambda m: self.matrix.messages[m].frame_id))
        self.bitmap_bits = dict(bit_of)
        mi = {m: j for j, m in enumerate(self.input_messages)}
        # per-signal / per-message constants of the tick's validity logic (plain lists: 12 signals are cheaper
        # in a Python loop than in a dozen tiny numpy calls)
        self._sig_msg = [mi[m] for m in sig_msg_names]
        self._sig_timeout = [self.timeout_cycles * self.matrix.messages[m].cycle_s for m in sig_msg_names]
        self._msg_timeout = [self.timeout_cycles * self.matrix.messages[m].cycle_s for m in self.input_messages]
        self._sig_hist = [max(f.history for f in self.spec.features if f.signal == s) for s in self.signals]
        self._critical = list(self.critical)
        self._sig_bit = [1 << bit_of[m] if m in bit_of else 0 for m in sig_msg_names]
        self._bitmap_msgs = [(mi[m], 1 << b) for m, b in bit_of.items()]
        self._msg_sigs = [[i for i, m in enumerate(sig_msg_names) if m == name] for name in self.input_messages]

        # ---- outputs ------------------------------------------------------------------------------------
        outs = tuple(model.outputs)
        self._wheels = []  # (model output index or -1, estimate signal, status signal, catalogue lo, hi)
        for out_name, (est, st) in OUTPUT_SIGNALS.items():
            if est not in sat_names or st not in sat_names:
                raise UserError(f"{matrix.source}: SAT_FRONT lacks {est}/{st}")
            spec = cat.SIGNALS[out_name]
            self._wheels.append((outs.index(out_name) if out_name in outs else -1, est, st,
                                 spec.minimum, spec.maximum))
        if not any(w[0] >= 0 for w in self._wheels):
            raise UserError(f"{where}: the model's outputs {list(outs)} include neither sat_fl_nm nor sat_fr_nm")

        # ---- identity, modes -----------------------------------------------------------------------------
        if model_id is None:
            cid = card.get("model_id")
            model_id = cid if isinstance(cid, int) and 0 <= cid <= 255 else int(str(card.get("sha256", "00"))[:2], 16)
        self.model_id = int(model_id)
        own_ids = {self.matrix.messages["SAT_FRONT"].frame_id, self.matrix.messages["VS_Health"].frame_id}
        if sync_id is not None and sync_id in own_ids:
            raise UserError(f"sync id 0x{sync_id:X} is one of the daemon's own frames (SAT_FRONT/VS_Health)")
        if sync_every < 1:
            raise ValueError("sync_every must be >= 1")
        self.sync_id = sync_id
        self.sync_every = int(sync_every)
        self.cpu, self.realtime, self.rt_priority = cpu, bool(realtime), int(rt_priority)
        self._freeze_gc = freeze_gc
        self._factory = bus_factory
        self._backoff0, self._backoff_max = float(reconnect_backoff_s), float(reconnect_max_s)

        # ---- state shared by the receive path and the tick (under _lock) -----------------------------------
        self._lock = threading.Lock()
        # free-running, the tick thread reads what the receive thread writes: each frame is stored under the lock.
        # In sync mode every tick runs inside process(), in the thread that feeds the frames: no lock per frame.
        self._rx_lock: threading.Lock | None = self._lock if sync_id is None else None
        self._io_lock = threading.Lock()
        self._bus = bus
        # the sample-and-hold store (the semantics of frontend.SampleHoldStore) as plain lists, written per frame
        # by the generated receivers (a list item store avoids numpy's per-scalar conversion)
        self._rx_vals: list[float] = [math.nan] * n  # latest usable value per input signal
        self._rx_times: list[float] = [-math.inf] * n  # its receive time
        self._rx_flag: list[bool] = [False] * n  # SNA / implausible in the latest intact frame
        self._rx_err: list[bool] = [False] * len(self.input_messages)  # E2E error since the last tick
        self._rx_last_ok: list[float] = [-math.inf] * len(self.input_messages)  # last usable frame per message
        self._no_err: list[bool] = [False] * len(self.input_messages)
        self._complete = False
        self._sync_count = 0

        # ---- tick buffers (preallocated) -------------------------------------------------------------------
        self._builder = FeatureBuilder(self.spec)
        self._vals = np.full(n, np.nan)
        self._stale = [False] * n  # of the last tick (for the logs)
        self._bad = [False] * n
        self._recover = [0] * n  # ticks left until a signal back from stale may count as good again
        self._msg_err_tick = [False] * len(self.input_messages)  # the tick's snapshots of the _rx_* lists
        self._t_times = [-math.inf] * n
        self._t_flags = [False] * n
        self._t_last_ok = [-math.inf] * len(self.input_messages)
        self._xzero = np.zeros(len(self.spec.features))  # x . 0 is nan iff some feature is not finite (0 * inf)
        self._sat_values: dict[str, float] = {}
        for _, est, st, _, _ in self._wheels:
            self._sat_values[est] = math.nan
            self._sat_values[st] = INIT
        self._health_values: dict[str, float] = {"VS_TickOverruns": 0, "VS_TickLatency": 0,
                                                 "VS_InputStatus": 0, "VS_ModelId": self.model_id}
        sat_m, health_m = self.matrix.messages["SAT_FRONT"], self.matrix.messages["VS_Health"]
        # generated encoders: byte for byte CanMatrix.encode (tests/test_fastdecode.py), with the
        # message's layout unrolled instead of looked up per signal
        self._encode_sat = compile_encoder(sat_m)
        self._encode_health = compile_encoder(health_m)
        self._sat_msg = can.Message(arbitration_id=sat_m.frame_id, is_extended_id=False, dlc=sat_m.length,
                                    data=_Payload(sat_m.length))
        self._health_msg = can.Message(arbitration_id=health_m.frame_id, is_extended_id=False, dlc=health_m.length,
                                       data=_Payload(health_m.length))
        self._sat_ctr = 0
        self._health_ctr = 0
        self._lat_us = np.zeros(8192)  # ring of tick latencies (us): tick start -> SAT_FRONT sent
        self._cmp_us = np.zeros(8192)  # ring of tick compute times (us): tick start -> SAT_FRONT encoded
        self._jit_us = np.zeros(8192)  # ring of wake-up lateness (us, free-running mode)
        self._n_jit = 0
        self._last = (INIT, INIT, -1)  # statuses and bitmap of the previous tick (for change logs)
        self.last_statuses: tuple[int, ...] = (INIT, INIT)
        self.last_bitmap = 0

        #: event counters (frames, E2E outcomes, ticks, bus errors, reconnects, ...)
        self.counters: dict[str, int] = dict.fromkeys((
            "frames", "input_frames", "other_frames", "unknown_ids", "error_frames", "remote_frames", "sync_frames",
            "crc_errors", "dlc_errors", "sna_values", "implausible_values",
            *(STATUS_KEYS[s] for s in E2EStatus if s is not E2EStatus.NODATA),
            "ticks", "overruns", "tick_errors", "sent", "send_errors", "unsent", "recv_errors", "reconnects",
            "reconnect_failures", "status_changes"), 0)
        #: frame id -> generated handler ``rx(data, t)`` (DLC, CRC, E2E, decode into the ``_rx_*`` lists)
        self._receivers: dict[int, Callable[[Any, float], None]] = {}
        for j, name in enumerate(self.input_messages):
            mc = self.matrix.messages[name]
            slots = [(next(s for s in mc.signals if s.catalogue == self.signals[i]), i) for i in self._msg_sigs[j]]
            self._receivers[mc.frame_id] = compile_receiver(
                mc, self.matrix.receivers[name], j, slots, self._rx_vals, self._rx_times, self._rx_flag,
                self._rx_last_ok, self._rx_err, self.counters)
        self._stop = threading.Event()
        self._reconnect_needed = threading.Event()
        self._rx_thread: threading.Thread | None = None
        self._tick_thread: threading.Thread | None = None
        self._started = self._stopped = self._frozen = False
        self._signal_ns: int | None = None
        self._signal_name: str | None = None
        self._loop_exit_ns: int | None = None
        self._last_reconnect_ns = 0
        self._backoff = self._backoff0
        #: the configuration it was built from (set by :meth:`from_config`)
        self.config: RuntimeConfig | None = None

    # ------------------------------------------------------------------------------------------ construction
    @classmethod
    def from_config(
        cls,
        config: RuntimeConfig | Mapping[str, Any] | str | os.PathLike,
        *,
        bus: Any = None,
        bus_factory: Callable[[], Any] | None = None,
        **kwargs: Any,
    ) -> VirtualSensor:
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
        from virtsensor.model.onnx import OnnxModel
        from virtsensor.replay import open_bus

        if isinstance(config, (str, os.PathLike)):
            cfg = load_config(config)
        elif isinstance(config, RuntimeConfig):
            cfg = config
        else:
            cfg = load_config(None, config)
        model = OnnxModel.load(cfg.model)
        matrix = CanMatrix.load(cfg.dbc)
        if bus is None:
            def factory():
                return open_bus(cfg.interface, cfg.channel, cfg.bitrate)
            bus_factory = bus_factory or factory
            sensor_bus = None
        else:
            sensor_bus = bus
        sensor = cls(sensor_bus, model, matrix, sync_id=cfg.sync_id, sync_every=cfg.sync_every,
                     timeout_cycles=cfg.timeout_cycles, model_id=cfg.model_id, bus_factory=bus_factory,
                     cpu=cfg.cpu, realtime=cfg.realtime, rt_priority=cfg.rt_priority, **kwargs)
        if sensor_bus is None:  # everything checked: now open the bus (UserError when it cannot be opened)
            sensor._bus = bus_factory()
        sensor.config = cfg
        return sensor

    @property
    def bus(self):
        """The bus in use (None while re-opening it)."""
        return self._bus

    @property
    def mode(self) -> str:
        return "free-running" if self.sync_id is None else f"sync 0x{self.sync_id:X}/{self.sync_every}"

    # ------------------------------------------------------------------------------------------ receive path
    def process(self, msg: Any, rx_time: float | None = None) -> None:
        """Handle one received python-can ``Message`` (decode, E2E, store; a sync frame then ticks).

        ``rx_time``: receive time (s) in free-running mode (default ``time.monotonic()``); sync mode uses
        ``msg.timestamp``.
        """
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
        sync = fid == self.sync_id  # (never when free-running: sync_id is None)
        rx = self._receivers.get(fid)
        if rx is not None:
            c["input_frames"] += 1
            if self.sync_id is not None:
                t = float(msg.timestamp)
            else:
                t = time.monotonic() if rx_time is None else rx_time
            lock = self._rx_lock
            if lock is None:  # sync mode: the ticks run in this very thread, inside process()
                rx(msg.data, t)
            else:
                lock.acquire()  # (cheaper than ``with``: this runs per frame)
                try:
                    rx(msg.data, t)
                finally:
                    lock.release()
        elif sync:
            pass
        elif fid in self.matrix.by_id:
            c["other_frames"] += 1
        else:
            c["unknown_ids"] += 1
        if sync:  # after the frame's own data, when the sync id is also an input (e.g. every 5th IMU frame)
            c["sync_frames"] += 1
            k = self._sync_count
            self._sync_count = k + 1
            if k % self.sync_every == 0:
                self._safe_tick(float(msg.timestamp), time.monotonic_ns())

    # ------------------------------------------------------------------------------------------ the tick
    def tick(self, t: float | None = None) -> tuple[int, ...]:
        """Run one tick at time ``t`` (s, the receive-time clock; default now) and publish; returns the statuses."""
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
            times, flags, msg_err, last_ok = self._t_times, self._t_flags, self._msg_err_tick, self._t_last_ok
            with self._lock:  # snapshot into the preallocated buffers
                self._vals[:] = self._rx_vals
                times[:] = self._rx_times
                flags[:] = self._rx_flag
                msg_err[:] = self._rx_err
                self._rx_err[:] = self._no_err
                last_ok[:] = self._rx_last_ok
            if not self._complete:
                self._complete = min(times) > -math.inf
            complete = self._complete
            # ---- input validity: stale = not (age <= timeout) (so a NaN age is stale too) or SNA/implausible;
            # bad = stale, recovering (history features still read held samples) or an E2E error of its message
            stale, bad, rec, hist = self._stale, self._bad, self._recover, self._sig_hist
            sig_to, sig_msg, crit = self._sig_timeout, self._sig_msg, self._critical
            any_bad = crit_bad = False
            for i in range(len(times)):
                st = not (t - times[i] <= sig_to[i]) or flags[i]
                r = rec[i]
                b = r > 0 or st or msg_err[sig_msg[i]]
                stale[i] = st
                bad[i] = b
                rec[i] = hist[i] if st else (r - 1 if r > 0 else 0)
                if b:
                    any_bad = True
                    if crit[i]:
                        crit_bad = True
            in_status = INVALID if crit_bad else DEGRADED if any_bad else VALID
            bitmap = 0
            msg_to = self._msg_timeout
            for j, bit in self._bitmap_msgs:
                if t - last_ok[j] <= msg_to[j] and not msg_err[j]:
                    bitmap |= bit
            if any_bad:
                for i, bit in enumerate(self._sig_bit):
                    if bad[i]:
                        bitmap &= ~bit
            # ---- features and model
            x = self._builder.push(self._vals) if complete else None
            sv = self._sat_values
            if x is None:
                for _, est, st, _, _ in self._wheels:
                    sv[est] = math.nan
                    sv[st] = INIT
            else:
                x_ok = x.dot(self._xzero) == 0.0  # every feature finite (one call instead of isfinite + all)
                y = self.model.predict_one(x) if x_ok else None
                for k, est, st, lo, hi in self._wheels:
                    v = float(y[k]) if (y is not None and k >= 0) else math.nan
                    if in_status == INVALID or not (lo <= v <= hi):  # also catches NaN
                        sv[est] = math.nan  # -> SNA on the bus
                        sv[st] = INVALID
                    else:
                        sv[est] = v
                        sv[st] = in_status
            # ---- publish
            m = self._sat_msg
            m.data[:] = self._encode_sat(sv, self._sat_ctr)
            self._sat_ctr = next_counter(self._sat_ctr)
            compute_us = (time.monotonic_ns() - start_ns) // 1000
            self._send(m)
            lat_us = (time.monotonic_ns() - start_ns) // 1000
            c = self.counters
            hv = self._health_values
            hv["VS_TickOverruns"] = c["overruns"]
            hv["VS_TickLatency"] = lat_us
            hv["VS_InputStatus"] = bitmap
            h = self._health_msg
            h.data[:] = self._encode_health(hv, self._health_ctr)
            self._health_ctr = next_counter(self._health_ctr)
            self._send(h)
            k = c["ticks"]
            self._lat_us[k % self._lat_us.shape[0]] = lat_us
            self._cmp_us[k % self._cmp_us.shape[0]] = compute_us
            c["ticks"] = k + 1
            if self.sync_id is not None and lat_us * 1000 > TICK_NS:
                c["overruns"] += 1
        finally:
            if gc_off:
                gc.enable()
        statuses = tuple(int(sv[w[2]]) for w in self._wheels)
        self.last_statuses = statuses
        self.last_bitmap = bitmap
        if (*statuses, bitmap) != self._last:
            self._log_change(t, statuses, bitmap, in_status)
            self._last = (*statuses, bitmap)

    def _log_change(self, t: float, statuses: tuple[int, ...], bitmap: int, in_status: int) -> None:
        self.counters["status_changes"] += 1
        if not log.isEnabledFor(logging.INFO):
            return
        bad = [s for i, s in enumerate(self.signals) if self._bad[i]]
        _event(logging.INFO, "status_change", t=round(t, 6),
               **{w[1].lower(): STATUS_NAMES[s] for w, s in zip(self._wheels, statuses, strict=True)},
               inputs=STATUS_NAMES[in_status], input_bitmap=f"0x{bitmap:02X}",
               bad_inputs=bad, stale_inputs=[s for i, s in enumerate(self.signals) if self._stale[i]],
               e2e_error_messages=[m for j, m in enumerate(self.input_messages) if self._msg_err_tick[j]],
               missing_messages=[m for m, b in self.bitmap_bits.items() if not bitmap >> b & 1])

    def _send(self, msg: Any) -> None:
        with self._io_lock:
            bus = self._bus
            if bus is None:
                self.counters["unsent"] += 1
                return
            try:
                msg.timestamp = time.time()
                bus.send(msg, timeout=0.005)
                self.counters["sent"] += 1
                return
            except Exception as exc:  # noqa: BLE001 - any interface error: count, reconnect
                self.counters["send_errors"] += 1
                err = exc
        self._reconnect_needed.set()
        n = self.counters["send_errors"]
        if n <= 5 or n % 100 == 0:
            _event(logging.WARNING, "bus_error", where="send", error=f"{type(err).__name__}: {err}",
                   send_errors=n, frame_id=f"0x{msg.arbitration_id:X}")

    # ------------------------------------------------------------------------------------------ threads
    def start(self) -> None:
        """Apply CPU affinity/SCHED_FIFO (if asked), start the receive thread (and the tick thread when
        free-running), then freeze the start-up heap out of the GC's reach."""
        if self._started:
            raise RuntimeError("VirtualSensor.start() called twice")
        self._started = True
        self._tune_os()
        main = threading.current_thread() is threading.main_thread()
        sigs = {signal.SIGTERM, signal.SIGINT}
        if main:  # worker threads block the stop signals, so the kernel delivers them to the main thread
            old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
        try:
            self._rx_thread = threading.Thread(target=self._rx_loop, name="virtsensor-rx", daemon=True)
            self._rx_thread.start()
            if self.sync_id is None:
                self._tick_thread = threading.Thread(target=self._tick_loop, name="virtsensor-tick", daemon=True)
                self._tick_thread.start()
        finally:
            if main:
                signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
        if self._freeze_gc:
            gc.collect()
            gc.freeze()
            self._frozen = True
        _event(logging.INFO, "started", mode=self.mode, tick_hz=1e9 / TICK_NS,
               timeout_cycles=self.timeout_cycles, inputs=list(self.signals),
               critical=[s for s, c in zip(self.signals, self.critical, strict=True) if c],
               input_messages=list(self.input_messages), model_id=self.model_id,
               bus=str(getattr(self._bus, "channel_info", self._bus)))

    def _tune_os(self) -> None:
        if self.cpu is not None:
            try:
                os.sched_setaffinity(0, {self.cpu})
                _event(logging.INFO, "affinity", cpu=self.cpu, ok=True)
            except (OSError, AttributeError, ValueError) as exc:
                _event(logging.WARNING, "affinity", cpu=self.cpu, ok=False, error=str(exc))
        if self.realtime:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.rt_priority))
                _event(logging.INFO, "realtime", policy="SCHED_FIFO", priority=self.rt_priority, ok=True)
            except (OSError, AttributeError) as exc:
                _event(logging.WARNING, "realtime", policy="SCHED_FIFO", priority=self.rt_priority, ok=False,
                       error=str(exc))

    def _tick_loop(self) -> None:
        _set_timer_slack(TIMER_SLACK_NS)
        mono = time.monotonic_ns
        stop = self._stop
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
                j = self._n_jit
                self._jit_us[j % self._jit_us.shape[0]] = (now - deadline) * 1e-3
                self._n_jit = j + 1
                self._safe_tick(now * 1e-9, now)
                k += 1
                end = mono()
                nxt = t0 + k * period
                if end > nxt:  # deadline missed: count it; skip deadlines already a full period gone
                    self.counters["overruns"] += 1
                    k += (end - nxt) // period
        finally:
            self._loop_exit_ns = mono()

    def _rx_loop(self) -> None:
        stop = self._stop
        try:
            while not stop.is_set():
                if self._reconnect_needed.is_set() or self._bus is None:
                    self._reconnect()
                    continue
                bus = self._bus
                try:
                    msg = bus.recv(RECV_TIMEOUT_S)
                except Exception as exc:  # noqa: BLE001 - any interface error: count, reconnect
                    if stop.is_set():
                        break
                    self.counters["recv_errors"] += 1
                    _event(logging.WARNING, "bus_error", where="recv", error=f"{type(exc).__name__}: {exc}",
                           recv_errors=self.counters["recv_errors"])
                    self._reconnect_needed.set()
                    continue
                if msg is not None:
                    self.process(msg)
        finally:
            if self.sync_id is not None:
                self._loop_exit_ns = time.monotonic_ns()

    def _reconnect(self) -> None:
        """Close the bus, back off (interruptible by stop), re-open it with the factory."""
        now = time.monotonic_ns()
        # a reconnect soon after the previous one doubles the wait (storms back off); else start over
        self._backoff = (min(self._backoff * 2, self._backoff_max)
                         if now - self._last_reconnect_ns < 5e9 else self._backoff0)
        if self._factory is not None:
            with self._io_lock:
                old, self._bus = self._bus, None
            _shutdown_bus(old)
        delay = self._backoff
        while not self._stop.is_set():
            if self._stop.wait(delay):
                return
            if self._factory is None:  # nothing to re-open: retry the same bus
                self._reconnect_needed.clear()
                self.counters["reconnects"] += 1
                self._last_reconnect_ns = time.monotonic_ns()
                _event(logging.WARNING, "reconnect", ok=True, reopened=False, delay_s=delay,
                       reconnects=self.counters["reconnects"])
                return
            try:
                new = self._factory()
            except Exception as exc:  # noqa: BLE001 - keep trying, slower
                self.counters["reconnect_failures"] += 1
                _event(logging.WARNING, "reconnect", ok=False, error=f"{type(exc).__name__}: {exc}",
                       delay_s=delay, failures=self.counters["reconnect_failures"])
                delay = min(delay * 2, self._backoff_max)
                continue
            with self._io_lock:
                self._bus = new
            self._reconnect_needed.clear()
            self.counters["reconnects"] += 1
            self._last_reconnect_ns = time.monotonic_ns()
            _event(logging.WARNING, "reconnect", ok=True, reopened=True, delay_s=delay,
                   reconnects=self.counters["reconnects"])
            return

    def _on_signal(self, signum: int, frame: Any) -> None:
        if self._signal_ns is None:
            self._signal_ns = time.monotonic_ns()
            self._signal_name = signal.Signals(signum).name
        self._stop.set()

    def request_stop(self) -> None:
        """Ask the threads to stop (thread-safe; :meth:`stop` then joins them)."""
        self._stop.set()

    def stop(self, timeout: float = 1.0) -> dict[str, Any]:
        """Stop the threads, shut the bus down, log ``shutdown`` with the counters; returns :meth:`stats`."""
        if self._stopped:
            return self.stats()
        self._stopped = True
        self._stop.set()
        for th in (self._tick_thread, self._rx_thread):
            if th is not None:
                th.join(timeout)
        joined_ns = time.monotonic_ns()
        with self._io_lock:
            bus, self._bus = self._bus, None
        _shutdown_bus(bus)
        if self._frozen:
            gc.unfreeze()
            self._frozen = False
        st = self.stats()
        extra: dict[str, Any] = {}
        if self._signal_ns is not None:
            extra["signal"] = self._signal_name
            if self._loop_exit_ns is not None:
                extra["signal_to_loop_exit_ms"] = round(max(self._loop_exit_ns - self._signal_ns, 0) / 1e6, 3)
            extra["signal_to_stopped_ms"] = round((time.monotonic_ns() - self._signal_ns) / 1e6, 3)
            extra["signal_to_joined_ms"] = round((joined_ns - self._signal_ns) / 1e6, 3)
        _event(logging.INFO, "shutdown", **extra, **st)
        return st

    def run(self, duration: float | None = None) -> int:
        """Start, serve until SIGTERM/SIGINT (handlers installed when called from the main thread) or
        ``duration`` seconds, stop. Returns 0 on a clean stop, 1 when a worker thread died."""
        self.start()
        old: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGTERM, signal.SIGINT):
                old[s] = signal.signal(s, self._on_signal)
        rc = 0
        try:
            end = None if duration is None else time.monotonic() + duration
            waiter = self._tick_thread or self._rx_thread
            while not self._stop.is_set():
                timeout = 0.5 if end is None else min(0.5, end - time.monotonic())
                if timeout <= 0:
                    break
                waiter.join(timeout)  # a signal interrupts this wait; the handler sets the stop event
                if not waiter.is_alive() and not self._stop.is_set():
                    _event(logging.ERROR, "fatal", error=f"thread {waiter.name} ended unexpectedly")
                    rc = 1
                    break
        finally:
            self.stop()
            for s, h in old.items():
                signal.signal(s, h)
        return rc

    # ------------------------------------------------------------------------------------------ reporting
    def stats(self) -> dict[str, Any]:
        """Counters plus percentiles of the tick latency (us, tick start to SAT_FRONT sent), of the compute
        time (us, tick start to SAT_FRONT encoded: no bus I/O) and of the wake-up lateness (free-running)."""
        out: dict[str, Any] = dict(self.counters)
        n = min(self.counters["ticks"], self._lat_us.shape[0])
        if n:
            lat, cmp_ = self._lat_us[:n], self._cmp_us[:n]
            out.update(latency_p50_us=float(np.percentile(lat, 50)), latency_p99_us=float(np.percentile(lat, 99)),
                       latency_max_us=float(lat.max()), compute_p50_us=float(np.percentile(cmp_, 50)),
                       compute_p99_us=float(np.percentile(cmp_, 99)))
        m = min(self._n_jit, self._jit_us.shape[0])
        if m:
            jit = self._jit_us[:m]
            out.update(wake_late_p50_us=float(np.percentile(jit, 50)), wake_late_p99_us=float(np.percentile(jit, 99)),
                       wake_late_max_us=float(jit.max()))
        out["statuses"] = [STATUS_NAMES[s] for s in self.last_statuses]
        return out

    def __enter__(self) -> VirtualSensor:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()
