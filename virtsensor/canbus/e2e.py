"""AUTOSAR E2E Profile 11 (Data ID mode BOTH) protection of the virtsensor CAN frames.

Frame layout (every message of ``dbc/virtsensor.dbc``, 8-byte classic CAN,
Intel/little-endian bit numbering, bit 0 = LSB of byte 0), the fixed header
of Profile 11 (``CRCOffset`` 0, ``CounterOffset`` 8)::

    byte 0        <Msg>_CRC      8 bits, start bit 0
    byte 1 [3:0]  <Msg>_Counter  4 bits, start bit 8: 0..14, +1 modulo 15 per frame (15 is invalid)
    bit 12..63    the signals of the message

Data ID mode BOTH: the 16-bit data ID is not transmitted; both of its bytes
enter the CRC (so bits 12..15, which mode NIBBLE would use for the data ID's
high nibble, carry signals).

CRC (exactly what ``E2E_P11Protect`` computes)::

    crc = CRC8( [data_id & 0xFF, data_id >> 8] + payload[1:length] )

where ``CRC8`` is the Crc library's CRC-8/SAE-J1850 polynomial 0x1D, chained
the way the profile calls it (``Crc_CalculateCRC8(..., StartValue 0xFF,
IsFirstCall FALSE)``): the register starts at ``0xFF ^ 0xFF = 0x00`` and no
final XOR remains, i.e. polynomial 0x1D, register start 0x00, final XOR 0x00,
no reflection. (The stand-alone CRC-8/SAE-J1850, :func:`crc8_sae_j1850`, has
start 0xFF and final XOR 0xFF; it shares the table and the loop.)

Why Profile 11 and not Profile 1: the frames already had Profile 11's fixed
header (CRC in byte 0, counter in the low nibble of byte 1), Profile 11 is the
CAN profile of the current AUTOSAR releases (Profile 1 is kept for legacy
ECUs), and its per-frame check is a pure function of the last counter (no
``WaitForFirstData``/``SyncCounter``/``MaxNoNewOrRepeatedData`` state and no
``INITIAL``/``SYNC`` statuses). Mode BOTH keeps all 52 payload bits and puts
all 16 bits of the data ID into the CRC (mode NIBBLE would cost 4 bits).

Receiver side: :class:`E2EReceiver` is the ``E2E_P11CheckStateType`` with the
``E2E_P11Check`` rules (see its docstring). The profile-independent state
machine ``E2E_SMCheck`` (NODATA/INIT/VALID/INVALID over a window of statuses)
is not implemented: the daemon judges each message by its own timeout and the
per-tick error flag instead.
"""

from __future__ import annotations

from collections.abc import Iterable
from enum import IntEnum
from typing import Any

__all__ = [
    "COUNTER_MAX",
    "COUNTER_MODULO",
    "CRC8_INIT",
    "CRC8_POLY",
    "CRC8_TABLE",
    "CRC8_XOROUT",
    "GAP_TOLERANCE_S",
    "P11_CRC_START",
    "P11_CRC_XOROUT",
    "USABLE",
    "E2EReceiver",
    "E2EStatus",
    "counter_sequence",
    "crc8_register",
    "crc8_sae_j1850",
    "data_id_seed",
    "frame_crc",
    "next_counter",
]

CRC8_POLY = 0x1D
#: start value and final XOR of the stand-alone CRC-8/SAE-J1850 (``Crc_CalculateCRC8`` with IsFirstCall TRUE)
CRC8_INIT = 0xFF
CRC8_XOROUT = 0xFF
#: Profile 11's effective register start and final XOR (see the module docstring)
P11_CRC_START = 0x00
P11_CRC_XOROUT = 0x00

#: largest valid alive counter; the counter counts 0..COUNTER_MAX and wraps to 0
COUNTER_MAX = 14
COUNTER_MODULO = COUNTER_MAX + 1
#: The rounding of float timestamps a gap may carry beyond the timeout (s): a frame exactly one timeout after the
#: previous one, ``0.01`` cycles apart summed as floats, is on time.
GAP_TOLERANCE_S = 1e-6


def _make_table(poly: int) -> bytes:
    table = bytearray(256)
    for i in range(256):
        c = i
        for _ in range(8):
            c = ((c << 1) ^ poly) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        table[i] = c
    return bytes(table)


