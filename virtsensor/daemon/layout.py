"""The daemon's input and output layout, read once at start-up from the model card and the DBC.

Which signals the model reads (the card's ``feature_spec``, never code), which are critical (the card's
``inputs[].critical``, default the catalogue's flag), which other signals the plausibility checks read
(:func:`check_references`), which messages carry them, their cycle times and timeouts, which bit of
``VS_Health.VS_InputStatus`` each message owns (read from that signal's DBC comment), and the ``SAT_FRONT``
estimate/status signal pairs per model output.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from virtsensor import signals as cat
from virtsensor.canbus.codec import CanMatrix
from virtsensor.daemon.validity import PlausibilityRule, ValidityRules
from virtsensor.errors import UserError
from virtsensor.features import FeatureSpec
from virtsensor.signals import INPUT_TIMEOUT_CYCLES

__all__ = ["OUTPUT_SIGNALS", "SYNC_ID", "SYNC_OFFSET_S", "InputLayout", "Wheel", "bitmap_order", "check_references",
           "grip_references", "plausibility_rules", "read_feature_spec", "sync_frames"]

#: Sync frame id of ``demo`` and ``bench`` (standard 11-bit id, not in the DBC; ``run --sync-id`` takes any).
SYNC_ID = 0x7F0
#: A sync frame goes this long (s) after its 20 Hz instant: after every frame stamped at the instant (frame
#: phases are whole multiples of 0.25 ms), before any later one, and inside the offline table's 1 us
#: tolerance, so the daemon and the offline table see the same frames at each tick.
SYNC_OFFSET_S = 0.5e-6

#: Catalogue output -> (estimate, status) signal of SAT_FRONT.
OUTPUT_SIGNALS = {"sat_fl_nm": ("SAT_FL", "SAT_FL_Status"), "sat_fr_nm": ("SAT_FR", "SAT_FR_Status")}


@dataclass(frozen=True)
class Wheel:
    """One published estimate: model output index (-1: the model lacks it), SAT_FRONT signal names,
    catalogue range (Nm) an estimate must lie in to be sent."""

    output: int
    estimate: str
    status: str
    lo: float
    hi: float


def bitmap_order(matrix: CanMatrix) -> dict[str, int]:
    """Message -> bit of ``VS_Health.VS_InputStatus``, from the signal's DBC comment ("bit 0 IMU_Motion, ...")."""
    try:
        comment = matrix.db.get_message_by_name("VS_Health").get_signal_by_name("VS_InputStatus").comment or ""
    except (KeyError, AttributeError):
        return {}
    return {name: int(bit) for bit, name in re.findall(r"\bbit\s+(\d+)\s+([A-Za-z_]\w*)", comment)
            if name in matrix.messages and int(bit) < 8}


def read_feature_spec(model: Any) -> FeatureSpec:
    """The model card's ``feature_spec``, checked against the model's input names.

    Raises:
        UserError: no or invalid ``feature_spec``, or feature names that differ from the model's inputs.
    """
    card = model.card
    where = str(getattr(model, "card_path", "model card"))
    if not isinstance(card.get("feature_spec"), Mapping):
        raise UserError(f"{where}: the model card has no feature_spec (re-export the model with virtsensor train)")
    try:
        spec = FeatureSpec.from_json(card["feature_spec"])
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{where}: invalid feature_spec: {exc}") from None
    if tuple(model.input_names) != spec.names:
        raise UserError(f"{where}: feature_names {list(model.input_names)} differ from the feature_spec's "
                        f"{list(spec.names)}")
    return spec


def _critical(card: Mapping[str, Any], signals: tuple[str, ...]) -> tuple[bool, ...]:
    crit: dict[str, bool] = {}
    for entry in card.get("inputs") or ():
        if isinstance(entry, Mapping) and "critical" in entry:
            s = entry.get("signal", entry.get("name"))
            crit[s] = bool(entry["critical"]) or crit.get(s, False)
    return tuple(crit.get(s, cat.SIGNALS[s].critical) for s in signals)


