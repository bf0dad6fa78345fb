"""End-to-end (E2E) protection of the virtsensor CAN frames, in the manner of AUTOSAR E2E Profile 1/11.

Frame layout (every message of ``dbc/virtsensor.dbc``, 8-byte classic CAN,
Intel/little-endian bit numbering, bit 0 = LSB of byte 0)::

    byte 0        <Msg>_CRC      8 bits, start bit 0
    byte 1 [3:0]  <Msg>_Counter  4 bits, start bit 8 (alive counter 0..15, +1 mod 16 per frame)
    bit 12..63    the signals of the message

CRC definition (exactly)::

    CRC-8/SAE-J1850: width 8, poly 0x1D, init 0xFF, no reflection, xorout 0xFF
    (check value over ASCII "123456789" = 0x4B)

    crc = CRC8_SAE_J1850( [data_id & 0xFF, data_id >> 8] + payload[1:8] )

i.e. one CRC over the two bytes of the message's 16-bit data ID (low byte
first; the data ID is *not* transmitted, as in Profile 1 ``DataIDMode = BOTH``)
followed by payload bytes 1..7 (everything except the CRC byte itself).
Deviation from Profile 1/11: the counter uses all 16 values 0..15 (0xF is not
reserved) and wraps 15 -> 0.

Receiver side: :class:`E2EReceiver` keeps the per-message state and returns an
:class:`E2EStatus` per frame (see its docstring for the rules).
"""

from __future__ import annotations

from enum import IntEnum

__all__ = [
    "CRC8_POLY",
    "CRC8_TABLE",
    "CRC8_INIT",
    "CRC8_XOROUT",
    "crc8_sae_j1850",
    "crc8_update",
    "data_id_seed",
    "frame_crc",
    "E2EStatus",
    "E2EReceiver",
    "USABLE",
]

CRC8_POLY = 0x1D
CRC8_INIT = 0xFF
CRC8_XOROUT = 0xFF


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


def crc8_update(state: int, data: bytes | bytearray | memoryview) -> int:
    """Feed ``data`` into a raw (not yet xor-ed out) CRC register and return the new register."""
    t = CRC8_TABLE
    for b in data:
        state = t[state ^ b]
    return state


def crc8_sae_j1850(data: bytes | bytearray | memoryview | str) -> int:
    """CRC-8/SAE-J1850 of ``data`` (str is encoded as ASCII). ``crc8_sae_j1850("123456789") == 0x4B``."""
    if isinstance(data, str):
        data = data.encode("ascii")
    return crc8_update(CRC8_INIT, data) ^ CRC8_XOROUT


def data_id_seed(data_id: int) -> int:
    """CRC register after the two data-ID bytes (low byte first): precompute once per message."""
    if not 0 <= data_id <= 0xFFFF:
        raise ValueError(f"E2E data ID {data_id:#x} is not 16-bit")
    return crc8_update(CRC8_INIT, bytes((data_id & 0xFF, data_id >> 8)))


def frame_crc(seed: int, payload: bytes | bytearray | memoryview) -> int:
    """The CRC byte of an 8-byte ``payload`` given the message's :func:`data_id_seed`.

    Byte 0 of ``payload`` (the CRC position) is ignored.
    """
    t = CRC8_TABLE
    s = seed
    for i in range(1, len(payload)):
        s = t[s ^ payload[i]]
    return s ^ CRC8_XOROUT


class E2EStatus(IntEnum):
    """Receiver-side status of one message, after AUTOSAR ``E2E_P01CheckStatusType``."""

    OK = 0  #: CRC fine, counter advanced by exactly 1.
    NODATA = 1  #: no frame within the timeout (see :meth:`E2EReceiver.poll`).
    REPEATED = 8  #: CRC fine, counter unchanged (delta 0): a repetition, data is not new.
    OKSOMELOST = 0x20  #: CRC fine, counter advanced by 2..max_delta: some frames lost.
    WRONGSEQUENCE = 0x40  #: CRC fine, counter jumped by more than max_delta.
    ERROR = 0x80  #: CRC mismatch or wrong length (DLC): the frame is rejected.
    INITIAL = 0x90  #: first valid frame since start or since a timeout: counter not checkable.


