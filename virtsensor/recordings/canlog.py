"""CAN log files (write and read through python-can) and the canonical 20 Hz CSV table.

Writing (:func:`write_log`): the simulator's signals, sampled on a uniform
base grid ``time_s`` (e.g. 100 Hz, already held at each sensor's own rate),
become one frame per message per cycle (``GenMsgCycleTime``). Frame ``k`` of a
message is stamped ``start_time + k * cycle + phase`` seconds (run time
``time_s[0]`` maps to ``start_time``) where ``phase`` is a fixed per-message
offset (:func:`phase_offset`: 0.25 ms times the message's rank by frame id)
so that messages do not share timestamps. It carries the latest sample at or
before its own time, an alive counter (E2E Profile 11: from 0, as after
``E2E_P11ProtectInit``, +1 mod 15 per message, so that a reader's Profile 11
check accepts the very first frame) and its E2E CRC. Messages none of whose catalogue
signals are given are not sent.

Reading (:func:`read_log`): any log python-can reads (``.blf``, ``.asc``,
``.log`` candump, ``.csv``, ``.trc``) is decoded through the DBC with the E2E
checks and turned into the canonical table by the front-end
(:mod:`virtsensor.frontend`). Table time ``time_s`` is seconds since the
log's first frame (log formats differ in how they keep absolute time: ASC
stores it relative to its first frame, BLF only to the millisecond).

Failures to read a file raise :class:`~virtsensor.errors.UserError` naming the
file and the position (frame index, line number or byte offset). A log cut by
the end of its file (a BLF shorter than its header says, a text log whose last
line has no end of line, an ASC log without its ``End TriggerBlock`` line) is
refused as a whole, naming its last good frame and timestamp; so is a CSV table
whose last row has no end of line. A ``.gz`` text log is decompressed through
once before its first frame is read, for the same checks on its text and to
refuse a gzip stream cut short, corrupt or not gzip at all. A log whose time is not one run's (a frame
stamped more than one tick before the latest before it, :data:`~virtsensor.frontend.MAX_BACK_S`,
checked as it is read; a jump of more than a minute between consecutive frames, or
more than 12 hours from first to last: :func:`virtsensor.frontend.time_problem`)
is refused naming the frame or the time of the jump, before any tick grid is built.
"""

from __future__ import annotations

import io
import logging
import math
import os
import re
import threading
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.canbus.codec import CanMatrix
from virtsensor.canbus.e2e import USABLE, E2EStatus, counter_sequence
from virtsensor.errors import UserError
from virtsensor.frontend import MAX_BACK_S, TIME_TOLERANCE_S, TableBuild, collect, table_from_collected
from virtsensor.recordings.files import LOG_SUFFIXES

__all__ = [
    "CAN_LOG_SUFFIXES",
    "PHASE_STEP_S",
    "LogSummary",
    "Recording",
    "phase_offset",
    "frame_arrays",
    "iter_frames",
    "write_log",
    "iter_log",
    "read_log",
    "simulated_recording",
    "decode_recording",
    "write_csv",
    "read_csv",
]

#: Log formats python-can both writes and reads (by file suffix; ``.gz`` text variants too): a recording's CAN
#: logs and python-can's own CSV (which recording folders never hold: there ``.csv`` is the table).
CAN_LOG_SUFFIXES: tuple[str, ...] = (*LOG_SUFFIXES, ".csv")
_TEXT_SUFFIXES = (".asc", ".log", ".csv", ".trc")
#: Phase step between messages (s): message of rank r (by frame id) is sent at k*cycle + r*PHASE_STEP_S.
PHASE_STEP_S = 0.00025
#: Tolerance (s) when looking up "the latest sample at or before" a frame time on the base grid.
_GRID_TOL_S = 1e-9


def _suffix(path: Path) -> tuple[str, bool]:
    sfx = [s.lower() for s in path.suffixes]
    if sfx and sfx[-1] == ".gz":
        return (sfx[-2] if len(sfx) >= 2 else ""), True
    return (sfx[-1] if sfx else ""), False


def _check_suffix(path: Path) -> None:
    real, gz = _suffix(path)
    if real not in CAN_LOG_SUFFIXES or (gz and real == ".blf"):
        raise UserError(
            f"{path}: unsupported CAN log format {''.join(path.suffixes) or '(no suffix)'!r}; "
            f"use one of {', '.join(CAN_LOG_SUFFIXES)} (text formats may end in .gz)"
        )