#: Byte-wise lookup table of the non-reflected CRC-8 with polynomial 0x1D.
CRC8_TABLE: bytes = _make_table(CRC8_POLY)


def crc8_register(state: Any, data: Iterable[Any], table: Any = CRC8_TABLE) -> Any:
    """Feed ``data`` into a raw CRC-8 register (before any final XOR) and return the new register.

    The one CRC loop of the package. ``state`` is an int and ``data`` bytes, or (vectorised over
    frames) ``state`` a uint8 array, ``data`` an iterable of uint8 columns and ``table`` the table
    as a uint8 numpy array.
    """
    for b in data:
        state = table[state ^ b]
    return state


def crc8_sae_j1850(data: bytes | bytearray | memoryview | str) -> int:
    """CRC-8/SAE-J1850 of ``data`` (str is encoded as ASCII). ``crc8_sae_j1850("123456789") == 0x4B``."""
    if isinstance(data, str):
        data = data.encode("ascii")
    return crc8_register(CRC8_INIT, data) ^ CRC8_XOROUT


def data_id_seed(data_id: int) -> int:
    """Profile 11 CRC register after the two data-ID bytes (low byte first): precompute once per message.

    Raises:
        ValueError: the data ID is not 16-bit.
    """
    if not 0 <= data_id <= 0xFFFF:
        raise ValueError(f"E2E data ID {data_id:#x} is not 16-bit")
    return crc8_register(P11_CRC_START, (data_id & 0xFF, data_id >> 8))


def frame_crc(seed: int, payload: bytes | bytearray | memoryview) -> int:
    """The Profile 11 CRC byte of ``payload`` given the message's :func:`data_id_seed`.

    Byte 0 of ``payload`` (the CRC position) is ignored.
    """
    return crc8_register(seed, memoryview(payload)[1:]) ^ P11_CRC_XOROUT


def next_counter(counter: int) -> int:
    """The alive counter a sender puts in its next frame: ``counter + 1`` modulo 15 (14 wraps to 0)."""
    return (counter + 1) % COUNTER_MODULO


def counter_sequence(start: int, n: int) -> Any:
    """The ``n`` alive counters of consecutive frames from ``start`` (numpy int64 array): :func:`next_counter`
    applied ``0..n-1`` times."""
    import numpy as np

    return (int(start) + np.arange(n, dtype=np.int64)) % COUNTER_MODULO


class E2EStatus(IntEnum):
    """Per-frame check status, the values of AUTOSAR ``E2E_P11CheckStatusType``."""

    OK = 0x00  #: CRC fine, counter advanced by exactly 1.
    NONEWDATA = 0x01  #: no frame received (see :meth:`E2EReceiver.poll`).
    ERROR = 0x07  #: CRC mismatch, wrong length (DLC) or invalid counter 15: the frame is rejected.
    REPEATED = 0x08  #: CRC fine, counter unchanged (delta 0): a repetition, data is not new.
    OKSOMELOST = 0x20  #: CRC fine, counter advanced by 2..max_delta: some frames lost.
    WRONGSEQUENCE = 0x40  #: CRC fine, counter advanced by more than max_delta.
    NODATA = 0x01  #: alias of NONEWDATA


#: Statuses whose data a receiver may use (fresh and intact): those ``E2E_P11MapStatusToSM`` maps to OK.
USABLE = frozenset({E2EStatus.OK, E2EStatus.OKSOMELOST})

_OK = E2EStatus.OK
_REPEATED = E2EStatus.REPEATED
_OKSOMELOST = E2EStatus.OKSOMELOST
_WRONGSEQUENCE = E2EStatus.WRONGSEQUENCE
_ERROR = E2EStatus.ERROR
_NONEWDATA = E2EStatus.NONEWDATA
_NEVER = float("-inf")
assert (COUNTER_MAX, COUNTER_MODULO) == (14, 15)  # E2EReceiver.check spells them out


