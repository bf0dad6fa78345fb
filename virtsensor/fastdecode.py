"""Per-message decoders generated at start-up from the DBC's signal definitions (the daemon's receive path).

:meth:`virtsensor.can_codec.CanMatrix.decode` is general: it loops over a message's signals, reads each
one's attributes, builds dicts and a :class:`~virtsensor.can_codec.DecodedFrame` per frame (about 3.5 us
a frame). At 600 input frames a second, or 30 per tick when ticking as fast as possible, that loop was
the larger half of the daemon's cost. This module writes, once per message, a small Python function with
every constant (byte count, CRC seed, bit positions, masks, sign bits, scale, offset, ranges, SNA codes)
inlined, and compiles it with :func:`exec`: no per-frame attribute look-ups, loops, dicts or frame objects.

* :func:`compile_decoder` -- a cantools ``Message`` -> ``decode(data) -> tuple`` of the DBC physical
  values (``raw * scale + offset``, no choices), exactly what ``Message.decode(data, decode_choices=False)``
  returns; the tests compare both on random frames of every message of ``dbc/virtsensor.dbc``.
* :func:`compile_encoder` -- ``encode(values, counter) -> bytes`` of a compiled message, byte for byte what
  :meth:`CanMatrix.encode` gives (the daemon's SAT_FRONT and VS_Health).
* :func:`compile_receiver` -- the daemon's handler of one input message: DLC, CRC (CRC-8/SAE-J1850
  unrolled over the payload bytes, table-driven), the :class:`~virtsensor.e2e.E2EReceiver` check, then the
  model's input signals of that message decoded straight into the daemon's sample-and-hold lists, with the
  same arithmetic, SNA and plausibility rules as :meth:`CanMatrix.decode` (tests drive both on random frames
  and compare the state they leave).

Only Intel (little-endian) integer signals without multiplexing are supported, as in the codec.
"""

from __future__ import annotations

from collections.abc import Callable, MutableMapping, MutableSequence, Sequence
from typing import Any

from virtsensor.e2e import CRC8_TABLE, CRC8_XOROUT, E2EReceiver, E2EStatus

__all__ = ["STATUS_KEYS", "compile_decoder", "compile_encoder", "compile_receiver", "crc_ok_expr", "raw_expr"]

#: ``E2EStatus`` -> its counter name (``e2e_ok``...), for the generated receivers and the daemon's counters.
STATUS_KEYS = {s: f"e2e_{s.name.lower()}" for s in E2EStatus}