def _wheels(model: Any, matrix: CanMatrix) -> tuple[Wheel, ...]:
    sat_names = {s.name for s in matrix.messages["SAT_FRONT"].signals}
    outs = tuple(model.outputs)
    wheels = []
    for out_name, (est, st) in OUTPUT_SIGNALS.items():
        if est not in sat_names or st not in sat_names:
            raise UserError(f"{matrix.source}: SAT_FRONT lacks {est}/{st}")
        spec = cat.SIGNALS[out_name]
        wheels.append(Wheel(outs.index(out_name) if out_name in outs else -1, est, st, spec.minimum, spec.maximum))
    if not any(w.output >= 0 for w in wheels):
        where = str(getattr(model, "card_path", "model card"))
        raise UserError(f"{where}: the model's outputs {list(outs)} include neither sat_fl_nm nor sat_fr_nm")
    return tuple(wheels)


def check_references(model_signals: Iterable[str], matrix: CanMatrix) -> tuple[str, ...]:
    """The signals the daemon reads for its plausibility checks alone, in catalogue order: those that a check of
    :data:`virtsensor.signals.REDUNDANCIES` reads beside its subjects, when they are model inputs, the model
    does not read them, and the DBC carries each of them in a message with a cycle time (a check whose signals
    the bus lacks is not run)."""
    model = set(model_signals)
    out: set[str] = set()
    for r in cat.REDUNDANCIES:
        if not all(s in model for s in r.subjects):
            continue
        extra = [s for s in r.reads if s not in model]
        if all((m := matrix.message_of(s)) is not None and matrix.messages[m].cycle_s > 0 for s in extra):
            out.update(extra)
    return tuple(s for s in cat.SIGNALS if s in out)


def grip_references(model_signals: Iterable[str], matrix: CanMatrix) -> tuple[str, ...]:
    """The signals the daemon reads for its grip estimate alone (VS_Grip): the front TPMS pressures
    (:data:`virtsensor.grip.PRESSURE_INPUTS`) that the model does not read, when the DBC carries VS_Grip and both
    pressures in messages with a cycle time and the model reads every other signal the estimate needs
    (:data:`virtsensor.grip.GRIP_INPUTS`); else none (no grip estimate, or one that reads the trail as measured)."""
    from virtsensor.grip import GRIP_INPUTS, PRESSURE_INPUTS

    model = set(model_signals)
    extra = [s for s in PRESSURE_INPUTS if s not in model]
    if "VS_Grip" not in matrix.messages or not model.issuperset(GRIP_INPUTS) or not all(
            (m := matrix.message_of(s)) is not None and matrix.messages[m].cycle_s > 0 for s in extra):
        return ()
    return tuple(extra)


def plausibility_rules(signals: Sequence[str]) -> tuple[PlausibilityRule, ...]:
    """The catalogue's redundancy checks (:data:`virtsensor.signals.REDUNDANCIES`) whose signals are all among
    ``signals`` (the daemon's decoded signals), laid out on their indices; steadiness rates (unit/s) become
    steps per 20 Hz tick."""
    idx = {s: i for i, s in enumerate(signals)}
    out = []
    for r in cat.REDUNDANCIES:
        if not all(s in idx for s in r.reads):
            continue
        turn = None if r.turn is None else (
            idx[r.references[0]], idx[r.references[1]], idx["steer_angle_rad"],
            1.0 / (r.turn.steer_ratio * r.turn.wheelbase_m), r.turn.min_yaw_radps, r.turn.lo, r.turn.hi)
        boost = None if r.boost is None else (
            tuple(map(float, r.boost.speeds_mps)), tuple(map(float, r.boost.gains)), float(r.boost.knee_nm),
            float(r.boost.max_nm))
        out.append(PlausibilityRule(
            r.name, idx[r.subject], tuple(idx[x] for x in r.references), float(r.scale), float(r.tolerance_abs),
            float(r.tolerance_rel), int(r.debounce_ticks), r.relation,
            tuple((idx[g], float(rate) / cat.TABLE_RATE_HZ) for g, rate in r.steady),
            tuple((idx[g], float(bound)) for g, bound in r.within), turn, boost,
            tuple((idx[g], float(bound)) for g, bound in r.above), float(r.max_expected), float(r.min_expected),
            int(r.window), idx[r.minus] if r.minus is not None else -1,
            tuple((idx[g], float(c)) for g, c in r.tolerance_per)))
    return tuple(out)