class E2EReceiver:
    """The Profile 11 check state of one message and its per-frame check (allocation-free).

    ``E2E_P11CheckInit``: ``counter = 14``, ``status = ERROR``. Per received frame (:meth:`check`):

    * wrong length, CRC mismatch, or counter 15 -> ``ERROR``; the state is left unchanged;
    * else with ``d = (counter - self.counter) mod 15``: ``d == 0`` -> ``REPEATED``, ``d == 1`` -> ``OK``,
      ``2 <= d <= max_delta`` -> ``OKSOMELOST``, else ``WRONGSEQUENCE``; in every one of these cases the
      state takes the received counter (so a jump costs one frame).

    So the first frame after start is ``OK`` when its counter is 0 (a sender starts at 0). No ``INITIAL``
    status exists in Profile 11.

    Time (not part of the profile's check, which sees counters only): the gap ``t - last_rx_s`` since the
    last frame that passed the CRC must satisfy ``0 <= gap <= timeout_s``. A frame stamped before that one
    (a time step back), or after a gap longer than ``timeout_s`` (the 4-bit counter cannot tell how many
    frames were lost), or at a NaN time is ``WRONGSEQUENCE`` whatever its counter; the state takes its
    counter and time, so it costs one frame, as a counter jump does. (Before any frame, ``last_rx_s`` is
    -inf and only the counter judges.)

    Timeout supervision (the caller's "no new data" call): :meth:`poll` reports ``NONEWDATA`` unless
    ``0 <= now - last_rx_s <= timeout_s``: nothing received yet, overdue, or a last frame stamped after
    ``now`` (a future stamp is not fresh data).

    Attributes:
        max_delta: ``MaxDeltaCounter``, 1..14 (default 3: up to 2 lost frames still OKSOMELOST).
        timeout_s: reception timeout in seconds for :meth:`poll` (e.g. 3 x the message cycle).
        limit_s: ``timeout_s`` plus :data:`GAP_TOLERANCE_S`, the gap both checks allow (frames exactly
            ``timeout_s`` apart pass, whatever the rounding of their float timestamps).
        counter: the last received counter (14 after init).
        last_rx_s: receive time (s, the frame timestamps' clock) of the last frame that passed the CRC.
        status: the most recent status.
    """

    __slots__ = ("max_delta", "timeout_s", "limit_s", "counter", "last_rx_s", "status")

    def __init__(self, max_delta: int = 3, timeout_s: float = float("inf")) -> None:
        if not 1 <= max_delta <= COUNTER_MAX:
            raise ValueError(f"max_delta must be 1..{COUNTER_MAX}, got {max_delta}")
        self.max_delta = max_delta
        self.timeout_s = timeout_s
        self.limit_s = timeout_s + GAP_TOLERANCE_S
        self.counter = COUNTER_MAX
        self.last_rx_s = _NEVER
        self.status: E2EStatus = _ERROR

    def reset(self) -> None:
        """``E2E_P11CheckInit``: back to the initial state."""
        self.counter = COUNTER_MAX
        self.last_rx_s = _NEVER
        self.status = _ERROR

    def check(self, counter: int, intact: bool, t: float) -> E2EStatus:
        """Status of one received frame (``E2E_P11Check`` with new data).

        Args:
            counter: received alive counter (the low nibble of byte 1, 0..15).
            intact: CRC matched and the length is right.
            t: receive timestamp in seconds.
        """
        # literals: COUNTER_MAX (14) and COUNTER_MODULO (15), spelt out on this per-frame path
        if not intact or counter > 14:
            self.status = _ERROR
            return _ERROR
        d = counter - self.counter
        if d < 0:
            d += 15
        last = self.last_rx_s
        if not (0.0 <= t - last <= self.limit_s) and last != _NEVER:
            st = _WRONGSEQUENCE  # time step back, gap past the timeout, or NaN time: the counter says nothing
        elif d == 1:
            st = _OK
        elif d == 0:
            st = _REPEATED
        elif d <= self.max_delta:
            st = _OKSOMELOST
        else:
            st = _WRONGSEQUENCE
        self.counter = counter
        self.last_rx_s = t
        self.status = st
        return st

    def poll(self, now: float) -> E2EStatus:
        """Timeout supervision at ``now`` (s): ``NONEWDATA`` unless ``0 <= now - last_rx_s <= timeout_s``
        (received, not overdue, not stamped after ``now``), else the last status."""
        if not (0.0 <= now - self.last_rx_s <= self.limit_s):
            self.status = _NONEWDATA
        return self.status
