"""The one CAN codec: DBC tables, and the generated per-message encoders and decoders behind them.

Values cross this module's boundary in the catalogue's SI units under their
catalogue names (``tyre_pressure_fl_pa`` in Pa); the DBC may carry another
unit (bar for the TPMS pressures) and the conversion is done here, once (factors from
:data:`virtsensor.canbus.dbcgen.UNIT_CONVERSIONS`). Frames are 8-byte classic
CAN frames protected with AUTOSAR E2E Profile 11 as described in
:mod:`virtsensor.canbus.e2e`.

The DBC is read once with cantools and compiled into immutable tables
(:class:`MessageCodec`, :class:`SignalCodec`). From those tables this module
writes, once per message, small Python functions with every constant (byte
count, CRC seed, bit positions, masks, sign bits, scale, offset, ranges, SNA
codes) inlined, and compiles them with :func:`exec`: no per-frame attribute
look-ups, loops over signals, or per-signal branches on the signal's kind.
One generator (:func:`raw_expr`, the CRC chain, the per-signal decode) serves

* :meth:`MessageCodec.encode` / :func:`compile_encoder` -- the senders
  (simulator recordings, replay, the daemon's SAT_FRONT and VS_Health);
* :meth:`CanMatrix.decode` -- one frame to a :class:`DecodedFrame`;
* :func:`compile_receiver` -- the daemon's receive path: one frame straight
  into its sample-and-hold lists.

The E2E receiver state (:class:`~virtsensor.canbus.e2e.E2EReceiver`, one per
message) lives in a :class:`CanMatrix` instance, apart from the tables, which
instances share. Only Intel (little-endian) integer signals without
multiplexing are supported.

Where the DBC comes from (:meth:`CanMatrix.load` with ``path=None``): the bundled
``virtsensor.dbc`` (package data, :func:`virtsensor.assets.dbc_path`), generated from the
catalogue by :mod:`virtsensor.canbus.dbcgen` (a test keeps the file identical to the generated text).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Iterable, Mapping, MutableMapping, MutableSequence, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import signals as cat
from virtsensor.assets import dbc_path
from virtsensor.canbus.dbcgen import UNIT_CONVERSIONS
from virtsensor.canbus.e2e import (
    COUNTER_MODULO,
    CRC8_TABLE,
    P11_CRC_XOROUT,
    USABLE,
    E2EReceiver,
    E2EStatus,
    crc8_register,
    data_id_seed,
)
from virtsensor.errors import UserError
from virtsensor.heldlog import held_records

__all__ = [
    "DEFAULT_DBC",
    "STATUS_KEYS",
    "CanMatrix",
    "DecodedFrame",
    "MessageCodec",
    "SignalCodec",
    "compile_encoder",
    "compile_receiver",
    "crc_ok_expr",
    "raw_expr",
]

#: The bundled DBC (package data ``virtsensor.assets.dbc``, the repository's ``dbc/virtsensor.dbc``).
DEFAULT_DBC = dbc_path()

class SignalCodec:
    """Compiled facts of one DBC signal (Intel byte order).

    Attributes:
        name: DBC signal name; catalogue: catalogue name or None.
        start, length, signed, mask: bit position and raw format.
        scale, offset: DBC physical = raw * scale + offset (DBC unit).
        si_factor: DBC physical = SI * si_factor (1 unless the DBC unit differs).
        raw_lo, raw_hi: raw clip range = the DBC ``minimum..maximum``.
        lo_si, hi_si: plausible SI range (catalogue range) for decoded values.
        sna: raw code of "signal not available" (None: none).
        unit: DBC unit.
    """

    __slots__ = (
        "name",
        "catalogue",
        "start",
        "length",
        "signed",
        "mask",
        "scale",
        "offset",
        "si_factor",
        "raw_lo",
        "raw_hi",
        "lo_si",
        "hi_si",
        "sna",
        "unit",
        "resolution_si",
    )

    def __init__(
        self,
        name: str,
        catalogue: str | None,
        start: int,
        length: int,
        signed: bool,
        scale: float,
        offset: float,
        si_factor: float,
        raw_lo: int,
        raw_hi: int,
        lo_si: float,
        hi_si: float,
        sna: int | None,
        unit: str,
    ) -> None:
        self.name = name
        self.catalogue = catalogue
        self.start = start
        self.length = length
        self.signed = signed
        self.mask = (1 << length) - 1
        self.scale = scale
        self.offset = offset
        self.si_factor = si_factor
        self.raw_lo = raw_lo
        self.raw_hi = raw_hi
        self.lo_si = lo_si
        self.hi_si = hi_si
        self.sna = sna
        self.unit = unit
        #: the step the frame carries, in SI units
        self.resolution_si = scale / si_factor


class MessageCodec:
    """Compiled facts of one DBC message.

    Attributes:
        name, frame_id, length (bytes), sender, cycle_s (``GenMsgCycleTime``/1000),
        data_id (E2E), seed (CRC register after the data ID),
        signals: the payload signals (without CRC and counter), in bit order;
        catalogue_names: catalogue names of the signals that have one;
        encode: the generated ``encode(values, counter) -> bytes`` (:func:`compile_encoder`);
        decode_frame: the generated ``decode_frame(data, t, check) -> DecodedFrame`` behind
            :meth:`CanMatrix.decode` (``check`` is the message's :meth:`E2EReceiver.check`).
    """

    __slots__ = (
        "name",
        "frame_id",
        "length",
        "sender",
        "cycle_s",
        "data_id",
        "seed",
        "signals",
        "catalogue_names",
        "_keys",
        "_by_key",
        "encode",
        "decode_frame",
    )

    def __init__(
        self,
        name: str,
        frame_id: int,
        length: int,
        sender: str,
        cycle_s: float,
        data_id: int,
        signals: tuple[SignalCodec, ...],
    ) -> None:
        self.name = name
        self.frame_id = frame_id
        self.length = length
        self.sender = sender
        self.cycle_s = cycle_s
        self.data_id = data_id
        self.seed = data_id_seed(data_id)
        self.signals = signals
        self.catalogue_names = tuple(s.catalogue for s in signals if s.catalogue)
        self._keys = tuple((s.catalogue, s.name, s) for s in signals)
        self._by_key = {**{s.name: s for s in signals}, **{s.catalogue: s for s in signals if s.catalogue}}
        self.encode: Callable[[Mapping[str, float], int], bytes] = compile_encoder(self)
        self.decode_frame: Callable[[bytes | bytearray, float, Callable[..., E2EStatus]], DecodedFrame] = (
            _compile_frame_decoder(self)
        )


class DecodedFrame:
    """One received frame after DBC decoding and the E2E check.

    Attributes:
        message: DBC message name; frame_id; timestamp: receive time (s).
        counter: received alive counter (-1 when the length was wrong).
        crc_ok: CRC matched; dlc_ok: payload length equals the DBC length.
        status: :class:`~virtsensor.canbus.e2e.E2EStatus` of the message's Profile 11 check.
        values: catalogue name -> SI value, for intact frames only, without SNA and
            implausible (out of catalogue range) values.
        other: DBC name -> DBC physical value of the signals without a catalogue
            name (SAT_FRONT estimates and statuses, VS_Health fields); SNA -> nan.
        unavailable: catalogue names received as SNA; implausible: catalogue names out of range.
    """

    __slots__ = (
        "message",
        "frame_id",
        "timestamp",
        "counter",
        "crc_ok",
        "dlc_ok",
        "status",
        "values",
        "other",
        "unavailable",
        "implausible",
    )

    def __init__(
        self,
        message: str,
        frame_id: int,
        timestamp: float,
        counter: int,
        crc_ok: bool,
        dlc_ok: bool,
        status: E2EStatus,
        values: dict[str, float],
        other: dict[str, float],
        unavailable: tuple[str, ...],
        implausible: tuple[str, ...],
    ) -> None:
        self.message = message
        self.frame_id = frame_id
        self.timestamp = timestamp
        self.counter = counter
        self.crc_ok = crc_ok
        self.dlc_ok = dlc_ok
        self.status = status
        self.values = values
        self.other = other
        self.unavailable = unavailable
        self.implausible = implausible

    @property
    def usable(self) -> bool:
        """The values are fresh and intact (E2E status OK or OKSOMELOST)."""
        return self.status in USABLE

    def __repr__(self) -> str:
        return (
            f"DecodedFrame({self.message} t={self.timestamp:.6f} ctr={self.counter} "
            f"{self.status.name} values={self.values} other={self.other})"
        )


_CACHE: dict[tuple[str, float], tuple[object, dict[str, MessageCodec], str]] = {}
_NP_TABLE = np.frombuffer(CRC8_TABLE, dtype=np.uint8)


def _e2e_data_id(m, source: str) -> int:
    """The E2E data ID of cantools message ``m``, after checking its Profile 11 header (CRC bits 0..7,
    counter bits 8..11)."""
    names = {s.name: s for s in m.signals}
    crc, ctr = names.get(f"{m.name}_CRC"), names.get(f"{m.name}_Counter")
    if crc is None or ctr is None or (crc.start, crc.length) != (0, 8) or (ctr.start, ctr.length) != (8, 4):
        raise UserError(
            f"{source}: message {m.name} lacks {m.name}_CRC at bits 0..7 and "
            f"{m.name}_Counter at bits 8..11 (E2E layout)"
        )
    attr = m.dbc.attributes.get("E2E_DataID") if m.dbc is not None else None
    if attr is not None:
        return int(attr.value)
    if m.name in cat.MESSAGES:
        return cat.MESSAGES[m.name].data_id
    raise UserError(f"{source}: message {m.name} has no E2E_DataID attribute and is not catalogued")


def _signal_codec(m, s, cname: str | None, source: str) -> SignalCodec:
    """The :class:`SignalCodec` of cantools signal ``s`` of message ``m`` carrying catalogue signal
    ``cname`` (None: none), with the unit factor, raw clip range and SNA code checked."""
    where = f"{source}: {m.name}.{s.name}"
    if s.byte_order != "little_endian":
        raise UserError(f"{where}: only Intel (little-endian) signals are supported")
    if m.is_multiplexed() or s.multiplexer_ids:
        raise UserError(f"{where}: multiplexed signals are not supported")
    if getattr(s, "is_float", False):
        raise UserError(f"{where}: float signals are not supported")
    scale, offset = float(s.scale), float(s.offset)
    unit = s.unit or ""
    factor = 1.0
    if cname is not None:
        spec = cat.SIGNALS[cname]
        if unit != spec.unit:
            conv = UNIT_CONVERSIONS.get(spec.unit)
            if conv is None or conv[0] != unit:
                raise UserError(f"{where} has unit {unit!r} but the catalogue's {cname} is in {spec.unit!r}")
            factor = conv[1]
        lo_si, hi_si = spec.minimum, spec.maximum
    else:
        lo_si, hi_si = -math.inf, math.inf
    lo = s.minimum if s.minimum is not None else -math.inf
    hi = s.maximum if s.maximum is not None else math.inf
    full_lo = -(1 << (s.length - 1)) if s.is_signed else 0
    full_hi = (1 << (s.length - 1)) - 1 if s.is_signed else (1 << s.length) - 1
    raw_lo = max(full_lo, math.ceil((lo - offset) / scale - 1e-6)) if math.isfinite(lo) else full_lo
    raw_hi = min(full_hi, math.floor((hi - offset) / scale + 1e-6)) if math.isfinite(hi) else full_hi
    sna = next((int(k) for k, v in (s.choices or {}).items() if str(v) == "SNA"), None)
    if sna is not None and raw_lo <= sna <= raw_hi:
        raise UserError(f"{where}: SNA code {sna} lies inside the signal range")
    return SignalCodec(s.name, cname, s.start, s.length, bool(s.is_signed), scale, offset, factor,
                       raw_lo, raw_hi, lo_si, hi_si, sna, unit)


def _compile(db, source: str) -> dict[str, MessageCodec]:
    """Build the :class:`MessageCodec` of every message of a cantools database."""
    where: dict[tuple[str, str], str] = {
        (s.message, s.dbc_signal): s.name for s in cat.SIGNALS.values() if s.message and s.dbc_signal
    }
    out: dict[str, MessageCodec] = {}
    for m in db.messages:
        if m.is_extended_frame:
            raise UserError(f"{source}: message {m.name}: extended (29-bit) ids are not supported")
        data_id = _e2e_data_id(m, source)
        header = (f"{m.name}_CRC", f"{m.name}_Counter")
        sigs = sorted(
            (_signal_codec(m, s, where.get((m.name, s.name)), source) for s in m.signals if s.name not in header),
            key=lambda x: x.start,
        )
        sender = m.senders[0] if m.senders else ""
        cycle_s = (m.cycle_time or 0) / 1000.0
        out[m.name] = MessageCodec(m.name, m.frame_id, m.length, sender, cycle_s, data_id, tuple(sigs))
    return out


def _load_db(path: Path | None):
    """(cantools db, compiled messages, source text) for ``path`` (None: bundled), cached."""
    import cantools

    path = DEFAULT_DBC if path is None else Path(path)
    try:
        key = (str(path.resolve()), os.stat(path).st_mtime)
    except OSError as exc:
        raise UserError(f"{path}: cannot read the DBC: {exc.strerror or exc}") from None
    if key not in _CACHE:
        # (cantools logs a message that replaces another by id: refused below, in one line)
        with held_records("cantools") as notes:
            try:
                db = cantools.database.load_file(str(path), database_format="dbc", strict=True)
            except Exception as exc:  # cantools raises ParseError, UnsupportedDatabaseFormatError, ...
                msg = " ".join(str(exc).split())
                msg = msg if len(msg) <= 240 else msg[:240] + "..."  # (the parser quotes the text it stopped at)
                raise UserError(f"{path}: not a valid DBC: {type(exc).__name__}: {msg}") from None
        _check_ids(db, str(path))
        for record in notes:  # (anything else cantools noted goes on as it would have)
            logging.getLogger(record.name).handle(record)
        _CACHE[key] = (db, _compile(db, str(path)), str(path))
    return _CACHE[key]


def _check_ids(db, source: str) -> None:
    """Refuse two messages with one frame id: a frame on it would be read as either, and the daemon would send
    its own frames on another ECU's id (cantools keeps the later one by id, with only a log line)."""
    first: dict[int, str] = {}
    for m in db.messages:
        other = first.setdefault(m.frame_id, m.name)
        if other != m.name:
            raise UserError(f"{source}: messages {other} and {m.name} share the frame id 0x{m.frame_id:03X} (one "
                            "id, one message)")


class CanMatrix:
    """A loaded CAN matrix with per-message E2E receiver state.

    Build it with :meth:`load`. The compiled tables are shared between
    instances; the E2E state is not (use one instance per receiver).

    Attributes:
        db: the cantools database (for tools that want it).
        source: where the DBC came from (path or ``<generated ...>``).
        messages: message name -> :class:`MessageCodec`.
        by_id: frame id -> :class:`MessageCodec`.
        receivers: message name -> :class:`~virtsensor.canbus.e2e.E2EReceiver` (the mutable E2E state).
    """

    def __init__(
        self,
        db,
        messages: dict[str, MessageCodec],
        source: str,
        *,
        max_delta: int = 3,
        timeout_cycles: float = 5.0,
    ) -> None:
        self.db = db
        self.source = source
        self.messages = messages
        self.by_id = {m.frame_id: m for m in messages.values()}
        self.max_delta = max_delta
        self.timeout_cycles = timeout_cycles
        self.receivers = {
            name: E2EReceiver(max_delta, timeout_cycles * m.cycle_s if m.cycle_s > 0 else math.inf)
            for name, m in messages.items()
        }
        self._rx_by_id = {m.frame_id: (m.decode_frame, self.receivers[m.name].check) for m in messages.values()}
        self._signal_message = {c: m.name for m in messages.values() for c in m.catalogue_names}

    @classmethod
    def load(
        cls, path: str | os.PathLike | None = None, *, max_delta: int = 3, timeout_cycles: float = 5.0
    ) -> CanMatrix:
        """Load a DBC (default: the bundled one, see the module docstring).

        Args:
            path: DBC file; None for the bundled matrix.
            max_delta: Profile 11 ``MaxDeltaCounter``, the largest counter delta still OKSOMELOST (1..14).
            timeout_cycles: reception timeout in message cycles (:meth:`E2EReceiver.poll`: NONEWDATA).

        Raises:
            UserError: naming the file and the cantools message when the DBC is
                unreadable or inconsistent with the catalogue.
        """
        db, msgs, source = _load_db(None if path is None else Path(path))
        return cls(db, msgs, source, max_delta=max_delta, timeout_cycles=timeout_cycles)

    def fresh(self) -> CanMatrix:
        """A new matrix sharing the compiled tables, with fresh E2E state."""
        return CanMatrix(
            self.db, self.messages, self.source, max_delta=self.max_delta, timeout_cycles=self.timeout_cycles
        )

    def reset(self) -> None:
        """Reset every E2E receiver to its initial state."""
        for r in self.receivers.values():
            r.reset()

    # ---------------------------------------------------------------- lookup
    def message(self, name: str) -> MessageCodec:
        """The compiled message ``name``; KeyError with the known names otherwise."""
        try:
            return self.messages[name]
        except KeyError:
            raise KeyError(
                f"message {name!r} is not in {self.source} (known: {', '.join(sorted(self.messages))})"
            ) from None

    def message_of(self, catalogue_name: str) -> str | None:
        """Name of the message carrying catalogue signal ``catalogue_name`` (None: not in this DBC)."""
        return self._signal_message.get(catalogue_name)

    def resolution(self, catalogue_name: str) -> float:
        """The SI step the frames carry ``catalogue_name`` with (may be coarser than the catalogue's)."""
        m = self.messages[self._signal_message[catalogue_name]]
        return next(s.resolution_si for s in m.signals if s.catalogue == catalogue_name)

    # ---------------------------------------------------------------- encode
    def encode(self, message_name: str, values: Mapping[str, float], counter: int) -> bytes:
        """Payload bytes of one frame (the message's generated encoder, :func:`compile_encoder`).

        Args:
            message_name: DBC message name.
            values: catalogue name -> SI value (or DBC signal name -> DBC physical
                value for signals without a catalogue name, e.g. ``SAT_FL_Status``).
                Keys of other messages are ignored; a signal that is missing or
                nan is sent as its SNA code (0 if it has none). Values are clipped
                to the signal's range.
            counter: alive counter, 0..14 (taken modulo 15; see
                :func:`~virtsensor.canbus.e2e.next_counter`).

        Returns:
            ``length`` bytes with CRC (byte 0) and counter (byte 1, bits 0..3) filled.
        """
        m = self.messages.get(message_name)
        if m is None:
            m = self.message(message_name)
        return m.encode(values, counter)

    def encode_many(
        self, message_name: str, columns: Mapping[str, np.ndarray], counters: np.ndarray
    ) -> np.ndarray:
        """Vectorised :meth:`encode` of ``n`` frames: returns an ``(n, length)`` uint8 array.

        ``columns`` maps names as in :meth:`encode` to arrays of length ``n``
        (missing names and nan -> SNA); ``counters`` are the ``n`` alive counters
        (taken modulo 15; :func:`~virtsensor.canbus.e2e.counter_sequence` makes them).
        """
        m = self.message(message_name)
        counters = np.asarray(counters, dtype=np.int64)
        n = counters.shape[0]
        payload = (counters % COUNTER_MODULO).astype(np.uint64) << np.uint64(8)
        for cname, dname, s in m._keys:
            col = columns.get(cname) if cname is not None else None
            if col is None:
                col = columns.get(dname)
            sna = s.sna if s.sna is not None else 0
            if col is None:
                raw = np.full(n, sna, dtype=np.int64)
            else:
                x = np.asarray(col, dtype=np.float64)
                bad = np.isnan(x)
                r = np.round((np.where(bad, 0.0, x) * s.si_factor - s.offset) / s.scale)
                raw = np.clip(r, s.raw_lo, s.raw_hi).astype(np.int64)
                raw[bad] = sna
            payload |= (raw & s.mask).astype(np.uint64) << np.uint64(s.start)
        data = payload.astype("<u8").view(np.uint8).reshape(n, 8)[:, : m.length].copy()
        seed = np.full(n, m.seed, dtype=np.uint8)
        columns_1_on = (data[:, i] for i in range(1, m.length))
        data[:, 0] = crc8_register(seed, columns_1_on, _NP_TABLE) ^ P11_CRC_XOROUT
        return data

    # ---------------------------------------------------------------- decode
    def decode(
        self, frame_id: int, data: bytes | bytearray, timestamp: float, is_extended: bool = False
    ) -> DecodedFrame | None:
        """Decode one received frame and run its E2E Profile 11 check.

        Args:
            frame_id: CAN identifier; data: payload; timestamp: receive time (s).
            is_extended: 29-bit identifier flag (never in this matrix).

        Returns:
            A :class:`DecodedFrame`, or None for frames not in the DBC (the caller counts them).
        """
        hit = self._rx_by_id.get(frame_id)
        if hit is None or is_extended:
            return None
        return hit[0](data, timestamp, hit[1])

    def decode_all(self, frames: Iterable, counts: dict[str, int] | None = None):
        """Yield the :class:`DecodedFrame` of every python-can ``Message`` in ``frames``.

        Error and remote frames and frames not in the DBC are skipped; when
        ``counts`` is given, ``counts['unknown']``/``counts['skipped']`` count them.
        """
        dec = self.decode
        for msg in frames:
            if msg.is_error_frame or msg.is_remote_frame:
                if counts is not None:
                    counts["skipped"] = counts.get("skipped", 0) + 1
                continue
            d = dec(msg.arbitration_id, msg.data, msg.timestamp, msg.is_extended_id)
            if d is None:
                if counts is not None:
                    counts["unknown"] = counts.get("unknown", 0) + 1
                continue
            yield d


# ==================================================================================== the code generator
#: ``E2EStatus`` -> its counter name (``e2e_ok``...), for the generated receivers and the daemon's counters.
STATUS_KEYS = {s: f"e2e_{s.name.lower()}" for s in E2EStatus}


def raw_expr(start: int, length: int, signed: bool) -> str:
    """Python expression of a signal's raw integer from the payload read as one little-endian int ``v``.

    Signed raws use ``(u ^ s) - s`` with ``s`` the sign bit: two's complement without a branch.
    Raises ValueError for a field outside 1..64 bits or a negative start.
    """
    if not 0 < length <= 64 or start < 0:
        raise ValueError(f"bad bit field start={start} length={length}")
    mask = (1 << length) - 1
    u = f"(v >> {start}) & {mask:#x}" if start else f"v & {mask:#x}"
    if signed:
        sign = 1 << (length - 1)
        return f"((({u}) ^ {sign:#x}) - {sign:#x})"
    return f"({u})"


def _crc_chain(seed: int, length: int) -> str:
    """The unrolled table-driven Profile 11 CRC over the data-ID ``seed`` then the locals ``b1``..``b{length-1}``
    (one look-up in ``T`` per byte), final XOR included."""
    if length < 2:
        raise ValueError("an E2E-protected payload has at least 2 bytes")
    e = f"{seed:#04x}"
    for i in range(1, length):
        e = f"T[{e} ^ b{i}]"
    return f"({e} ^ {P11_CRC_XOROUT:#04x})" if P11_CRC_XOROUT else e


def crc_ok_expr(seed: int, length: int) -> str:
    """Expression that is True when byte 0 (``b0``) is the Profile 11 CRC of the message's data-ID seed
    followed by bytes 1..length-1 (locals ``b1``...), with the CRC table as ``T``."""
    return f"{_crc_chain(seed, length)} == b0"


def _unpack(length: int) -> str:
    return f"{', '.join(f'b{i}' for i in range(length))}, = data"


def _ident(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name)


def _exec_source(lines: list[str], name: str, env: dict[str, Any]) -> Callable[..., Any]:
    """Compile the generated function ``name`` from ``lines`` in a namespace holding ``env``."""
    src = "\n".join(lines) + "\n"
    code = compile(src, f"<virtsensor.canbus.codec {name}>", "exec")
    ns: dict[str, Any] = {"T": CRC8_TABLE, "inf": math.inf, "nan": math.nan, **env}
    exec(code, ns)  # noqa: S102 - our own generated source, built from numbers and DBC names only
    fn = ns[name]
    fn.__source__ = src  # for the curious (and the tests)
    return fn


def _indent(ind: str, lines: Sequence[str]) -> list[str]:
    return [ind + line for line in lines]


def _decode_signal(
    s: SignalCodec, ind: str, on_sna: Sequence[str], on_value: Sequence[str], on_implausible: Sequence[str]
) -> list[str]:
    """Lines decoding signal ``s`` from ``v``: raw -> ``on_sna`` for the SNA code, else
    ``x = (raw * scale + offset) / si_factor`` (SI) -> ``on_value`` within the catalogue range (+-1e-9),
    ``on_implausible`` outside it. The one decoder of the package."""
    out = [f"{ind}r = {raw_expr(s.start, s.length, s.signed)}"]
    if s.sna is not None:
        out += [f"{ind}if r == {int(s.sna)}:", *_indent(ind + "    ", on_sna), f"{ind}else:"]
        ind += "    "
    x = f"r * {float(s.scale)!r}" + (f" + {float(s.offset)!r}" if s.offset else "")
    out.append(f"{ind}x = {x}" if s.si_factor == 1.0 else f"{ind}x = ({x}) / {float(s.si_factor)!r}")
    lo, hi = s.lo_si - 1e-9, s.hi_si + 1e-9
    if math.isinf(lo) and math.isinf(hi):
        return out + _indent(ind, on_value)
    return out + [f"{ind}if {lo!r} <= x <= {hi!r}:", *_indent(ind + "    ", on_value),
                  f"{ind}else:", *_indent(ind + "    ", on_implausible)]


def _to_raw_expr(s: SignalCodec) -> str:
    """Python expression of ``(v * si_factor - offset) / scale`` (the unrounded raw of SI value ``v``) without the
    operations that are identities in IEEE arithmetic (``* 1.0``, ``- 0.0``, ``/ 1.0``): the same float for every
    ``v``, fewer operations per signal on the daemon's output path."""
    x = "v" if s.si_factor == 1.0 else f"v * {float(s.si_factor)!r}"
    if s.offset:
        x = f"{x} - {float(s.offset)!r}"
    if s.scale == 1.0:
        return x
    return f"{x} / {float(s.scale)!r}" if x == "v" else f"({x}) / {float(s.scale)!r}"


def compile_encoder(message: MessageCodec) -> Callable[[Mapping[str, float], int], bytes]:
    """``encode(values, counter) -> bytes`` of a compiled :class:`MessageCodec` (see :meth:`CanMatrix.encode`
    for the contract: catalogue names first, then DBC names; missing or nan -> SNA (0 without one); clipped to
    the raw range; counter taken modulo 15; Profile 11 CRC and counter filled).
    """
    L = int(message.length)
    fn = "encode_" + _ident(message.name)
    lines = [f"def {fn}(values, counter):", "    get = values.get", f"    p = (counter % {COUNTER_MODULO}) << 8"]
    for s in message.signals:
        if s.catalogue is not None:
            lines += [f"    v = get({s.catalogue!r})", "    if v is None:", f"        v = get({s.name!r})"]
        else:
            lines.append(f"    v = get({s.name!r})")
        sna = int(s.sna) if s.sna is not None else 0
        lo, hi = int(s.raw_lo), int(s.raw_hi)
        lines += ["    if v is None or v != v:",
                  f"        r = {sna}",
                  "    else:",
                  f"        x = {_to_raw_expr(s)}",
                  f"        r = {lo} if x <= {lo} else {hi} if x >= {hi} else round(x)",
                  f"    p |= (r & {s.mask:#x}) << {int(s.start)}"]
    rest = ", ".join(f"b{i}" for i in range(1, L))
    lines.append(f"    {rest}, = p.to_bytes({L}, 'little')[1:]")
    lines.append(f"    return bytes(({_crc_chain(int(message.seed), L)}, {rest}))")
    return _exec_source(lines, fn, {})


def _compile_frame_decoder(message: MessageCodec) -> Callable[..., DecodedFrame]:
    """``decode_frame(data, t, check) -> DecodedFrame`` of a compiled :class:`MessageCodec`: length, CRC,
    ``check(counter, intact, t)`` (the message's E2E check), then every signal (see :class:`DecodedFrame`)."""
    L, fid, name = int(message.length), int(message.frame_id), message.name
    fn = "decode_" + _ident(name)
    head = f"DF({name!r}, {fid}, t"
    lines = [f"def {fn}(data, t, check):",
             f"    if len(data) != {L}:",
             f"        return {head}, -1, False, False, check(0, False, t), {{}}, {{}}, (), ())",
             f"    {_unpack(L)}",
             "    c = b1 & 15",
             f"    if not {crc_ok_expr(int(message.seed), L)}:",
             f"        return {head}, c, False, True, check(c, False, t), {{}}, {{}}, (), ())",
             "    st = check(c, True, t)",
             "    values = {}",
             "    other = {}",
             "    una = imp = ()"]
    if message.signals:
        lines.append("    v = int.from_bytes(data, 'little')")
    for s in message.signals:
        if s.catalogue is None:
            key = f"other[{s.name!r}]"
            lines += _decode_signal(s, "    ", [f"{key} = nan"], [f"{key} = x"], [f"{key} = x"])
        else:
            c = s.catalogue
            lines += _decode_signal(s, "    ", [f"una += ({c!r},)"], [f"values[{c!r}] = x"], [f"imp += ({c!r},)"])
    lines.append(f"    return {head}, c, True, True, st, values, other, una, imp)")
    return _exec_source(lines, fn, {"DF": DecodedFrame})


def compile_receiver(
    message: MessageCodec,
    receiver: E2EReceiver,
    msg_index: int,
    slots: Sequence[tuple[SignalCodec, int]],
    values: MutableSequence[float],
    times: MutableSequence[float],
    flags: MutableSequence[bool],
    last_ok: MutableSequence[float],
    errors: MutableSequence[bool],
    counters: MutableMapping[str, int],
) -> Callable[[bytes | bytearray, float], None]:
    """The daemon's handler ``rx(data, t)`` of one input message (a compiled :class:`MessageCodec`).

    Per frame, with the semantics of :meth:`CanMatrix.decode` followed by the daemon's bookkeeping:

    * wrong length -> ``receiver.check(0, False, t)`` (ERROR), ``errors[msg_index] = True``,
      ``counters['e2e_error']`` and ``counters['dlc_errors']`` + 1;
    * CRC mismatch -> the same with ``crc_errors``;
    * else ``st = receiver.check(counter, True, t)``, ``counters['e2e_<st>']`` + 1; any status but OK and
      OKSOMELOST (REPEATED, WRONGSEQUENCE, ERROR for the invalid counter 15) -> ``errors[msg_index] = True``;
      OK or OKSOMELOST -> ``last_ok[msg_index] = t`` and for each ``(signal_codec, i)`` of ``slots``:
      SNA -> ``flags[i] = True`` and ``sna_values`` + 1; ``(raw * scale + offset) / si_factor`` outside the
      catalogue range (+-1e-9) -> ``flags[i] = True`` and ``implausible_values`` + 1; else ``values[i]``,
      ``times[i] = value, t`` and ``flags[i] = False``.

    The lists are captured by reference: mutate them in place, never rebind them.
    """
    L, j = int(message.length), int(msg_index)
    fn = "rx_" + _ident(message.name)
    lines = [f"def {fn}(data, t):",
             f"    if len(data) != {L}:",
             "        check(0, False, t)",
             "        counters['e2e_error'] += 1",
             "        counters['dlc_errors'] += 1",
             f"        errors[{j}] = True",
             "        return",
             f"    {_unpack(L)}",
             f"    if not {crc_ok_expr(int(message.seed), L)}:",
             "        check(b1 & 15, False, t)",
             "        counters['e2e_error'] += 1",
             "        counters['crc_errors'] += 1",
             f"        errors[{j}] = True",
             "        return",
             "    st = check(b1 & 15, True, t)",
             "    if st is OK:",
             "        counters['e2e_ok'] += 1",
             "    else:",
             "        counters[KEYS[st]] += 1",
             "        if st is not OKSOMELOST:",
             f"            errors[{j}] = True",
             "            return",
             f"    last_ok[{j}] = t"]
    if slots:
        lines.append("    v = int.from_bytes(data, 'little')")
    for s, i in slots:
        i = int(i)
        lines += _decode_signal(s, "    ", [f"flags[{i}] = True", "counters['sna_values'] += 1"],
                                [f"values[{i}] = x", f"times[{i}] = t", f"flags[{i}] = False"],
                                [f"flags[{i}] = True", "counters['implausible_values'] += 1"])
    env = {"check": receiver.check, "counters": counters, "errors": errors, "last_ok": last_ok, "values": values,
           "times": times, "flags": flags, "KEYS": STATUS_KEYS, "OK": E2EStatus.OK,
           "OKSOMELOST": E2EStatus.OKSOMELOST}
    return _exec_source(lines, fn, env)