def phase_offset(matrix: CanMatrix, message: str) -> float:
    """Fixed transmit phase (s) of ``message``: ``PHASE_STEP_S`` x its rank by frame id."""
    ids = sorted(m.frame_id for m in matrix.messages.values())
    return ids.index(matrix.message(message).frame_id) * PHASE_STEP_S


def frame_arrays(
    time_s: np.ndarray,
    signals: Mapping[str, np.ndarray],
    *,
    matrix: CanMatrix | None = None,
    start_time: float = 0.0,
    phases: Mapping[str, float] | None = None,
):
    """All frames of a run as arrays, in time order (the vectorised core of :func:`write_log`).

    Args:
        time_s: uniform, increasing base grid of the run (s).
        signals: catalogue name -> array on ``time_s`` (SI). Other names are ignored.
        matrix: CAN matrix (default: bundled).
        start_time: timestamp (s) of run time ``time_s[0]``.
        phases: message name -> transmit phase (s, ``0 <= phase < cycle``) overriding
            :func:`phase_offset`, e.g. to send right after a sensor's own update instants.

    Returns:
        ``(timestamps (n,), frame_ids (n,), data (n, 8) uint8, per_message_counts)``.
    """
    matrix = matrix or CanMatrix.load()
    time_s = np.asarray(time_s, dtype=np.float64)
    if time_s.ndim != 1 or time_s.size == 0:
        raise ValueError("time_s must be a non-empty 1-D array")
    if time_s.size > 1 and not np.all(np.diff(time_s) > 0):
        raise ValueError("time_s must be strictly increasing")
    for name, arr in signals.items():
        if np.shape(arr) != time_s.shape:
            raise ValueError(f"signal {name!r} has shape {np.shape(arr)}, time_s has {time_s.shape}")
    span = float(time_s[-1] - time_s[0])
    ts_parts, id_parts, data_parts = [], [], []
    counts: dict[str, int] = {}
    for name, m in sorted(matrix.messages.items(), key=lambda kv: kv[1].frame_id):
        present = [c for c in m.catalogue_names if c in signals]
        if not present or m.cycle_s <= 0:
            continue
        phase = phase_offset(matrix, name) if phases is None or name not in phases else float(phases[name])
        if not 0.0 <= phase < m.cycle_s:
            raise ValueError(f"phase of {name} must be in [0, {m.cycle_s}) s, got {phase}")
        k = np.arange(int(np.floor((span - phase) / m.cycle_s + 1e-9)) + 1)
        rel = k * m.cycle_s + phase
        if rel.size == 0:
            continue
        idx = np.searchsorted(time_s, time_s[0] + rel + _GRID_TOL_S, side="right") - 1
        cols = {c: np.asarray(signals[c], dtype=np.float64)[idx] for c in present}
        data = matrix.encode_many(name, cols, counter_sequence(0, k.size))
        ts_parts.append(start_time + rel)
        id_parts.append(np.full(k.size, m.frame_id, dtype=np.int64))
        data_parts.append(data)
        counts[name] = int(k.size)
    if not ts_parts:
        return np.empty(0), np.empty(0, dtype=np.int64), np.empty((0, 8), dtype=np.uint8), counts
    ts = np.concatenate(ts_parts)
    order = np.argsort(ts, kind="stable")
    return ts[order], np.concatenate(id_parts)[order], np.concatenate(data_parts)[order], counts


def iter_frames(
    time_s: np.ndarray,
    signals: Mapping[str, np.ndarray],
    *,
    matrix: CanMatrix | None = None,
    start_time: float = 0.0,
    phases: Mapping[str, float] | None = None,
    channel=None,
) -> Iterator:
    """The frames of :func:`frame_arrays` as python-can ``Message`` objects, in time order."""
    import can

    ts, ids, data, _ = frame_arrays(
        time_s, signals, matrix=matrix, start_time=start_time, phases=phases
    )
    Message = can.Message
    for t, i, d in zip(ts.tolist(), ids.tolist(), data, strict=True):
        yield Message(
            timestamp=t,
            arbitration_id=i,
            is_extended_id=False,
            dlc=len(d),
            data=d.tobytes(),
            channel=channel,
            check=False,
        )


@dataclass
class LogSummary:
    """What :func:`write_log` wrote: path, total frames, frames per message, file size (bytes)."""

    path: Path
    frames: int
    per_message: dict[str, int]
    size_bytes: int


