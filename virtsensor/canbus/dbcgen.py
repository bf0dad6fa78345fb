"""Generate ``dbc/virtsensor.dbc`` from the signal catalogue (the one source of truth).

Usage::

    python -m virtsensor.canbus.dbcgen > dbc/virtsensor.dbc

The generated text is deterministic (a test checks the committed file equals
it). Layout rules, applied to every message (8-byte classic CAN frames,
Intel/little-endian, bit 0 = LSB of byte 0):

* byte 0: ``<Msg>_CRC`` (8 bits), byte 1 bits 0..3: ``<Msg>_Counter`` (4 bits):
  the header of AUTOSAR E2E Profile 11, Data ID mode BOTH; see
  :mod:`virtsensor.canbus.e2e` for the exact CRC definition (polynomial 0x1D
  over the 16-bit data ID, low byte first, then payload bytes 1..7);
* the signals follow from bit 12 in catalogue order, each with the fewest
  bits whose raw range covers the catalogue ``minimum..maximum`` at
  ``scale = resolution`` plus one spare code for "signal not available"
  (SNA, listed in the signal's VAL_ table): the most negative raw value for
  signed signals, all ones for unsigned ones. A signal is stored signed with
  offset 0 when that is as short as unsigned with ``offset = minimum``.
* physical DBC units equal the catalogue SI units except those in
  :data:`UNIT_CONVERSIONS` (gauge pressure in bar, as production TPMS report it); :mod:`virtsensor.canbus.codec`
  does that scaling, once.
* every signal is packed at its catalogue resolution; a message whose signals
  do not fit in the 52 free bits is refused (split it in the catalogue, as the
  ESC's front and rear wheel speeds are).

The module also exposes the layout as data (:func:`layout`) for tests and docs.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field, replace

from virtsensor import signals as cat
from virtsensor.canbus.e2e import COUNTER_MAX

#: catalogue SI unit -> (DBC unit, factor): DBC value = SI value * factor.
UNIT_CONVERSIONS: dict[str, tuple[str, float]] = {"Pa": ("bar", 1e-5)}

#: ECU nodes, in catalogue order, with their comments.
NODES: dict[str, str] = {
    "ESC": "Electronic stability control: wheel speeds and vehicle speed.",
    "ACU": "Airbag control unit with the inertial measurement unit: accelerations and yaw rate.",
    "EPAS": "Electric power-assisted steering: steering-wheel angle, torsion-bar and assist torque.",
    "PCU": "Powertrain control unit: traction-motor torque.",
    "CHS": "Chassis control: suspension deflections.",
    "TPMS": "Tyre-pressure monitoring system: four tyre pressures.",
    "VSENS": "The virtual sensor (virtsensor runtime): estimated front SATs, its health and the grip margin.",
    "TESTEQ": "Test equipment: wheel-force transducers giving the reference front SATs.",
}

#: Messages whose frames are produced by the virtual sensor (outputs).
_OUTPUT_SENDERS = ("VSENS",)
FREE_BIT = 12
FRAME_BYTES = 8

STATUS_CHOICES: dict[int, str] = {0: "VALID", 1: "DEGRADED", 2: "INVALID", 3: "INIT"}

_SIGN_CONVENTION = (
    "Axes ISO 8855 (x forward, y left, z up); angles and rates about z positive "
    "counter-clockwise seen from above: a left turn has positive yaw rate, steering angle "
    "and lateral acceleration, and negative front SATs (tyre Mz, ISO-W)."
)


@dataclass(frozen=True)
class SignalLayout:
    """One DBC signal.

    Attributes:
        name: DBC signal name.
        catalogue: catalogue signal name it carries (None: protocol or VSENS-only signal).
        start: Intel start bit (LSB position); length: bits.
        signed: two's complement raw value.
        scale, offset: physical = raw * scale + offset, in ``unit``.
        minimum, maximum: physical range in ``unit`` (the catalogue range, converted).
        unit: DBC unit; si_factor: DBC value = catalogue SI value * si_factor.
        sna: raw value meaning "signal not available" (None: none).
        receivers: receiving nodes.
        comment: CM_ text.
        choices: VAL_ table (raw -> name).
    """

    name: str
    catalogue: str | None
    start: int
    length: int
    signed: bool
    scale: float
    offset: float
    minimum: float
    maximum: float
    unit: str
    si_factor: float
    sna: int | None
    receivers: tuple[str, ...]
    comment: str
    choices: dict[int, str] = field(default_factory=dict)


@dataclass(frozen=True)
class MessageLayout:
    """One DBC message: identity from the catalogue plus its signals (CRC and counter first)."""

    name: str
    frame_id: int
    sender: str
    cycle_ms: int
    data_id: int
    comment: str
    signals: tuple[SignalLayout, ...]
    length: int = FRAME_BYTES


def _raw_format(lo: float, hi: float, scale: float) -> tuple[int, bool, float, int, int]:
    """Fewest bits for ``lo..hi`` at ``scale`` with one spare SNA code.

    Returns (length, signed, offset, raw_lo, raw_hi).
    """
    rlo_f, rhi_f = lo / scale, hi / scale
    rlo = round(rlo_f) if abs(rlo_f - round(rlo_f)) < 1e-6 else math.ceil(rlo_f)
    rhi = round(rhi_f) if abs(rhi_f - round(rhi_f)) < 1e-6 else math.floor(rhi_f)
    candidates: list[tuple[int, int, bool, float, int, int]] = []  # (bits, pref, ...)
    if rlo < 0:
        n = 2
        while not (-(2 ** (n - 1)) < rlo and rhi <= 2 ** (n - 1) - 1):
            n += 1
        candidates.append((n, 0, True, 0.0, rlo, rhi))
    else:
        n = 1
        while not rhi < 2**n - 1:
            n += 1
        candidates.append((n, 0, False, 0.0, rlo, rhi))
    span = rhi - rlo
    n = 1
    while not span < 2**n - 1:
        n += 1
    candidates.append((n, 1, False, rlo * scale, 0, span))
    bits, _, signed, offset, a, b = min(candidates, key=lambda c: (c[0], c[1]))
    return bits, signed, offset, a, b


def _sna(length: int, signed: bool) -> int:
    return -(2 ** (length - 1)) if signed else 2**length - 1


def _clean(x: float) -> float:
    """Round away binary noise (e.g. 500 * 1e-3) to 12 significant digits."""
    return float(f"{x:.12g}")


def _physical(
    name: str, catalogue: str | None, spec: cat.Signal, start: int, receivers: tuple[str, ...], comment: str
) -> SignalLayout:
    unit, factor = UNIT_CONVERSIONS.get(spec.unit, (spec.unit, 1.0))
    res = spec.resolution
    scale = _clean(res * factor)
    lo, hi = _clean(spec.minimum * factor), _clean(spec.maximum * factor)
    length, signed, offset, _, _ = _raw_format(lo, hi, scale)
    offset = _clean(offset)
    sna = _sna(length, signed)
    sna_raw_txt = f"{sna}" if signed else f"0x{sna:X}"
    extra = (
        f" Catalogue: {spec.name} [{spec.unit}], range {_num(spec.minimum)}..{_num(spec.maximum)}, "
        f"catalogue resolution {_num(spec.resolution)}"
    )
    if unit != spec.unit:
        extra += f"; on CAN in {unit} (1 {spec.unit} = {_num(factor)} {unit})"
    if scale != _clean(spec.resolution * factor):
        extra += f"; packed at the coarser resolution {_num(scale)} {unit} to fit the frame"
    extra += f". Raw {sna_raw_txt} = SNA (signal not available)."
    return SignalLayout(
        name=name,
        catalogue=catalogue,
        start=start,
        length=length,
        signed=signed,
        scale=scale,
        offset=offset,
        minimum=lo,
        maximum=hi,
        unit=unit,
        si_factor=factor,
        sna=sna,
        receivers=receivers,
        comment=comment + extra,
        choices={sna: "SNA"},
    )


def _integer(
    name: str,
    start: int,
    length: int,
    unit: str,
    receivers: tuple[str, ...],
    comment: str,
    choices: dict[int, str] | None = None,
) -> SignalLayout:
    return SignalLayout(
        name=name,
        catalogue=None,
        start=start,
        length=length,
        signed=False,
        scale=1.0,
        offset=0.0,
        minimum=0.0,
        maximum=float(2**length - 1),
        unit=unit,
        si_factor=1.0,
        sna=None,
        receivers=receivers,
        comment=comment,
        choices=dict(choices or {}),
    )


def _input_messages() -> tuple[str, ...]:
    """Messages carrying at least one estimator input, in frame-id order, then the optional input messages
    (:data:`OPTIONAL_INPUT_MESSAGES`), then the check-reference messages (:data:`CHECK_MESSAGES`): the VS_Health
    bitmap order."""
    names = {cat.SIGNALS[n].message for n in cat.INPUTS}
    ordered = tuple(m.name for m in sorted(cat.MESSAGES.values(), key=lambda m: m.frame_id) if m.name in names)
    return ordered + OPTIONAL_INPUT_MESSAGES + CHECK_MESSAGES


#: Messages some models read (the TPMS model, issue 17), after the inputs' messages in the VS_Health bitmap; a
#: daemon whose model does not read one leaves its bit at 0.
OPTIONAL_INPUT_MESSAGES = ("TPMS_Pressures",)
#: Messages that carry no estimator input but a plausibility check's reference (the rear wheel speeds of the
#: yaw-rate check), last in the VS_Health bitmap: their bit says the checks that read them are judged; it is 0
#: while such a message is missing, and the estimate's status does not change for it.
CHECK_MESSAGES = tuple(sorted({str(cat.SIGNALS[s].message) for r in cat.REDUNDANCIES for s in r.reads
                               if cat.SIGNALS[s].message is not None} - {cat.SIGNALS[n].message for n in cat.INPUTS}))


def _payload_sat_front(rx: tuple[str, ...]) -> list[SignalLayout]:
    sigs: list[SignalLayout] = []
    bit = FREE_BIT
    for corner, cname in (("FL", "sat_fl_nm"), ("FR", "sat_fr_nm")):
        spec = cat.SIGNALS[cname]
        s = _physical(
            f"SAT_{corner}",
            None,
            spec,
            bit,
            rx,
            f"Estimated {'front-left' if corner == 'FL' else 'front-right'} self-aligning torque "
            f"(tyre Mz at the contact centre, ISO-W, z up); negative in a left turn. Estimate of "
            f"{cname}; SNA while the estimator is initialising.",
        )
        sigs.append(s)
        bit += s.length
    for corner in ("FL", "FR"):
        sigs.append(
            _integer(
                f"SAT_{corner}_Status",
                bit,
                2,
                "",
                rx,
                f"Validity of SAT_{corner}: 0 VALID, 1 DEGRADED (a non-critical input held or "
                f"substituted, or the inputs outside the model's validity envelope), "
                f"2 INVALID (a critical input missing or implausible), 3 INIT.",
                STATUS_CHOICES,
            )
        )
        bit += 2
    return sigs


def _bitmap_text() -> str:
    """The VS_InputStatus bit order, as its comment states it ("bit 0 IMU_Motion, ...")."""
    notes = {**dict.fromkeys(OPTIONAL_INPUT_MESSAGES, " (only when the daemon reads it: a model input, or the grip "
                                                      "estimate's front pressures)"),
             **dict.fromkeys(CHECK_MESSAGES, " (a plausibility check's reference, no estimator input: 0 = the "
                                             "checks that read it are not judged; the SAT status is not lowered)")}
    inputs = _input_messages()
    assert len(inputs) <= 8, inputs  # (an 8-bit bitmap)
    return ", ".join(f"bit {i} {m}{notes.get(m, '')}" for i, m in enumerate(inputs))


def _payload_vs_health(rx: tuple[str, ...]) -> list[SignalLayout]:
    sigs: list[SignalLayout] = []
    bit = FREE_BIT
    bitmap = _bitmap_text()
    sigs.append(
        _integer(
            "VS_TickOverruns",
            bit,
            16,
            "",
            rx,
            "Number of estimator ticks that missed their deadline since start (saturates at 65535).",
        )
    )
    bit += 16
    sigs.append(
        _integer(
            "VS_TickLatency",
            bit,
            16,
            "us",
            rx,
            "Latency of the last estimator tick, from tick start to SAT_FRONT "
            "transmission, in microseconds (saturates at 65535).",
        )
    )
    bit += 16
    sigs.append(
        _integer(
            "VS_InputStatus",
            bit,
            8,
            "",
            rx,
            "Input status bitmap, one bit per input message, 1 = received intact "
            f"(E2E OK) within its timeout, in order, and every signal the daemon reads from it usable: {bitmap}; "
            "unused bits 0.",
        )
    )
    bit += 8
    sigs.append(
        _integer(
            "VS_ModelId",
            bit,
            8,
            "",
            rx,
            "Identifier/version byte of the estimator model in use "
            "(high nibble model id, low nibble version).",
        )
    )
    bit += 8
    sigs.append(
        _integer(
            "VS_OutOfEnvelope",
            bit,
            1,
            "",
            rx,
            "1 = the inputs lie outside the validity envelope the model card states (the ranges and grip per "
            "speed band of its training data): the estimator extrapolates and a VALID estimate is sent as "
            "DEGRADED; 0 = inside, or the model card states no envelope.",
        )
    )
    bit += 1
    sigs.append(
        _integer(
            "VS_EnvelopeExits",
            bit,
            3,
            "",
            rx,
            "Number of excursions outside the validity envelope since start (saturates at 7).",
        )
    )
    bit += 3
    return sigs


#: VS_Grip: DBC signal name -> (catalogue signal, comment head) of its physical signals, in payload order.
GRIP_SIGNALS: dict[str, tuple[str, str]] = {
    "VS_GripUtil": ("grip_util_front_1", "Estimated front-axle friction utilisation (0..1: the share of the "
                    "road's friction the more used front tyre uses). Always given while VALID or DEGRADED; SNA "
                    "while INIT or INVALID."),
    "VS_GripMu": ("grip_mu_1", "Estimated road friction coefficient. SNA (unknown) while the front tyres are not "
                  "excited enough to tell (straight driving, gentle corners), whatever its status, and while "
                  "INIT or INVALID."),
    "VS_GripMuHalfWidth": ("grip_mu_halfwidth_1", "Half-width of the interval VS_GripMu +- this that holds the "
                           "true road friction in 9 of 10 samples; SNA when VS_GripMu is."),
}
#: VS_Grip: status signal per field, in payload order (after the warning flag).
GRIP_STATUS = ("VS_GripUtil_Status", "VS_GripMu_Status", "VS_GripMuHalfWidth_Status", "VS_GripWarning_Status")


def _payload_vs_grip(rx: tuple[str, ...]) -> list[SignalLayout]:
    sigs: list[SignalLayout] = []
    bit = FREE_BIT
    for name, (cname, text) in GRIP_SIGNALS.items():
        s = _physical(name, None, cat.SIGNALS[cname], bit, rx, f"{text} Estimate of {cname}.")
        sigs.append(s)
        bit += s.length
    sigs.append(_integer("VS_GripWarning", bit, 1, "", rx,
                         "1 = grip-limit warning: the front axle is at or nearing the road's friction limit "
                         "(estimated utilisation high, or rising fast towards it); 0 = no warning.",
                         {0: "NO_WARNING", 1: "WARNING"}))
    bit += 1
    for name in GRIP_STATUS:
        held = ("; a friction held from earlier ticks is also no better than the statuses of the ticks it was read "
                "on" if name in ("VS_GripMu_Status", "VS_GripMuHalfWidth_Status") else "")
        sigs.append(_integer(name, bit, 2, "", rx,
                             f"Validity of {name[:-7]}, as SAT_FL/FR_Status: 0 VALID, 1 DEGRADED, 2 INVALID, "
                             f"3 INIT (the worse of the two SAT statuses it derives from{held}).", STATUS_CHOICES))
        bit += 2
    return sigs


def _payload_vsens(msg: cat.Message, rx: tuple[str, ...]) -> list[SignalLayout]:
    if msg.name == "SAT_FRONT":
        return _payload_sat_front(rx)
    if msg.name == "VS_Health":
        return _payload_vs_health(rx)
    if msg.name == "VS_Grip":
        return _payload_vs_grip(rx)
    # pragma: no cover - catalogue grew a VSENS message this generator does not know
    raise ValueError(f"dbcgen does not know the layout of VSENS message {msg.name}")


def layout() -> tuple[MessageLayout, ...]:
    """The full message layout derived from :mod:`virtsensor.signals`, in frame-id order.

    Raises:
        ValueError: when a message's signals do not fit its 8 bytes.
    """
    out: list[MessageLayout] = []
    for msg in sorted(cat.MESSAGES.values(), key=lambda m: m.frame_id):
        if msg.sender in _OUTPUT_SENDERS or msg.sender == "TESTEQ":
            rx: tuple[str, ...] = ("Vector__XXX",)
        else:
            rx = ("VSENS",)
        cycle_ms = round(msg.cycle_s * 1000)
        sigs = [
            _integer(
                f"{msg.name}_CRC",
                0,
                8,
                "",
                rx,
                f"AUTOSAR E2E Profile 11 CRC (Data ID mode BOTH): CRC-8 poly 0x1D, register start 0x00, "
                f"no final XOR (Crc_CalculateCRC8 chained with start value 0xFF) over the data ID "
                f"0x{msg.data_id:04X} (low byte first: 0x{msg.data_id & 0xFF:02X} "
                f"0x{msg.data_id >> 8:02X}) followed by payload bytes 1..7.",
            ),
            _integer(
                f"{msg.name}_Counter",
                8,
                4,
                "",
                rx,
                "AUTOSAR E2E Profile 11 alive counter: 0..14, +1 modulo 15 per transmitted frame (14 wraps "
                "to 0); 15 is invalid.",
            ),
        ]
        sigs[1] = replace(sigs[1], maximum=float(COUNTER_MAX))  # 15 is not a counter value
        if msg.sender in _OUTPUT_SENDERS:
            sigs += _payload_vsens(msg, rx)
        else:
            bit = FREE_BIT
            for spec in cat.by_message(msg.name):
                assert spec.dbc_signal is not None
                s = _physical(spec.dbc_signal, spec.name, spec, bit, rx, spec.description)
                sigs.append(s)
                bit += s.length
        used = sigs[-1].start + sigs[-1].length
        if used > 8 * FRAME_BYTES:
            detail = ", ".join(f"{s.name}={s.length}" for s in sigs)
            raise ValueError(
                f"message {msg.name} needs {used} bits > {8 * FRAME_BYTES} ({detail}); "
                f"split the message in the catalogue"
            )
        comment = (
            f"Sent by {msg.sender} every {cycle_ms} ms. E2E data ID 0x{msg.data_id:04X}: byte 0 CRC, "
            f"byte 1 bits 0-3 alive counter, signals from bit 12 (Intel). Bits used: {used} of 64."
        )
        out.append(
            MessageLayout(msg.name, msg.frame_id, msg.sender, cycle_ms, msg.data_id, comment, tuple(sigs))
        )
    return tuple(out)


def _num(x: float) -> str:
    """Shortest text of a number as DBC writes it (``10`` not ``10.0``)."""
    if float(x).is_integer() and abs(x) < 1e15:
        return str(int(x))
    return repr(float(x))


def _q(text: str) -> str:
    return '"' + text.replace("\\", "/").replace('"', "'") + '"'


#: The DBC new-symbols section (``NS_``), as cantools and CANdb++ write it.
_NS_KEYS = (
    "NS_DESC_",
    "CM_",
    "BA_DEF_",
    "BA_",
    "VAL_",
    "CAT_DEF_",
    "CAT_",
    "FILTER",
    "BA_DEF_DEF_",
    "EV_DATA_",
    "ENVVAR_DATA_",
    "SGTYPE_",
    "SGTYPE_VAL_",
    "BA_DEF_SGTYPE_",
    "BA_SGTYPE_",
    "SIG_TYPE_REF_",
    "VAL_TABLE_",
    "SIG_GROUP_",
    "SIG_VALTYPE_",
    "SIGTYPE_VALTYPE_",
    "BO_TX_BU_",
    "BA_DEF_REL_",
    "BA_REL_",
    "BA_DEF_DEF_REL_",
    "BU_SG_REL_",
    "BU_EV_REL_",
    "BU_BO_REL_",
    "SG_MUL_VAL_",
)


def generate() -> str:
    """The DBC file text (deterministic)."""
    msgs = layout()
    lines: list[str] = [
        'VERSION ""',
        "",
        "",
        "NS_ :",
        *(f"\t{k}" for k in _NS_KEYS),
        "",
        "BS_:",
        "",
        "BU_: " + " ".join(NODES),
        "",
    ]
    for m in msgs:
        lines.append(f"BO_ {m.frame_id} {m.name}: {m.length} {m.sender}")
        for s in m.signals:
            sign = "-" if s.signed else "+"
            lines.append(
                f" SG_ {s.name} : {s.start}|{s.length}@1{sign} ({_num(s.scale)},{_num(s.offset)}) "
                f"[{_num(s.minimum)}|{_num(s.maximum)}] {_q(s.unit)} {','.join(s.receivers)}"
            )
        lines.append("")
    lines.append("")
    lines.append(
        "CM_ "
        + _q(
            "virtsensor CAN matrix, generated by python -m virtsensor.canbus.dbcgen from virtsensor/signals.py; "
            "do not edit. " + _SIGN_CONVENTION + " E2E: AUTOSAR E2E Profile 11, Data ID mode BOTH "
            "(CRCOffset 0, CounterOffset 8): CRC-8 poly 0x1D with register start 0x00 and no final XOR "
            "(Crc_CalculateCRC8 chained with start value 0xFF) over the 16-bit data ID (attribute E2E_DataID, "
            "low byte first) followed by payload bytes 1..7, stored in byte 0; 4-bit alive counter in byte 1 "
            "bits 0-3, counting 0..14 (15 invalid)."
        )
        + ";"
    )
    for node, text in NODES.items():
        lines.append(f"CM_ BU_ {node} {_q(text)};")
    for m in msgs:
        lines.append(f"CM_ BO_ {m.frame_id} {_q(m.comment)};")
        for s in m.signals:
            lines.append(f"CM_ SG_ {m.frame_id} {s.name} {_q(s.comment)};")
    lines += [
        'BA_DEF_  "BusType" STRING ;',
        'BA_DEF_ BO_  "GenMsgCycleTime" INT 0 65535;',
        'BA_DEF_ BO_  "E2E_DataID" INT 0 65535;',
        'BA_DEF_DEF_  "BusType" "CAN";',
        'BA_DEF_DEF_  "GenMsgCycleTime" 0;',
        'BA_DEF_DEF_  "E2E_DataID" 0;',
        'BA_ "BusType" "CAN";',
    ]
    for m in msgs:
        lines.append(f'BA_ "GenMsgCycleTime" BO_ {m.frame_id} {m.cycle_ms};')
        lines.append(f'BA_ "E2E_DataID" BO_ {m.frame_id} {m.data_id};')
    for m in msgs:
        for s in m.signals:
            if s.choices:
                body = " ".join(f"{k} {_q(v)}" for k, v in sorted(s.choices.items(), reverse=True))
                lines.append(f"VAL_ {m.frame_id} {s.name} {body} ;")
    lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Write the DBC to stdout (``python -m virtsensor.canbus.dbcgen > dbc/virtsensor.dbc``)."""
    sys.stdout.write(generate())
    return 0


if __name__ == "__main__":
    sys.exit(main())
