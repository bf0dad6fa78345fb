"""The daemon's ``VS_Grip`` frame: the grip margin (:mod:`virtsensor.grip`) from the tick's SAT estimate.

Each tick, after ``SAT_FRONT`` is filled, :meth:`GripOutput.fill` runs one step of the grip estimate on the
published SATs and the tick's input values (the front TPMS pressures too, where the daemon decodes them and both
are usable: :meth:`~virtsensor.grip.GripEstimator.set_front_pressure`) and encodes ``VS_Grip`` with its own E2E
alive counter (Profile 11, data ID from the catalogue). Every field's status is the worse of the two SAT statuses
it derives from (INVALID before INIT before DEGRADED before VALID), so VS_Grip times out, degrades and recovers
exactly as SAT_FRONT: while INVALID or INIT its values are SNA, the warning 0 and the estimate's filters restart.
A held friction (and its half-width), read on earlier ticks, is also no better than the worst status of the
latest ``hold_count`` ticks that gave a friction (its median's): a friction read from DEGRADED SATs never turns
VALID by being held.
The friction is SNA whenever it is unknown (the tyres not excited enough, or the SATs outside the model's validity
envelope, an extrapolation: a friction held from before is still given), whatever its status.

A CAN matrix without ``VS_Grip`` (an older DBC) or a model whose inputs lack a signal the estimate needs gives
a :class:`NoGrip` stand-in (:func:`grip_output`): the daemon then publishes SAT_FRONT and VS_Health only.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from typing import Any

from virtsensor.canbus.codec import CanMatrix, compile_encoder
from virtsensor.canbus.dbcgen import GRIP_SIGNALS, GRIP_STATUS
from virtsensor.canbus.e2e import next_counter
from virtsensor.daemon.validity import DEGRADED, INIT, INVALID, VALID
from virtsensor.grip import GRIP_INPUTS, PRESSURE_INPUTS, GripEstimator, GripParams, reads_pressure

__all__ = ["GRIP_INPUTS", "GripOutput", "NoGrip", "grip_output", "worse_status"]

_RANK = {VALID: 0, DEGRADED: 1, INIT: 2, INVALID: 3}


def worse_status(a: float, b: float) -> int:
    """The worse of two status codes: INVALID, then INIT, then DEGRADED, then VALID."""
    return int(a) if _RANK[int(a)] >= _RANK[int(b)] else int(b)


class GripOutput:
    """The preallocated VS_Grip frame, its values, counter and the grip estimator.

    Args:
        matrix: the daemon's CAN matrix (with ``VS_Grip``).
        signals: the daemon's decoded signals (the order of the values :meth:`fill` gets; the front pressures
            are read where they are among them).
        wheels: the daemon's two published wheels (front left, front right; their ``estimate``/``status``
            SAT_FRONT signal names), read by :meth:`fill_tick`.
        params: the car's grip parameters (default: the catalogue car's, shipped with the package).
        sat_reads_pressure: the SAT model reads the front TPMS pressures (how the estimate reads a known pressure:
            :class:`~virtsensor.grip.GripEstimator`).
    """

    def __init__(self, matrix: CanMatrix, signals: Sequence[str], wheels: Sequence[Any] = (),
                 params: GripParams | None = None, sat_reads_pressure: bool = False) -> None:
        from virtsensor.daemon.publish import out_message

        m = matrix.messages["VS_Grip"]
        self._encode = compile_encoder(m)
        self.msg = out_message(m.frame_id, m.length)
        self._idx = tuple(list(signals).index(s) for s in GRIP_INPUTS)
        self._press = tuple(list(signals).index(s) for s in PRESSURE_INPUTS) if all(
            s in signals for s in PRESSURE_INPUTS) else ()
        self.estimator = GripEstimator(params, sat_reads_pressure=sat_reads_pressure)
        #: the statuses of the latest ticks that gave a friction (those the held median rests on)
        self._given: deque[int] = deque(maxlen=max(int(self.estimator.params.hold_count), 1))
        self._names = tuple(GRIP_SIGNALS)  # util, mu, half-width
        #: VS_Grip signal -> value (nan -> SNA), status codes
        self.values: dict[str, float] = {n: math.nan for n in self._names}
        self.values["VS_GripWarning"] = 0
        for s in GRIP_STATUS:
            self.values[s] = INIT
        self._ctr = 0
        self._sat = tuple((w.estimate, w.status) for w in wheels)

    #: this output publishes VS_Grip (the :class:`NoGrip` stand-in does not)
    enabled = True

    def fill_tick(self, sat_values: Any, inputs: Sequence[float], bad: Sequence[bool] = (),
                  outside: bool = False) -> Any:
        """:meth:`fill` from the tick's SAT_FRONT values (signal -> value), decoded values and their verdicts
        (``bad``: per decoded signal, stale, SNA, implausible or E2E-faulted this tick; empty: all usable) and
        whether the SATs' inputs are outside the model's envelope; returns the message."""
        (e_fl, s_fl), (e_fr, s_fr) = self._sat
        return self.fill(sat_values[e_fl], sat_values[e_fr], sat_values[s_fl], sat_values[s_fr], inputs, bad,
                         outside)

    def restart(self) -> None:
        """Restart the estimate's filters (after a gap between ticks); the friction held is kept."""
        self.estimator.reset()

    def send(self, send: Any) -> None:
        """Hand the latest filled frame to ``send`` (the bus link's)."""
        send(self.msg)

    @property
    def frame_id(self) -> int:
        return int(self.msg.arbitration_id)

    def fill(self, sat_fl: float, sat_fr: float, st_fl: float, st_fr: float, inputs: Sequence[float],
             bad: Sequence[bool] = (), outside: bool = False) -> Any:
        """One estimate step and the encoded frame (next alive counter); returns the message. The front pressures
        count only where both are decoded and neither is ``bad``. With the SATs ``outside`` the model's validity
        envelope (an extrapolation) no friction is read from them (:meth:`~virtsensor.grip.GripEstimator.step`)."""
        v = self.values
        status = mu_status = worse_status(st_fl, st_fr)
        util, mu, hw = self._names
        if status == INVALID or status == INIT:
            self.estimator.reset()
            v[util] = v[mu] = v[hw] = math.nan
            v["VS_GripWarning"] = 0
        else:
            pi = self._press
            if pi:
                a, b = pi
                ok = not bad or not (bad[a] or bad[b])
                self.estimator.set_front_pressure(0.5 * (inputs[a] + inputs[b]) if ok else math.nan)
            i = self._idx
            s = self.estimator.step(sat_fl, sat_fr, inputs[i[0]], inputs[i[1]], inputs[i[2]], inputs[i[3]],
                                    inputs[i[4]], inputs[i[5]], inputs[i[6]], inputs[i[7]], outside)
            v[util], v[mu], v[hw] = s.util, s.mu, s.halfwidth
            v["VS_GripWarning"] = 1 if s.warning else 0
            mu_status = self._friction_status(status, s.held, s.mu == s.mu)
        u_st, mu_st, hw_st, w_st = GRIP_STATUS
        v[u_st] = v[w_st] = status
        v[mu_st] = v[hw_st] = mu_status
        m = self.msg
        m.data[:] = self._encode(v, self._ctr)
        self._ctr = next_counter(self._ctr)
        return m

    def _friction_status(self, status: int, held: bool, given: bool) -> int:
        """The friction's status this tick: ``status``, or for a ``held`` friction the worse of it and the statuses
        of the ticks that gave the latest frictions (one ``given`` this tick joins them)."""
        if held:
            for g in self._given:
                status = worse_status(status, g)
        elif given:
            self._given.append(status)
        return status


