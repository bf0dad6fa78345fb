"""The DBC codec shared by the simulator writer, the replay, the trainer and the runtime.

Values cross this module's boundary in the catalogue's SI units under their
catalogue names (``tyre_pressure_fl_pa`` in Pa); the DBC may carry another
unit (kPa) and the conversion is done here, once (factors from
:data:`virtsensor.dbcgen.UNIT_CONVERSIONS`). Frames are 8-byte classic CAN
frames with E2E protection as described in :mod:`virtsensor.e2e`.

The DBC is read once with cantools and compiled into flat tuples so that
:meth:`CanMatrix.encode` and :meth:`CanMatrix.decode` run in a few
microseconds with plain integer bit operations (Intel byte order only).

Where the DBC comes from (:meth:`CanMatrix.load` with ``path=None``): the
file ``dbc/virtsensor.dbc`` of a source checkout; in an installed package
(where the repository's ``dbc/`` directory is absent) the very same text is
regenerated in memory from the catalogue by :func:`virtsensor.dbcgen.generate`
(a test keeps the committed file identical to the generated text), so no
copy of the DBC has to be kept in the package.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from virtsensor import signals as cat
from virtsensor.dbcgen import UNIT_CONVERSIONS
from virtsensor.e2e import CRC8_TABLE, CRC8_XOROUT, USABLE, E2EReceiver, E2EStatus, data_id_seed
from virtsensor.errors import UserError

__all__ = ["DEFAULT_DBC", "CanMatrix", "DecodedFrame", "MessageCodec", "SignalCodec"]

#: The bundled DBC of a source checkout.
DEFAULT_DBC = Path(__file__).resolve().parent.parent / "dbc" / "virtsensor.dbc"

_EMPTY: tuple[str, ...] = ()


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
        catalogue_names: catalogue names of the signals that have one.
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


class DecodedFrame:
    """One received frame after DBC decoding and the E2E check.

    Attributes:
        message: DBC message name; frame_id; timestamp: receive time (s).
        counter: received alive counter (-1 when the length was wrong).
        crc_ok: CRC matched; dlc_ok: payload length equals the DBC length.
        status: :class:`~virtsensor.e2e.E2EStatus` from the message's receiver state machine.
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
        """The values are fresh and intact (E2E status OK, OKSOMELOST or INITIAL)."""
        return self.status in USABLE

    def __repr__(self) -> str:
        return (
            f"DecodedFrame({self.message} t={self.timestamp:.6f} ctr={self.counter} "
            f"{self.status.name} values={self.values} other={self.other})"
        )


_CACHE: dict[tuple[str, float], tuple[object, dict[str, MessageCodec], str]] = {}


def _compile(db, source: str) -> dict[str, MessageCodec]:
    """Build the :class:`MessageCodec` of every message of a cantools database."""
    where: dict[tuple[str, str], str] = {
        (s.message, s.dbc_signal): s.name for s in cat.SIGNALS.values() if s.message and s.dbc_signal
    }
    out: dict[str, MessageCodec] = {}
    for m in db.messages:
        if m.is_extended_frame:
            raise UserError(f"{source}: message {m.name}: extended (29-bit) ids are not supported")
        names = {s.name: s for s in m.signals}
        crc, ctr = names.get(f"{m.name}_CRC"), names.get(f"{m.name}_Counter")
        if (
            crc is None
            or ctr is None
            or (crc.start, crc.length) != (0, 8)
            or (ctr.start, ctr.length) != (8, 4)
        ):
            raise UserError(
                f"{source}: message {m.name} lacks {m.name}_CRC at bits 0..7 and "
                f"{m.name}_Counter at bits 8..11 (E2E layout)"
            )
        attr = m.dbc.attributes.get("E2E_DataID") if m.dbc is not None else None
        if attr is not None:
            data_id = int(attr.value)
        elif m.name in cat.MESSAGES:
            data_id = cat.MESSAGES[m.name].data_id
        else:
            raise UserError(f"{source}: message {m.name} has no E2E_DataID attribute and is not catalogued")
        sigs: list[SignalCodec] = []
        for s in m.signals:
            if s is crc or s is ctr:
                continue
            if s.byte_order != "little_endian":
                raise UserError(
                    f"{source}: {m.name}.{s.name}: only Intel (little-endian) signals are supported"
                )
            if m.is_multiplexed() or s.multiplexer_ids:
                raise UserError(f"{source}: {m.name}.{s.name}: multiplexed signals are not supported")
            cname = where.get((m.name, s.name))
            scale, offset = float(s.scale), float(s.offset)
            unit = s.unit or ""
            factor = 1.0
            if cname is not None:
                spec = cat.SIGNALS[cname]
                if unit != spec.unit:
                    conv = UNIT_CONVERSIONS.get(spec.unit)
                    if conv is None or conv[0] != unit:
                        raise UserError(
                            f"{source}: {m.name}.{s.name} has unit {unit!r} but the catalogue's "
                            f"{cname} is in {spec.unit!r}"
                        )
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
                raise UserError(f"{source}: {m.name}.{s.name}: SNA code {sna} lies inside the signal range")
            sigs.append(
                SignalCodec(
                    s.name,
                    cname,
                    s.start,
                    s.length,
                    bool(s.is_signed),
                    scale,
                    offset,
                    factor,
                    raw_lo,
                    raw_hi,
                    lo_si,
                    hi_si,
                    sna,
                    unit,
                )
            )
        sigs.sort(key=lambda x: x.start)
        sender = m.senders[0] if m.senders else ""
        cycle_s = (m.cycle_time or 0) / 1000.0
        out[m.name] = MessageCodec(m.name, m.frame_id, m.length, sender, cycle_s, data_id, tuple(sigs))
    return out