#: Statuses whose data a receiver may use (fresh and intact).
USABLE = frozenset({E2EStatus.OK, E2EStatus.OKSOMELOST, E2EStatus.INITIAL})

_OK = E2EStatus.OK
_REPEATED = E2EStatus.REPEATED
_OKSOMELOST = E2EStatus.OKSOMELOST
_WRONGSEQUENCE = E2EStatus.WRONGSEQUENCE
_ERROR = E2EStatus.ERROR
_INITIAL = E2EStatus.INITIAL
_NODATA = E2EStatus.NODATA


class E2EReceiver:
    """Per-message receiver state machine (allocation-free per frame).

    Rules (counter delta ``d = (counter - last_valid_counter) mod 16``):

    * CRC mismatch or wrong length -> ``ERROR``; the state (last counter) is
      left unchanged, so the next good frame reports the frames lost meanwhile.
    * First intact frame, or first one after a ``NODATA`` timeout -> ``INITIAL``.
    * ``d == 0`` -> ``REPEATED``; ``d == 1`` -> ``OK``;
      ``2 <= d <= max_delta`` -> ``OKSOMELOST``; ``d > max_delta`` ->
      ``WRONGSEQUENCE``. In each case the counter is re-synchronised to the
      received one (so a single jump costs one frame, as in Profile 1's resync).
    * :meth:`poll` at time ``now`` returns ``NODATA`` when no intact frame has
      arrived for longer than ``timeout_s`` (or ever), and then re-initialises.

    Attributes:
        max_delta: largest accepted counter delta (default 3: up to 2 lost frames).
        timeout_s: reception timeout in seconds (e.g. 3 x the message cycle).
        last_counter: last valid counter (-1 before the first frame).
        last_rx_s: receive time (s, the frame timestamp's clock) of the last intact frame.
        status: the most recent status.
    """

    __slots__ = ("max_delta", "timeout_s", "last_counter", "last_rx_s", "status")

    def __init__(self, max_delta: int = 3, timeout_s: float = float("inf")) -> None:
        if not 1 <= max_delta <= 15:
            raise ValueError(f"max_delta must be 1..15, got {max_delta}")
        self.max_delta = max_delta
        self.timeout_s = timeout_s
        self.last_counter = -1
        self.last_rx_s = float("-inf")
        self.status: E2EStatus = _NODATA

    def reset(self) -> None:
        """Back to the initial state (next intact frame is ``INITIAL``)."""
        self.last_counter = -1
        self.last_rx_s = float("-inf")
        self.status = _NODATA

    def check(self, counter: int, intact: bool, t: float) -> E2EStatus:
        """Status of one received frame.

        Args:
            counter: received alive counter (0..15).
            intact: CRC matched and length is right.
            t: receive timestamp in seconds.
        """
        if not intact:
            self.status = _ERROR
            return _ERROR
        last = self.last_counter
        if last < 0 or t - self.last_rx_s > self.timeout_s:
            st = _INITIAL
        else:
            d = (counter - last) & 0xF
            if d == 1:
                st = _OK
            elif d == 0:
                st = _REPEATED
            elif d <= self.max_delta:
                st = _OKSOMELOST
            else:
                st = _WRONGSEQUENCE
        self.last_counter = counter
        self.last_rx_s = t
        self.status = st
        return st

    def poll(self, now: float) -> E2EStatus:
        """Timeout supervision at ``now`` (s): ``NODATA`` if the message is overdue, else the last status."""
        if now - self.last_rx_s > self.timeout_s:
            self.last_counter = -1
            self.status = _NODATA
        return self.status