@dataclass(frozen=True)
class InputLayout:
    """What the daemon decodes and publishes (built by :meth:`from_model`; immutable).

    The daemon decodes :attr:`decoded`: the model's inputs (indices ``0 .. len(signals) - 1``, in spec order),
    then the check references (:func:`check_references`), which only the plausibility checks read, then the grip
    references (:func:`grip_references`), which only the grip estimate reads. A bad reference leaves its checks
    unjudged (its grip input unknown), never changes the estimate's status, and clears its message's health bit
    only when that message carries no model input (the bit of a message with model inputs speaks for them).

    Attributes:
        spec: the card's feature spec. signals: its input signals (catalogue names), in spec order.
        check_signals: the check references, after the model's inputs in :attr:`decoded`.
        grip_signals: the grip references, after the check references in :attr:`decoded`.
        critical: per model input, a bad value makes the estimate INVALID (else DEGRADED).
        signal_messages: per decoded signal, the DBC message carrying it.
        input_messages: messages decoded (carrying decoded signals, or owning a health bit), by frame id.
        cycles_s: per input message, its DBC cycle time (s).
        bitmap_bits: message -> its bit of ``VS_Health.VS_InputStatus``.
        wheels: the published estimates. model_id: the ``VS_ModelId`` byte.
        timeout_cycles: a message is stale after this many of its cycles without a usable frame.
    """

    spec: FeatureSpec
    signals: tuple[str, ...]
    check_signals: tuple[str, ...]
    critical: tuple[bool, ...]
    signal_messages: tuple[str, ...]
    input_messages: tuple[str, ...]
    cycles_s: tuple[float, ...]
    bitmap_bits: dict[str, int]
    wheels: tuple[Wheel, ...]
    model_id: int
    timeout_cycles: float
    grip_signals: tuple[str, ...] = ()

    @classmethod
    def from_model(cls, model: Any, matrix: CanMatrix, timeout_cycles: float = INPUT_TIMEOUT_CYCLES,
                   model_id: int | None = None) -> InputLayout:
        """Read the layout from ``model.card``/``model.input_names``/``model.outputs`` and the DBC.

        Raises:
            UserError: unusable card (see :func:`read_feature_spec`); an input the DBC lacks or whose message
                has no cycle time; SAT_FRONT/VS_Health missing or lacking the estimate/status signals.
        """
        spec = read_feature_spec(model)
        for name in ("SAT_FRONT", "VS_Health"):
            if name not in matrix.messages:
                raise UserError(f"{matrix.source}: the DBC has no {name} message, which the daemon sends")
        sig_msgs = []
        for s in spec.signals:
            m = matrix.message_of(s)
            if m is None:
                home = cat.SIGNALS[s].message if s in cat.SIGNALS else None
                raise UserError(f"model input {s} (message {home}) is not in the DBC {matrix.source}")
            if not matrix.messages[m].cycle_s > 0:
                raise UserError(f"{matrix.source}: message {m} (carrying model input {s}) has no GenMsgCycleTime")
            sig_msgs.append(m)
        checks = check_references(spec.signals, matrix)
        grips = tuple(s for s in grip_references(spec.signals, matrix) if s not in checks)
        sig_msgs += [str(matrix.message_of(s)) for s in checks + grips]
        # a message that carries none of the catalogue's inputs (the TPMS, the rear wheel speeds) has its bit only
        # when the daemon reads it (for the model, a check or the grip estimate)
        bit_of = {m: b for m, b in bitmap_order(matrix).items()
                  if m in sig_msgs or any(s.role == "input" for s in cat.by_message(m))}
        if not bit_of:  # no documented order: the input messages by frame id
            ordered = sorted(set(sig_msgs), key=lambda m: matrix.messages[m].frame_id)
            bit_of = {m: i for i, m in enumerate(ordered[:8])}
        messages = tuple(sorted(set(sig_msgs) | set(bit_of), key=lambda m: matrix.messages[m].frame_id))
        card = model.card
        if model_id is None:
            cid = card.get("model_id")
            model_id = cid if isinstance(cid, int) and 0 <= cid <= 255 else int(str(card.get("sha256", "00"))[:2], 16)
        return cls(spec=spec, signals=spec.signals, check_signals=checks, critical=_critical(card, spec.signals),
                   signal_messages=tuple(sig_msgs), input_messages=messages,
                   cycles_s=tuple(float(matrix.messages[m].cycle_s) for m in messages),
                   bitmap_bits=dict(bit_of), wheels=_wheels(model, matrix), model_id=int(model_id),
                   timeout_cycles=float(timeout_cycles), grip_signals=grips)

    @property
    def decoded(self) -> tuple[str, ...]:
        """Every signal the daemon decodes: the model's inputs, then the check references, then the grip's."""
        return self.signals + self.check_signals + self.grip_signals

    def message_index(self) -> dict[str, int]:
        """Input message name -> its index in :attr:`input_messages`."""
        return {m: j for j, m in enumerate(self.input_messages)}

    def signal_slots(self, j: int) -> list[int]:
        """Indices (into :attr:`decoded`) of the signals carried by input message ``j``."""
        name = self.input_messages[j]
        return [i for i, m in enumerate(self.signal_messages) if m == name]

    def plausibility_rules(self) -> tuple[PlausibilityRule, ...]:
        """The catalogue's redundancy checks on :attr:`decoded` (:func:`plausibility_rules`)."""
        return plausibility_rules(self.decoded)

    def rules(self) -> ValidityRules:
        """The constants of :func:`~virtsensor.daemon.validity.assess_inputs` for this layout."""
        mi = self.message_index()
        tc = self.timeout_cycles
        cyc = dict(zip(self.input_messages, self.cycles_s, strict=True))
        n = len(self.signals)
        model_msgs = set(self.signal_messages[:n])
        # a health bit speaks for the model's inputs in its message: a bad check reference clears it only in a
        # message that carries no model input (the rear wheel speeds; not the rear deflections of the suspension)
        bits = tuple(1 << self.bitmap_bits[m] if m in self.bitmap_bits and (i < n or m not in model_msgs) else 0
                     for i, m in enumerate(self.signal_messages))
        return ValidityRules(
            sig_msg=tuple(mi[m] for m in self.signal_messages),
            sig_timeout=tuple(tc * cyc[m] for m in self.signal_messages),
            sig_hist=tuple(max(f.history for f in self.spec.features if f.signal == s) for s in self.signals),
            critical=self.critical,
            sig_bit=bits,
            msg_timeout=tuple(tc * c for c in self.cycles_s),
            bitmap_msgs=tuple((mi[m], 1 << b) for m, b in self.bitmap_bits.items()))


def sync_frames(instants: Iterable[float], sync_id: int = SYNC_ID) -> list[Any]:
    """One ``can.Message`` per instant (s, log time): id ``sync_id`` (standard), no data, stamped
    :data:`SYNC_OFFSET_S` after the instant. A daemon in sync mode ticks once on each."""
    import can

    return [can.Message(timestamp=float(t) + SYNC_OFFSET_S, arbitration_id=sync_id, is_extended_id=False,
                        dlc=0, data=b"") for t in instants]