class NoGrip:
    """The stand-in of a daemon that publishes no VS_Grip: :meth:`fill_tick` and :meth:`send` do nothing."""

    enabled = False

    def fill_tick(self, sat_values: Any, inputs: Sequence[float], bad: Sequence[bool] = (),
                  outside: bool = False) -> None:
        return None

    def restart(self) -> None:
        return None

    def send(self, send: Any) -> None:
        return None


def grip_output(matrix: CanMatrix, signals: Sequence[str], wheels: Sequence[Any],
                params: GripParams | None = None, model_signals: Sequence[str] | None = None) -> GripOutput | NoGrip:
    """A :class:`GripOutput` reading ``signals`` (the daemon's decoded signals), or a :class:`NoGrip` when the
    matrix lacks VS_Grip, the model's inputs (``model_signals``, default ``signals``) lack a signal the estimate
    needs (whose status the SATs' would not carry) or the model does not give both front SATs. The estimate reads
    a known pressure on the tyre's own curves only where ``model_signals`` is given and holds both front
    pressures (decoded signals may hold them for the grip alone: without the model's inputs, the ``PPZ1`` scale,
    which never over-corrects a pressure-blind model)."""
    model = signals if model_signals is None else model_signals
    if "VS_Grip" not in matrix.messages or any(s not in model for s in GRIP_INPUTS) or len(wheels) != 2:
        return NoGrip()
    reads = model_signals is not None and reads_pressure(model_signals)
    return GripOutput(matrix, signals, wheels, params, sat_reads_pressure=reads)