def write_log(
    path: str | os.PathLike,
    time_s: np.ndarray,
    signals: Mapping[str, np.ndarray],
    *,
    matrix: CanMatrix | None = None,
    start_time: float = 0.0,
    phases: Mapping[str, float] | None = None,
) -> LogSummary:
    """Write a run as a CAN log; the format follows the suffix (see :data:`CAN_LOG_SUFFIXES`).

    Args:
        path: output file (``.blf``, ``.asc``, ``.log``, ``.csv``, ``.trc``).
        time_s, signals, matrix, start_time, phases: see :func:`frame_arrays`
            (SI values under catalogue names on the base grid ``time_s`` in s).

    Note:
        BLF keeps absolute time only for ``start_time`` 0 or after 1990
        (python-can writes no start date before that); either way
        :func:`read_log` measures time from the first frame.
    """
    import can

    path = Path(path)
    _check_suffix(path)
    matrix = matrix or CanMatrix.load()
    ts, ids, data, counts = frame_arrays(
        time_s, signals, matrix=matrix, start_time=start_time, phases=phases
    )
    try:
        writer = can.Logger(path)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot write the log: {exc}") from None
    Message = can.Message
    try:
        on_msg = writer.on_message_received
        for t, i, d in zip(ts.tolist(), ids.tolist(), data, strict=True):
            on_msg(
                Message(
                    timestamp=t, arbitration_id=i, is_extended_id=False, dlc=8, data=d.tobytes(), check=False
                )
            )
    finally:
        writer.stop()
    return LogSummary(path, int(ts.size), counts, path.stat().st_size)


# ------------------------------------------------------------------------------------------- reading
class _GarbageLine(Exception):
    pass


_ASC_HEADER = re.compile(
    r"^(date\s|base\s|(no\s+)?internal\s+events|begin\s+triggerblock|end\s+triggerblock)", re.IGNORECASE
)
_ASC_EVENT = re.compile(r"^\d+\.\d+\s")
_CANDUMP = re.compile(r"^\(\d+(\.\d+)?\)\s+\S+\s+[0-9A-Fa-f]{1,8}#")


def _asc_ok(line: str) -> bool:
    s = line.strip()
    return not s or s.startswith("//") or bool(_ASC_HEADER.match(s)) or bool(_ASC_EVENT.match(s))


def _candump_ok(line: str) -> bool:
    s = line.strip()
    return not s or bool(_CANDUMP.match(s))


class _Lines:
    """Text file iterator that counts lines and rejects garbage ones (for error positions)."""

    def __init__(self, f, check) -> None:
        self._f = f
        self._check = check
        self.lineno = 0

    def __iter__(self):
        return self

    def __next__(self) -> str:
        line = next(self._f)
        self.lineno += 1
        if self._check is not None and not self._check(line):
            raise _GarbageLine(f"unparsable line {line.strip()[:60]!r}")
        return line

    def readline(self) -> str:
        try:
            return self.__next__()
        except StopIteration:
            return ""

    def read(self, *args):  # pragma: no cover - readers iterate lines
        return self._f.read(*args)

    def close(self) -> None:
        self._f.close()

    @property
    def closed(self) -> bool:
        return self._f.closed


def _blf_truncation(path: Path, reader) -> str | None:
    expected = int(getattr(reader, "file_size", 0) or 0)
    actual = path.stat().st_size
    if expected > actual:
        return (
            f"truncated: the BLF header says {expected} bytes, the file has {actual} "
            f"(data ends at byte offset {actual})"
        )
    return None


def _check_whole(path: Path, real: str, gz: bool) -> None:
    """Refuse, before reading frames, a log that cannot be whole: empty, a 20 Hz table named ``.csv``, binary data
    named as a text log, a text log cut short (:func:`_text_cut`), or a gzip-compressed one whose compressed data
    is cut, corrupt or not gzip at all (read through once to know: :func:`_text_ends`)."""
    if path.stat().st_size == 0:
        raise UserError(f"{path}: the file is empty (no {real} CAN log in it)")
    if real not in _TEXT_SUFFIXES:
        return
    head, tail, lines = _text_ends(path, real, gz)
    if real == ".csv" and _is_table(head):
        raise UserError(f"{path}: a 20 Hz table (first column time_s), not a CAN log (python-can's CSV log starts "
                        "with timestamp,arbitration_id): write the run as a CAN log (virtsensor simulate ... --out "
                        "x.blf) to play it")
    if not _looks_like_text(head):
        raise UserError(f"{path}: not a {real} CAN log: binary data, not UTF-8 text")
    cut = _text_cut(path, real, tail, lines)
    if cut is not None:
        raise UserError(f"{path}: truncated: {cut[1]}; {_last_good(path, real, cut[0], gz)}")