def _load_db(path: Path | None):
    """(cantools db, compiled messages, source text) for ``path`` (None: bundled), cached."""
    import cantools

    if path is None:
        if DEFAULT_DBC.is_file():
            path = DEFAULT_DBC
        else:
            key = ("<generated>", 0.0)
            if key not in _CACHE:
                from virtsensor import dbcgen

                db = cantools.database.load_string(dbcgen.generate(), database_format="dbc")
                _CACHE[key] = (db, _compile(db, "<generated virtsensor DBC>"), "<generated virtsensor DBC>")
            return _CACHE[key]
    path = Path(path)
    try:
        key = (str(path.resolve()), os.stat(path).st_mtime)
    except OSError as exc:
        raise UserError(f"{path}: cannot read the DBC: {exc.strerror or exc}") from None
    if key not in _CACHE:
        try:
            db = cantools.database.load_file(str(path), database_format="dbc", strict=True)
        except Exception as exc:  # cantools raises ParseError, UnsupportedDatabaseFormatError, ...
            msg = " ".join(str(exc).split())
            raise UserError(f"{path}: not a valid DBC: {type(exc).__name__}: {msg}") from None
        _CACHE[key] = (db, _compile(db, str(path)), str(path))
    return _CACHE[key]


class CanMatrix:
    """A loaded CAN matrix with per-message E2E receiver state.

    Build it with :meth:`load`. The compiled tables are shared between
    instances; the E2E state is not (use one instance per receiver).

    Attributes:
        db: the cantools database (for tools that want it).
        source: where the DBC came from (path or ``<generated ...>``).
        messages: message name -> :class:`MessageCodec`.
        by_id: frame id -> :class:`MessageCodec`.
        receivers: message name -> :class:`~virtsensor.e2e.E2EReceiver`.
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
        self._rx_by_id = {m.frame_id: (m, self.receivers[m.name]) for m in messages.values()}
        self._signal_message = {c: m.name for m in messages.values() for c in m.catalogue_names}

    @classmethod
    def load(
        cls, path: str | os.PathLike | None = None, *, max_delta: int = 3, timeout_cycles: float = 5.0
    ) -> CanMatrix:
        """Load a DBC (default: the bundled one, see the module docstring).

        Args:
            path: DBC file; None for the bundled matrix.
            max_delta: largest counter delta still reported OKSOMELOST.
            timeout_cycles: E2E reception timeout in message cycles (NODATA / resync).

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
        """Payload bytes of one frame.

        Args:
            message_name: DBC message name.
            values: catalogue name -> SI value (or DBC signal name -> DBC physical
                value for signals without a catalogue name, e.g. ``SAT_FL_Status``).
                Keys of other messages are ignored; a signal that is missing or
                nan is sent as its SNA code (0 if it has none). Values are clipped
                to the signal's range.
            counter: alive counter (taken modulo 16).

        Returns:
            ``length`` bytes with CRC (byte 0) and counter (byte 1, bits 0..3) filled.
        """
        m = self.messages.get(message_name)
        if m is None:
            self.message(message_name)
        payload = (counter & 0xF) << 8
        get = values.get
        for cname, dname, s in m._keys:  # type: ignore[union-attr]
            v = get(cname) if cname is not None else None
            if v is None:
                v = get(dname)
            if v is None or v != v:
                raw = s.sna if s.sna is not None else 0
            else:
                x = (v * s.si_factor - s.offset) / s.scale
                if x <= s.raw_lo:
                    raw = s.raw_lo
                elif x >= s.raw_hi:
                    raw = s.raw_hi
                else:
                    raw = round(x)
            payload |= (raw & s.mask) << s.start
        data = bytearray(payload.to_bytes(m.length, "little"))  # type: ignore[union-attr]
        t = CRC8_TABLE
        c = m.seed  # type: ignore[union-attr]
        for i in range(1, len(data)):
            c = t[c ^ data[i]]
        data[0] = c ^ CRC8_XOROUT
        return bytes(data)

    def encode_many(
        self, message_name: str, columns: Mapping[str, np.ndarray], counters: np.ndarray
    ) -> np.ndarray:
        """Vectorised :meth:`encode` of ``n`` frames: returns an ``(n, length)`` uint8 array.

        ``columns`` maps names as in :meth:`encode` to arrays of length ``n``
        (missing names and nan -> SNA); ``counters`` are the ``n`` alive counters.
        """
        m = self.message(message_name)
        counters = np.asarray(counters, dtype=np.int64)
        n = counters.shape[0]
        payload = (counters & 0xF).astype(np.uint64) << np.uint64(8)
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
        table = np.frombuffer(CRC8_TABLE, dtype=np.uint8)
        c = np.full(n, m.seed, dtype=np.uint8)
        for i in range(1, m.length):
            c = table[c ^ data[:, i]]
        data[:, 0] = c ^ CRC8_XOROUT
        return data

    # ---------------------------------------------------------------- decode
    def decode(
        self, frame_id: int, data: bytes | bytearray, timestamp: float, is_extended: bool = False
    ) -> DecodedFrame | None:
        """Decode one received frame and run its E2E check.

        Args:
            frame_id: CAN identifier; data: payload; timestamp: receive time (s).
            is_extended: 29-bit identifier flag (never in this matrix).

        Returns:
            A :class:`DecodedFrame`, or None for frames not in the DBC (the caller counts them).
        """
        hit = self._rx_by_id.get(frame_id)
        if hit is None or is_extended:
            return None
        m, rx = hit
        if len(data) != m.length:
            st = rx.check(0, False, timestamp)
            return DecodedFrame(m.name, frame_id, timestamp, -1, False, False, st, {}, {}, _EMPTY, _EMPTY)
        t = CRC8_TABLE
        c = m.seed
        for i in range(1, m.length):
            c = t[c ^ data[i]]
        crc_ok = (c ^ CRC8_XOROUT) == data[0]
        counter = data[1] & 0xF
        st = rx.check(counter, crc_ok, timestamp)
        values: dict[str, float] = {}
        other: dict[str, float] = {}
        unavailable = implausible = _EMPTY
        if crc_ok:
            v = int.from_bytes(data, "little")
            for s in m.signals:
                raw = (v >> s.start) & s.mask
                if s.signed and raw >> (s.length - 1):
                    raw -= 1 << s.length
                cname = s.catalogue
                if cname is None:
                    other[s.name] = math.nan if raw == s.sna else raw * s.scale + s.offset
                elif raw == s.sna:
                    unavailable = (*unavailable, cname)
                else:
                    x = (raw * s.scale + s.offset) / s.si_factor
                    if s.lo_si - 1e-9 <= x <= s.hi_si + 1e-9:
                        values[cname] = x
                    else:
                        implausible = (*implausible, cname)
        return DecodedFrame(
            m.name, frame_id, timestamp, counter, crc_ok, True, st, values, other, unavailable, implausible
        )

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
