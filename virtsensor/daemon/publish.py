"""The daemon's output frames: ``SAT_FRONT`` and ``VS_Health``, preallocated, encoded by generated encoders.

:func:`virtsensor.canbus.codec.compile_encoder` gives, byte for byte, what :meth:`CanMatrix.encode` gives with
the message's layout unrolled. Each message's E2E alive counter advances in :meth:`Publisher.fill_sat` /
:meth:`Publisher.fill_health` only, through :func:`next_counter` (a send that fails still advances it, so a
receiver sees the lost frame as a counter gap).
"""

from __future__ import annotations

import functools
import math
from typing import Any

from virtsensor.canbus.codec import CanMatrix, compile_encoder
from virtsensor.canbus.e2e import next_counter
from virtsensor.daemon.gripout import grip_output
from virtsensor.daemon.layout import InputLayout
from virtsensor.daemon.receive import StageHook
from virtsensor.daemon.validity import INIT

__all__ = ["Publisher"]


@functools.cache
def _out_message_class() -> Any:
    import can

    class _OutMessage(can.Message):
        """An output frame whose deep copy is a plain ``can.Message`` built field by field."""

        __slots__ = ()

        def __deepcopy__(self, memo: Any) -> can.Message:
            m = can.Message.__new__(can.Message)
            m.timestamp, m.arbitration_id, m.is_extended_id = self.timestamp, self.arbitration_id, self.is_extended_id
            m.is_remote_frame, m.is_error_frame, m.channel = self.is_remote_frame, self.is_error_frame, self.channel
            m.dlc, m.data, m.is_fd, m.is_rx = self.dlc, bytearray(self.data), self.is_fd, self.is_rx
            m.bitrate_switch, m.error_state_indicator = self.bitrate_switch, self.error_state_indicator
            return m

    return _OutMessage


def out_message(frame_id: int, length: int) -> Any:
    """A preallocated output frame (standard id, ``length`` data bytes) whose deep copy is a plain ``can.Message``
    built field by field, its data one C-level bytearray copy: python-can's ``virtual`` bus deep-copies every sent
    message once per receiving bus, and ``Message.__deepcopy__`` goes through the full constructor and the generic
    deep copy of the data. Other interfaces only read the frame."""
    return _out_message_class()(arbitration_id=frame_id, is_extended_id=False, dlc=length, data=bytearray(length))


class Publisher:
    """Preallocated ``can.Message`` objects and value dicts of SAT_FRONT and VS_Health, and their counters.

    Attributes:
        sat_values: SAT_FRONT signal -> value (estimate in Nm, nan -> SNA; status code), written by the tick.
        health_values: VS_Health signal -> value (``VS_ModelId`` fixed).
        sat_msg, health_msg: the frames (their ``data`` rewritten in place by the fill methods).
    """

    def __init__(self, layout: InputLayout, matrix: CanMatrix, hook: StageHook | None = None) -> None:
        sat_m, health_m = matrix.messages["SAT_FRONT"], matrix.messages["VS_Health"]
        enc = compile_encoder(sat_m)
        self._encode_sat = hook("encode", enc) if hook is not None else enc
        self._encode_health = compile_encoder(health_m)
        self.sat_msg = out_message(sat_m.frame_id, sat_m.length)
        self.health_msg = out_message(health_m.frame_id, health_m.length)
        self.sat_values: dict[str, float] = {}
        for w in layout.wheels:
            self.sat_values[w.estimate] = math.nan
            self.sat_values[w.status] = INIT
        self.health_values: dict[str, float] = {"VS_TickOverruns": 0, "VS_TickLatency": 0, "VS_InputStatus": 0,
                                                "VS_ModelId": layout.model_id, "VS_OutOfEnvelope": 0,
                                                "VS_EnvelopeExits": 0}  # (a DBC without a signal ignores it)
        self._sat_ctr = 0
        self._health_ctr = 0
        #: the VS_Grip frame and the grip estimate (a stand-in that sends nothing when the DBC has no VS_Grip)
        self.grip = grip_output(matrix, layout.decoded, layout.wheels, model_signals=layout.signals)

    def fill_sat(self) -> Any:
        """Encode :attr:`sat_values` into :attr:`sat_msg` with the next alive counter; returns the message."""
        m = self.sat_msg
        m.data[:] = self._encode_sat(self.sat_values, self._sat_ctr)
        self._sat_ctr = next_counter(self._sat_ctr)
        return m

    def fill_health(self, overruns: int, latency_us: int, bitmap: int, out_of_envelope: bool = False,
                    envelope_exits: int = 0) -> Any:
        """Encode VS_Health (values saturate at the DBC's raw range) with the next counter; returns it."""
        hv = self.health_values
        hv["VS_TickOverruns"] = overruns
        hv["VS_TickLatency"] = latency_us
        hv["VS_InputStatus"] = bitmap
        hv["VS_OutOfEnvelope"] = out_of_envelope
        hv["VS_EnvelopeExits"] = envelope_exits
        m = self.health_msg
        m.data[:] = self._encode_health(hv, self._health_ctr)
        self._health_ctr = next_counter(self._health_ctr)
        return m