#: How much of a text log's beginning :func:`_looks_like_text` and :func:`_is_table` judge, and of its end
#: :func:`_text_cut` (bytes).
_HEAD_BYTES, _TAIL_BYTES = 1 << 16, 4096


def _open_text(path: Path, gz: bool):
    """``path`` opened as UTF-8 text (universal newlines), through gzip when ``gz``."""
    if gz:
        import gzip

        return gzip.open(path, "rt", encoding="utf-8", newline=None)
    return open(path, encoding="utf-8", newline=None)  # noqa: SIM115 - the caller closes it


def _text_ends(path: Path, real: str, gz: bool) -> tuple[bytes, bytes, int | None]:
    """The first :data:`_HEAD_BYTES` and the last :data:`_TAIL_BYTES` of a text log's text, and its number of line
    ends when known (None: count them when needed). A ``.gz`` log is decompressed through once, a block at a time,
    which counts its line ends and proves its compressed data whole.

    Raises:
        UserError: compressed data that is not gzip, corrupt, or cut (naming the line it ends in and the last
            good frame before it).
    """
    if not gz:
        with open(path, "rb") as f:
            head = f.read(_HEAD_BYTES)
            f.seek(max(0, path.stat().st_size - _TAIL_BYTES))
            return head, f.read(), None
    import gzip
    import zlib

    head, tail, lines = b"", b"", 0
    try:
        with gzip.open(path, "rb") as f:
            # read1: what was decompressed is returned before the EOFError of a cut stream, never dropped with it
            for block in iter(lambda: f.read1(1 << 16), b""):
                head = head if len(head) >= _HEAD_BYTES else head + block[:_HEAD_BYTES - len(head)]
                tail = (tail + block)[-_TAIL_BYTES:]
                lines += block.count(b"\n")
    except EOFError:
        where = f"after line {lines}" if tail.endswith(b"\n") or not tail else f"inside line {lines + 1}"
        raise UserError(f"{path}: truncated: the gzip stream is cut, its text ends {where}; "
                        f"{_last_good(path, real, lines + 1, gz)}") from None
    except (gzip.BadGzipFile, zlib.error, OSError) as exc:
        with open(path, "rb") as f:
            gzipped = f.read(2) == b"\x1f\x8b"
        what = f"corrupt compressed data after line {lines}" if gzipped else "not gzip-compressed"
        raise UserError(f"{path}: not a {real}.gz CAN log: {what} ({type(exc).__name__}: {exc})") from None
    return head, tail, lines


def _looks_like_text(head: bytes) -> bool:
    """Whether ``head``, the beginning of a file, is UTF-8 text without NUL bytes (a character cut at the end of
    the sample is allowed)."""
    if b"\0" in head:
        return False
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        return exc.start >= len(head) - 3 and exc.reason == "unexpected end of data"
    return True


def _text_cut(path: Path, real: str, tail: bytes, lines: int | None) -> tuple[int, str] | None:
    """Where a text log was cut: ``(first line not read, why)``, or None when it is whole.

    ``tail`` is the end of its text, ``lines`` its number of line ends (None: counted here, when needed). A last
    line without its end of line is a record cut in the middle; an ASC log without its closing
    ``End TriggerBlock`` line stopped before its writer closed it.
    """
    if not tail:
        return None
    whole_asc = real == ".asc" and tail.rstrip().lower().endswith(b"end triggerblock")
    if whole_asc or (real != ".asc" and tail.endswith(b"\n")):
        return None
    if lines is None:
        with open(path, "rb") as f:
            lines = sum(block.count(b"\n") for block in iter(lambda: f.read(1 << 20), b""))
    if not tail.endswith(b"\n"):
        return lines + 1, f"line {lines + 1} is cut mid-record (the file ends inside it)"
    return lines + 1, f"it ends at line {lines} without its 'End TriggerBlock' line (the log was not closed)"