def raw_expr(start: int, length: int, signed: bool) -> str:
    """Python expression of a signal's raw integer from the payload read as one little-endian int ``v``.

    Signed raws use ``(u ^ s) - s`` with ``s`` the sign bit: two's complement without a branch.
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
    """The unrolled table-driven CRC-8/SAE-J1850 register over the data-ID ``seed`` then the locals
    ``b1``..``b{length-1}`` (one look-up in ``T`` per byte), before the final XOR."""
    e = f"{seed:#04x}"
    for i in range(1, length):
        e = f"T[{e} ^ b{i}]"
    return e


def crc_ok_expr(seed: int, length: int) -> str:
    """Expression that is True when byte 0 (``b0``) is the CRC-8/SAE-J1850 of the message's data-ID
    seed followed by bytes 1..length-1 (locals ``b1``...), one table look-up per byte, unrolled."""
    if length < 2:
        raise ValueError("an E2E-protected payload has at least 2 bytes")
    return f"({_crc_chain(seed, length)} ^ {CRC8_XOROUT:#04x}) == b0"


def _check_signal(message_name: str, s: Any) -> None:
    if getattr(s, "byte_order", "little_endian") != "little_endian":
        raise ValueError(f"{message_name}.{s.name}: only Intel (little-endian) signals are supported")
    if getattr(s, "is_float", False):
        raise ValueError(f"{message_name}.{s.name}: float signals are not supported")
    if getattr(s, "multiplexer_ids", None):
        raise ValueError(f"{message_name}.{s.name}: multiplexed signals are not supported")


def _compile(src: str, name: str, env: dict[str, Any]) -> Callable[..., Any]:
    code = compile(src, f"<virtsensor.fastdecode {name}>", "exec")
    ns: dict[str, Any] = dict(env)
    exec(code, ns)  # noqa: S102 - our own generated source, built from numbers only
    fn = ns[name]
    fn.__source__ = src  # for the curious (and the tests)
    return fn


def _ident(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name)


def compile_decoder(message: Any, names: Sequence[str] | None = None) -> Callable[[bytes | bytearray], tuple]:
    """``decode(data) -> tuple`` of the DBC physical values of ``names`` (default: every signal, in the
    message's order) of a cantools ``Message``, as ``Message.decode(data, decode_choices=False)`` gives them
    (same types: integer scale and offset keep integers). Raises ValueError for a payload of the wrong length.
    """
    sigs = list(message.signals)
    if names is not None:
        by = {s.name: s for s in sigs}
        sigs = [by[n] for n in names]
    lines = [f"def {(fn := 'decode_' + _ident(message.name))}(data):",
             f"    if len(data) != {message.length}:",
             f"        raise ValueError('{message.name}: expected {message.length} bytes, got %d' % len(data))",
             "    v = int.from_bytes(data, 'little')"]
    out = []
    for k, s in enumerate(sigs):
        _check_signal(message.name, s)
        conv = s.conversion
        scale, offset = conv.scale, conv.offset
        raw = raw_expr(s.start, s.length, bool(s.is_signed))
        if type(scale) is int and type(offset) is int and scale == 1 and offset == 0:
            lines.append(f"    x{k} = {raw}")
        else:
            lines.append(f"    x{k} = {raw} * {scale!r} + {offset!r}")
        out.append(f"x{k}")
    lines.append(f"    return ({', '.join(out)}{',' if len(out) == 1 else ''})")
    return _compile("\n".join(lines) + "\n", fn, {})


def compile_encoder(message: Any) -> Callable[[Any, int], bytes]:
    """``encode(values, counter) -> bytes`` of a compiled :class:`~virtsensor.can_codec.MessageCodec`:
    the payload :meth:`CanMatrix.encode` returns for the same arguments (catalogue names first, then DBC
    names; missing or nan -> SNA (0 without one); clipped to the raw range; CRC and counter filled).
    """
    L = int(message.length)
    if L < 2:
        raise ValueError(f"{message.name}: an E2E-protected payload has at least 2 bytes")
    fn = "encode_" + _ident(message.name)
    lines = [f"def {fn}(values, counter):", "    get = values.get", "    p = (counter & 15) << 8"]
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
                  f"        x = (v * {float(s.si_factor)!r} - {float(s.offset)!r}) / {float(s.scale)!r}",
                  f"        r = {lo} if x <= {lo} else {hi} if x >= {hi} else round(x)",
                  f"    p |= (r & {s.mask:#x}) << {int(s.start)}"]
    lines.append(f"    {', '.join(f'b{i}' for i in range(1, L))}, = p.to_bytes({L}, 'little')[1:]")
    crc = _crc_chain(int(message.seed), L)
    lines.append(f"    return bytes(({crc} ^ {CRC8_XOROUT:#04x}, {', '.join(f'b{i}' for i in range(1, L))}))")
    return _compile("\n".join(lines) + "\n", fn, {"T": CRC8_TABLE})


def compile_receiver(
    message: Any,
    receiver: E2EReceiver,
    msg_index: int,
    slots: Sequence[tuple[Any, int]],
    values: MutableSequence[float],
    times: MutableSequence[float],
    flags: MutableSequence[bool],
    last_ok: MutableSequence[float],
    errors: MutableSequence[bool],
    counters: MutableMapping[str, int],
) -> Callable[[bytes | bytearray, float], None]:
    """The daemon's handler ``rx(data, t)`` of one input message (a compiled
    :class:`~virtsensor.can_codec.MessageCodec`).

    Per frame, with the semantics of :meth:`CanMatrix.decode` followed by the daemon's bookkeeping:

    * wrong length -> ``receiver.check(0, False, t)`` (ERROR), ``errors[msg_index] = True``,
      ``counters['e2e_error']`` and ``counters['dlc_errors']`` + 1;
    * CRC mismatch -> the same with ``crc_errors``;
    * else ``st = receiver.check(counter, True, t)``, ``counters['e2e_<st>']`` + 1; REPEATED or
      WRONGSEQUENCE -> ``errors[msg_index] = True``; OK, OKSOMELOST or INITIAL -> ``last_ok[msg_index] = t``
      and for each ``(signal_codec, i)`` of ``slots``: SNA -> ``flags[i] = True`` and ``sna_values`` + 1;
      ``(raw * scale + offset) / si_factor`` outside the catalogue range (+-1e-9) -> ``flags[i] = True``
      and ``implausible_values`` + 1; else ``values[i]``, ``times[i] = value, t`` and ``flags[i] = False``.

    The lists are captured by reference: mutate them in place, never rebind them.
    """
    L = int(message.length)
    if L < 2:
        raise ValueError(f"{message.name}: an E2E-protected payload has at least 2 bytes")
    j = int(msg_index)
    fn = "rx_" + _ident(message.name)
    bs = ", ".join(f"b{i}" for i in range(L))
    lines = [
        f"def {fn}(data, t):",
        f"    if len(data) != {L}:",
        "        check(0, False, t)",
        "        counters['e2e_error'] += 1",
        "        counters['dlc_errors'] += 1",
        f"        errors[{j}] = True",
        "        return",
        f"    {bs} = data",
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
        "        if st is not INITIAL and st is not OKSOMELOST:",
        f"            errors[{j}] = True",
        "            return",
        f"    last_ok[{j}] = t",
    ]
    if slots:
        lines.append("    v = int.from_bytes(data, 'little')")
    for s, i in slots:
        i = int(i)
        raw = raw_expr(s.start, s.length, bool(s.signed))
        lines.append(f"    r = {raw}")
        ind = "    "
        if s.sna is not None:
            lines += [f"    if r == {int(s.sna)}:",
                      f"        flags[{i}] = True",
                      "        counters['sna_values'] += 1",
                      "    else:"]
            ind = "        "
        # the very expression and bounds of CanMatrix.decode (bit-identical values)
        lines += [f"{ind}x = (r * {float(s.scale)!r} + {float(s.offset)!r}) / {float(s.si_factor)!r}",
                  f"{ind}if {s.lo_si - 1e-9!r} <= x <= {s.hi_si + 1e-9!r}:",
                  f"{ind}    values[{i}] = x",
                  f"{ind}    times[{i}] = t",
                  f"{ind}    flags[{i}] = False",
                  f"{ind}else:",
                  f"{ind}    flags[{i}] = True",
                  f"{ind}    counters['implausible_values'] += 1"]
    src = "\n".join(lines) + "\n"
    # "inf": the repr of an unbounded range (a signal without a catalogue range) in the bounds above
    env = {"T": CRC8_TABLE, "check": receiver.check, "counters": counters, "errors": errors, "last_ok": last_ok,
           "values": values, "times": times, "flags": flags, "KEYS": STATUS_KEYS, "OK": E2EStatus.OK,
           "INITIAL": E2EStatus.INITIAL, "OKSOMELOST": E2EStatus.OKSOMELOST, "inf": float("inf")}
    return _compile(src, fn, env)
