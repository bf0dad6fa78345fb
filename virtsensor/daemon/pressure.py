"""The daemon's pressure status: when to publish the pressure-free fallback instead of the TPMS model.

A model whose card names a ``fallback`` (:mod:`virtsensor.model.fallback`: the TPMS model, whose last features
are the front tyres' pressures) reads the pressures as optional inputs. They are not critical (the catalogue's
and the card's flag): a pressure that is stale (no usable ``TPMS_Pressures`` frame within the timeout,
``timeout_cycles`` x its 1 s cycle: 3 s by default), out of order, E2E-broken or reported SNA ("sensor missing")
makes the input status DEGRADED, never INVALID by itself (:func:`~virtsensor.daemon.validity.assess_inputs`),
and on such a tick the daemon publishes the fallback's estimate from the same feature vector's first features.
When the frames return, the first usable one makes the pressures fresh again: the TPMS model and VALID are back.

Before the first TPMS frame the daemon does not wait for it: the estimate starts with the fallback as soon as the
other inputs are complete.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

__all__ = ["PressureFallback"]


class PressureFallback:
    """The fallback of a daemon's model (None from :meth:`for_model` when its card names none).

    Attributes:
        n: leading features the fallback reads. slots: indices (in the daemon's inputs) of the optional signals
            (the pressures). required: indices of the other inputs (the estimate waits for these only).
        predict_one: the fallback model's one-vector inference (its result is overwritten by the next call).
    """

    __slots__ = ("model", "n", "slots", "required", "predict_one")

    def __init__(self, model: Any, n: int, slots: Sequence[int], n_signals: int) -> None:
        self.model = model
        self.n = int(n)
        self.slots = tuple(slots)
        self.required = tuple(i for i in range(n_signals) if i not in self.slots)
        self.predict_one = model.predict_one

    @classmethod
    def for_model(cls, model: Any, signals: Sequence[str]) -> PressureFallback | None:
        """The fallback named by ``model``'s card, laid out on the daemon's input ``signals``; None when none.

        Raises:
            UserError: see :func:`virtsensor.model.fallback.load_fallback`; or an optional feature that is not
                a plain value of one of the inputs.
        """
        from virtsensor.errors import UserError
        from virtsensor.model.fallback import load_fallback

        fb = load_fallback(model)
        if fb is None:
            return None
        idx = {s: i for i, s in enumerate(signals)}
        if not all(name in idx for name in fb.optional):
            raise UserError(f"{getattr(model, 'card_path', 'model card')}: optional features {list(fb.optional)} "
                            f"are not plain inputs of the model")
        return cls(fb.model, fb.n, [idx[name] for name in fb.optional], len(signals))

    def active(self, bad: Sequence[bool]) -> bool:
        """Whether this tick must use the fallback: some pressure is bad (stale, SNA, E2E error, out of order)."""
        for i in self.slots:
            if bad[i]:
                return True
        return False

    def complete(self, times: Sequence[float]) -> bool:
        """Whether every required (non-optional) input has been received once."""
        for i in self.required:
            if times[i] == -math.inf:
                return False
        return True