def _last_good(path: Path, real: str, stop_line: int, gz: bool = False) -> str:
    """The last frame read intact before text line ``stop_line`` (through gzip when ``gz``), for messages."""
    import logging

    from can.io.player import MESSAGE_READERS

    lines = _Lines(_open_text(path, gz), None)
    n, first, last = 0, 0.0, 0.0
    log = logging.getLogger("can")
    level = log.level
    log.setLevel(logging.ERROR)  # python-can warns about the cut line: the message says it already
    try:
        for msg in MESSAGE_READERS[real](file=lines):  # type: ignore[arg-type]
            if lines.lineno >= stop_line:
                break
            first = msg.timestamp if n == 0 else first
            last, n = msg.timestamp, n + 1
    except Exception:  # noqa: BLE001 - what is readable before the cut is all that is wanted
        pass
    finally:
        log.setLevel(level)
        lines.close()
    if n == 0:
        return "no frame before it is complete"
    return (f"the last good frame is frame {n - 1}, timestamp {last:.6f} s "
            f"({last - first:.3f} s after the first frame)")


#: python-can's loggers of the log readers :func:`iter_log` uses
_READER_LOGGERS = ("can.io.trc", "can.io.asc", "can.io.canutils", "can.io.blf")


class _ReaderWarnings(logging.Filter):
    """Keeps python-can's reader warnings off stderr while :func:`iter_log` reads (records of this thread only):
    our errors are one line. A line the reader could not parse (python-can warns and skips it, dropping a frame)
    is kept in ``skipped`` as ``(line number, text)`` so that the read fails instead; an empty one (what an
    empty file gives) is not a frame. The reader's other warnings (an ASC frame whose DLC and data length
    differ, say) are dropped too: the frame itself is still yielded, and the decoder counts it as a length
    error. Installed on creation; :meth:`remove` takes it off."""

    def __init__(self, lines: _Lines | None) -> None:
        super().__init__()
        self._thread = threading.get_ident()
        self._lines = lines
        self.skipped: tuple[int, str] | None = None
        for name in _READER_LOGGERS:
            logging.getLogger(name).addFilter(self)

    def filter(self, record: logging.LogRecord) -> bool:
        if record.thread != self._thread or record.levelno < logging.WARNING:
            return True
        args = record.args if isinstance(record.args, tuple) else ()
        if "Failed to parse" in str(record.msg) and args and str(args[0]).strip() and self.skipped is None:
            self.skipped = (self._lines.lineno if self._lines is not None else 0, str(args[0]))
        return False

    def remove(self) -> None:
        for name in _READER_LOGGERS:
            logging.getLogger(name).removeFilter(self)


def _is_table(head: bytes) -> bool:
    """Whether a text file beginning with ``head`` starts as a canonical table does (its header's first column
    ``time_s``)."""
    first = head[:4096].split(b"\n", 1)[0].decode("utf-8", errors="replace")
    return first.lstrip("\ufeff").split(",", 1)[0].strip() == "time_s"


def iter_log(path: str | os.PathLike) -> Iterator:
    """Yield the python-can ``Message`` objects of a log file, in file order.

    Raises:
        UserError: missing file, unknown format, or a read failure, naming the
            file, the frame index and the line number (text) or byte offset (BLF);
            a frame stamped more than :data:`~virtsensor.frontend.MAX_BACK_S` before
            the latest one before it (its time goes back), naming the frame.
    """
    import can
    from can.io.player import MESSAGE_READERS

    path = Path(path)
    _check_suffix(path)
    if not path.is_file():
        raise UserError(f"{path}: no such log file")
    real, gz = _suffix(path)
    _check_whole(path, real, gz)
    lines: _Lines | None = None
    try:
        if real in _TEXT_SUFFIXES:
            raw = _open_text(path, gz)
            check = {".asc": _asc_ok, ".log": _candump_ok}.get(real)
            lines = _Lines(raw, check)
            reader = MESSAGE_READERS[real](file=lines)
        else:
            reader = can.LogReader(path)
    except Exception as exc:  # python-can raises BLFParseError, ValueError, struct.error ...
        raise UserError(f"{path}: not a readable {real} CAN log: {type(exc).__name__}: {exc}") from None
    if real == ".blf":
        problem = _blf_truncation(path, reader)
        if problem:
            n, first, last = 0, 0.0, 0.0
            try:
                for msg in reader:
                    first = msg.timestamp if n == 0 else first
                    last, n = msg.timestamp, n + 1
            except Exception:  # noqa: BLE001 - only counting what is readable
                pass
            good = "no frame is readable" if n == 0 else (
                f"frames 0..{n - 1} are readable (the last good one at timestamp {last:.6f} s, "
                f"{last - first:.3f} s after the first frame), frame {n} is cut")
            raise UserError(f"{path}: {problem}; {good}")
    index = 0
    quiet = _ReaderWarnings(lines)
    latest = -math.inf
    try:
        for msg in reader:
            if quiet.skipped is not None:
                break
            t = float(msg.timestamp)
            if t < latest - MAX_BACK_S:
                at = f" at line {lines.lineno}" if lines is not None else ""
                raise UserError(f"{path}: frame {index}{at} goes back in time {latest - t:.6g} s, from {latest:.6f} s "
                                f"to {t:.6f} s (frames may be out of order by {MAX_BACK_S * 1e3:g} ms at most: a "
                                f"logger's clock set back, or two logs joined?)")
            latest = max(latest, t)
            yield msg
            index += 1
    except UserError:
        raise
    except Exception as exc:  # noqa: BLE001 - translated into one line naming the position
        if lines is not None:
            where = f"line {lines.lineno}"
        else:
            try:
                where = f"byte offset {reader.file.tell()}"
            except Exception:  # noqa: BLE001
                where = "unknown byte offset"
        detail = str(exc) if isinstance(exc, _GarbageLine) else f"{type(exc).__name__}: {exc}"
        raise UserError(f"{path}: cannot read frame {index} at {where}: {detail}") from None
    finally:
        quiet.remove()
        try:
            reader.stop()
        except Exception:  # noqa: BLE001
            pass
    if quiet.skipped is not None:
        line, text = quiet.skipped
        raise UserError(f"{path}: cannot read frame {index} at line {line}: unparsable line {text.strip()[:60]!r}")


@dataclass
class Recording:
    """A CAN log read back (see :func:`read_log`).

    Attributes:
        path: the file.
        table: canonical table: ``time_s`` (s since the first frame) then SI columns.
        signals: the table's signal columns (catalogue names).
        frames: frames decoded (in the DBC); unknown_frames: frames not in the DBC;
        skipped_frames: error/remote frames.
        e2e: message -> E2E status name -> count.
        dropped_ticks: leading ticks dropped before every signal was seen.
        missing_signals: requested (or default) signals never received.
        start_time: timestamp (s) of the first frame in the log's clock; duration_s: last - first.
        rate_hz: table rate.
    """

    path: Path
    table: dict[str, np.ndarray]
    signals: tuple[str, ...]
    frames: int
    unknown_frames: int
    skipped_frames: int
    e2e: dict[str, dict[str, int]]
    dropped_ticks: int
    missing_signals: tuple[str, ...]
    start_time: float
    duration_s: float
    rate_hz: float
    counts_by_status: dict[str, int] = field(default_factory=dict)

    @property
    def e2e_errors(self) -> int:
        """Frames whose E2E status is not OK (ERROR, REPEATED, OKSOMELOST, WRONGSEQUENCE)."""
        return sum(n for st, n in self.counts_by_status.items() if st != "OK")

    def count(self, status: str | E2EStatus, message: str | None = None) -> int:
        """Frames with E2E ``status`` (name or enum), over all messages or one."""
        name = status.name if isinstance(status, E2EStatus) else str(status)
        if message is None:
            return self.counts_by_status.get(name, 0)
        return self.e2e.get(message, {}).get(name, 0)


def read_log(
    path: str | os.PathLike,
    *,
    matrix: CanMatrix | None = None,
    rate_hz: float = 20.0,
    signals: Sequence[str] | None = None,
    t0: float = 0.0,
) -> Recording:
    """Read a CAN log and build the canonical table with the front-end.

    Args:
        path: log file (any :data:`CAN_LOG_SUFFIXES`).
        matrix: CAN matrix (default bundled); a fresh E2E state is used either way.
        rate_hz: table rate (Hz).
        signals: catalogue names of the columns; all must occur in the log
            (UserError otherwise). Default: those of ``TABLE_COLUMNS`` (inputs,
            then reference outputs) that occur in the log.
        t0: first tick, in seconds after the first frame.

    Returns:
        :class:`Recording`.

    Raises:
        UserError: an unreadable, cut or malformed log (:func:`iter_log`), a requested signal never
            received intact, no frame of the matrix, or a time that is not one run's
            (:func:`virtsensor.frontend.time_problem`), naming the file.
    """
    path = Path(path)
    return decode_recording(iter_log(path), path, matrix=matrix, rate_hz=rate_hz, signals=signals, t0=t0)


def simulated_recording(
    time_s: np.ndarray,
    signals: Mapping[str, np.ndarray],
    *,
    matrix: CanMatrix | None = None,
    rate_hz: float = 20.0,
) -> Recording:
    """What a receiver on the bus makes of a simulated run: its sensor streams are
    encoded into frames exactly as :func:`write_log` writes them, decoded with the
    E2E checks and sampled by the front-end. The simulator's canonical table is
    built this way, so a table and the log of the same run agree frame for frame,
    and training sees the signals as the runtime will."""
    frames = iter_frames(time_s, signals, matrix=matrix)
    return decode_recording(frames, Path("<simulated>"), matrix=matrix, rate_hz=rate_hz)


_TPMS_MESSAGE = "TPMS_Pressures"


class _TpmsTrack:
    """The TPMS frames of a log, kept apart from the table's inputs: they are slow (1 frame/s) and optional, so
    they neither delay the table's first row nor are required. A wheel whose sensor reports SNA ("sensor
    missing") is NaN from that frame on, not its last value held."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.rows: list[tuple[float, ...]] = []

    def add(self, d: Any) -> None:
        if d.status not in USABLE:
            return
        self.t.append(float(d.timestamp))
        self.rows.append(tuple(float(d.values.get(s, math.nan)) for s in cat.TPMS_SIGNALS))

    def sample(self, ticks: np.ndarray) -> dict[str, np.ndarray]:
        """Sample-and-hold at the table's absolute ``ticks`` (s, log clock): NaN before the first frame (pressure
        unknown). No TPMS frame at all: no column (a car or a recording without TPMS)."""
        if not self.t:
            return {}
        t = np.asarray(self.t)
        v = np.asarray(self.rows, dtype=np.float64)
        order = np.argsort(t, kind="stable")
        idx = np.searchsorted(t[order], ticks + TIME_TOLERANCE_S, side="right") - 1
        vals = np.where((idx >= 0)[:, None], v[order][np.maximum(idx, 0)], math.nan)
        return {s: vals[:, i] for i, s in enumerate(cat.TPMS_SIGNALS)}


def decode_recording(
    frames: Iterable,
    path: Path,
    *,
    matrix: CanMatrix | None = None,
    rate_hz: float = 20.0,
    signals: Sequence[str] | None = None,
    t0: float = 0.0,
) -> Recording:
    """Decode raw CAN frames (python-can messages) through the DBC and the front-end.

    ``path`` names the source in messages and in the result. See :func:`read_log`.
    """
    matrix = (matrix or CanMatrix.load()).fresh()
    counts: dict[str, int] = {}
    e2e: dict[str, dict[str, int]] = {}

    def decoded():
        for d in matrix.decode_all(frames, counts):
            per = e2e.get(d.message)
            if per is None:
                per = e2e[d.message] = {}
            name = d.status.name
            per[name] = per.get(name, 0) + 1
            if tpms is not None and d.message == _TPMS_MESSAGE:
                tpms.add(d)
            yield d

    wanted = tuple(signals) if signals is not None else tuple(cat.TABLE_COLUMNS[1:])
    tpms = _TpmsTrack() if signals is None else None
    for s in wanted:
        if s not in cat.SIGNALS:
            raise UserError(f"{path}: unknown signal {s!r} requested")
    col = collect(decoded(), wanted)
    missing = tuple(s for s in wanted if not col.times[s])
    if signals is not None and missing:
        raise UserError(
            f"{path}: signal(s) never received intact: {', '.join(missing)} "
            f"(messages {', '.join(sorted({str(matrix.message_of(s)) for s in missing}))})"
        )
    used = tuple(s for s in wanted if s not in missing)
    n_frames = sum(sum(v.values()) for v in e2e.values())
    if not np.isfinite(col.t_first):
        raise UserError(
            f"{path}: no frame of the CAN matrix in this log ({counts.get('unknown', 0)} unknown frames)"
        )
    build: TableBuild = table_from_collected(col, used, rate_hz, col.t_first + t0, source=str(path),
                                             max_age=_timeouts(matrix, used))
    table = dict(build.table)
    if tpms is not None:
        table.update(tpms.sample(np.asarray(build.table["time_s"], dtype=np.float64)))
    k = np.arange(build.dropped_ticks, build.ticks)
    table["time_s"] = t0 + k / rate_hz
    by_status: dict[str, int] = {}
    for per in e2e.values():
        for st, n in per.items():
            by_status[st] = by_status.get(st, 0) + n
    return Recording(
        path=path,
        table=table,
        signals=used,
        frames=n_frames,
        unknown_frames=counts.get("unknown", 0),
        skipped_frames=counts.get("skipped", 0),
        e2e=e2e,
        dropped_ticks=build.dropped_ticks,
        missing_signals=missing,
        start_time=float(col.t_first),
        duration_s=float(col.t_last - col.t_first),
        rate_hz=rate_hz,
        counts_by_status=by_status,
    )


def _timeouts(matrix: CanMatrix, signals: Sequence[str]) -> dict[str, float]:
    """Per signal the oldest value (s) a tick may hold: :data:`~virtsensor.signals.INPUT_TIMEOUT_CYCLES` cycles of
    its message (messages without a cycle time: no limit), the daemon's freshness rule."""
    out = {}
    for s in signals:
        m = matrix.message_of(s)
        cycle = matrix.messages[m].cycle_s if m is not None else 0.0
        if cycle > 0:
            out[s] = cat.INPUT_TIMEOUT_CYCLES * cycle
    return out


# ---------------------------------------------------------------------------------------------- CSV
def write_csv(path: str | os.PathLike, table: Mapping[str, np.ndarray]) -> None:
    """Write a canonical table as CSV: header = column names, rows of shortest round-trip floats."""
    path = Path(path)
    names = list(table)
    if not names:
        raise ValueError("empty table")
    n = len(np.asarray(table[names[0]]))
    for k in names:
        if len(np.asarray(table[k])) != n:
            raise ValueError(f"column {k!r} has {len(np.asarray(table[k]))} rows, expected {n}")
    mat = np.column_stack([np.asarray(table[k], dtype=np.float64) for k in names]) if n else np.empty((0, 0))
    with open(path, "w", encoding="utf-8", newline="\n") as f:
        f.write(",".join(names) + "\n")
        rep = float.__repr__
        for row in mat.tolist():
            f.write(",".join(map(rep, row)) + "\n")


def read_csv(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a canonical table written by :func:`write_csv` (dict of float arrays, file column order).

    Raises:
        UserError: naming the file and line of a malformed header or row, of a blank line between rows, or of a
            last row the file ends inside (cut mid-row), with the last good row.
    """
    path = Path(path)
    with io.StringIO(_utf8_text(path), newline=None) as f:
        header = f.readline().strip()
        if not header:
            raise UserError(f"{path}:1: empty file, expected a header of signal names")
        names = [h.strip() for h in header.split(",")]
        for h in names:
            if h not in cat.SIGNALS:
                raise UserError(f"{path}:1: unknown column {h!r} (not a catalogue signal name)")
        if len(set(names)) != len(names):
            raise UserError(f"{path}:1: duplicate column names in the header")
        rows: list[list[float]] = []
        width = len(names)
        blank = 0  # (the latest blank line: blank lines end a table, none lies between its rows)
        for lineno, line in enumerate(f, start=2):
            s = line.strip()
            if not s:
                blank = blank or lineno
                continue
            if blank:
                raise UserError(f"{path}:{blank}: a blank line between rows (a table has one row on every line, "
                                "so that the line of a row is its number plus one)")
            if not line.endswith("\n"):
                raise UserError(f"{path}:{lineno}: truncated: the file ends inside this row; "
                                f"{_last_good_row(names, rows)} (a complete file ends with a newline)")
            parts = s.split(",")
            if len(parts) != width:
                raise UserError(f"{path}:{lineno}: expected {width} fields, got {len(parts)}")
            try:
                rows.append([float(p) for p in parts])
            except ValueError:
                col = next(k for k, p in enumerate(parts) if not _is_float(p))
                raise UserError(f"{path}:{lineno}: column {names[col]}: {parts[col].strip()!r} is not a "
                                "number") from None
    mat = np.array(rows, dtype=np.float64).reshape(len(rows), width)
    return {n: mat[:, i].copy() for i, n in enumerate(names)}


def _utf8_text(path: Path) -> str:
    """The text of a CSV table; a file that cannot be read or is not UTF-8 (a binary file, a CAN log renamed
    ``.csv``, a Latin-1 header) is a UserError naming the file, the line and the byte offset."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise UserError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        return raw.decode("utf-8-sig")  # (a byte-order mark, as spreadsheets write "CSV UTF-8", is no column name)
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise UserError(f"{path}:{line}: not UTF-8 text (byte 0x{raw[exc.start]:02x} at byte offset {exc.start}); "
                        f"a CSV table is UTF-8 text (a binary file or a CAN log named .csv?)") from None


def _last_good_row(names: Sequence[str], rows: Sequence[Sequence[float]]) -> str:
    if not rows:
        return "no row before it"
    at = f", time_s {rows[-1][names.index('time_s')]:.6g} s" if "time_s" in names else ""
    return f"the last good row is line {len(rows) + 1}{at}"


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
