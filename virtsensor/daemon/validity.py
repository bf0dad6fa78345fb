"""The daemon's input-validity contract as pure functions: VALID / DEGRADED / INVALID / INIT.

No threads, no bus, no clock: every function here is a function of its arguments (plus the explicit
state objects it updates), so the contract is testable tick by tick (``tests/test_validity.py``).

Freshness. An input value is *fresh* at tick time ``t`` only when ``0 <= t - time <= timeout`` on the
daemon's clock (a value stamped after the tick is not fresh, whatever its age's magnitude), and only
while its message's frames arrive in order (:class:`FrameOrder`): a frame stamped more than one cycle of
its message ahead of the tick that follows it (*future-stamped*) or before the message's previous frame
(*time step back*) makes the message non-fresh until its frames have been in order again for
``timeout_cycles`` of its cycles.

Per signal, per tick (:func:`assess_inputs`): *stale* = not fresh, or SNA/implausible in the latest intact
frame; *bad* = stale, or *implausible* (:class:`Plausibility`: it disagrees with redundant signals), or still
*recovering* (the first ``h`` fresh ticks after a stale one, ``h`` the
history the signal's features read), or its message had an E2E error since the previous tick. The input
status is INVALID when a critical signal is bad, DEGRADED when only non-critical ones are, else VALID.
The health bitmap has a message's bit set when its last usable frame is fresh, in order, without E2E
error, and none of its signals is bad. Per wheel (:func:`wheel_status`): INVALID also when the estimate
is not finite or outside the catalogue range.

Envelope (:class:`EnvelopeRules`, :func:`outside_envelope`): the inputs are *outside the envelope* when a
bounded input lies outside the training range the model card states, or the grip used (``|ay|``,
``hypot(ax, ay)``) exceeds the ceiling of the speed band, or the speed band had no training rows
(:mod:`virtsensor.model.envelope`), or were at one of the ticks whose rows the features still read (their
rates, accelerations and lags: :class:`EnvelopeMemory`). Then a VALID wheel is DEGRADED (:func:`envelope_status`);
INVALID and INIT are kept.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["VALID", "DEGRADED", "INVALID", "INIT", "STATUS_NAMES", "ValidityRules", "ValidityState", "FrameOrder",
           "restart_recovery", "PlausibilityRule", "Plausibility", "judge", "assess_inputs", "wheel_status",
           "EnvelopeRules", "outside_envelope", "EnvelopeMemory", "envelope_status"]

#: Per-wheel status codes of ``SAT_FRONT.SAT_xx_Status`` (DBC value table).
VALID, DEGRADED, INVALID, INIT = 0, 1, 2, 3
STATUS_NAMES = {VALID: "VALID", DEGRADED: "DEGRADED", INVALID: "INVALID", INIT: "INIT"}

_INF = math.inf


@dataclass(frozen=True)
class ValidityRules:
    """Constants of :func:`assess_inputs` (index ``i``: decoded signal, ``j``: input message).

    The decoded signals are the model's inputs (``i < len(critical)``), then the check references (read by the
    plausibility checks alone, :class:`~virtsensor.daemon.layout.InputLayout`).

    Attributes:
        sig_msg: message ``j`` of each decoded signal. sig_timeout: each decoded signal's timeout (s).
        sig_hist: ticks of history each model input's features read (recovery length).
        critical: each model input's criticality. sig_bit: each decoded signal's message's health bit mask (0:
            none). msg_timeout: each message's timeout (s). bitmap_msgs: ``(j, bit mask)`` of the health bitmap.
    """

    sig_msg: tuple[int, ...]
    sig_timeout: tuple[float, ...]
    sig_hist: tuple[int, ...]
    critical: tuple[bool, ...]
    sig_bit: tuple[int, ...]
    msg_timeout: tuple[float, ...]
    bitmap_msgs: tuple[tuple[int, int], ...]


class ValidityState:
    """What :func:`assess_inputs` carries from tick to tick (``recover``) and reports (``stale``, ``bad``).

    Attributes:
        recover: per model input, fresh ticks still needed before it counts as good again.
        stale, bad: per decoded signal, the verdicts of the latest tick.
    """

    __slots__ = ("recover", "stale", "bad", "never")

    def __init__(self, n_signals: int) -> None:
        self.recover = [0] * n_signals  # (the check references' items stay 0: they have no recovery)
        self.stale = [False] * n_signals
        self.bad = [False] * n_signals
        self.never = (False,) * n_signals  # (no signal implausible)


def assess_inputs(t: float, sig_time: Sequence[float], sig_flag: Sequence[bool], msg_last_ok: Sequence[float],
                  msg_err: Sequence[bool], msg_in_order: Sequence[bool], rules: ValidityRules,
                  state: ValidityState, implausible: Sequence[bool] | None = None) -> tuple[int, int]:
    """The input status and health bitmap at tick time ``t`` (s, the daemon's clock).

    The model's inputs make the status; a check reference (a decoded signal after them) is only judged stale or
    bad, which leaves the checks that read it unjudged and clears its ``sig_bit`` (0 for a reference in a message
    that carries model inputs: :meth:`~virtsensor.daemon.layout.InputLayout.rules`).

    Args:
        sig_time: per decoded signal, the time of its latest usable value (-inf: never).
        sig_flag: per decoded signal, SNA or implausible in its message's latest intact frame.
        msg_last_ok: per message, the time of its latest usable frame. msg_err: E2E error since the last tick.
        msg_in_order: per message, its frames are in order (:attr:`FrameOrder.in_order`).
        state: updated in place (recovery counters; stale/bad verdicts of this tick).
        implausible: per signal, a plausibility check against redundant signals fails (:attr:`Plausibility.
            implausible`; None: none does). An implausible signal is bad, not stale (no recovery period).

    Returns:
        ``(status, bitmap)``: VALID, DEGRADED or INVALID, and the ``VS_InputStatus`` bits.
    """
    stale, bad, rec = state.stale, state.bad, state.recover
    hist, sig_to, sig_msg, crit = rules.sig_hist, rules.sig_timeout, rules.sig_msg, rules.critical
    any_bad = crit_bad = False
    imp = implausible if implausible is not None else state.never
    n = len(crit)
    for i in range(n):
        j = sig_msg[i]
        # fresh: 0 <= age <= timeout (a NaN or negative age is not), in order, neither SNA nor implausible
        st = not (0.0 <= t - sig_time[i] <= sig_to[i]) or sig_flag[i] or not msg_in_order[j]
        r = rec[i]
        b = r > 0 or st or msg_err[j] or imp[i]
        stale[i] = st
        bad[i] = b
        rec[i] = hist[i] if st else (r - 1 if r > 0 else 0)
        if b:
            any_bad = True
            if crit[i]:
                crit_bad = True
    status = INVALID if crit_bad else DEGRADED if any_bad else VALID
    for i in range(n, len(sig_msg)):  # the check references: stale or bad, never the status
        j = sig_msg[i]
        st = not (0.0 <= t - sig_time[i] <= sig_to[i]) or sig_flag[i] or not msg_in_order[j]
        b = st or msg_err[j]
        stale[i] = st
        bad[i] = b
        if b:
            any_bad = True
    bitmap = 0
    msg_to = rules.msg_timeout
    for j, bit in rules.bitmap_msgs:
        if 0.0 <= t - msg_last_ok[j] <= msg_to[j] and not msg_err[j] and msg_in_order[j]:
            bitmap |= bit
    if any_bad:
        for i, bit in enumerate(rules.sig_bit):
            if bad[i]:
                bitmap &= ~bit
    return status, bitmap


def restart_recovery(rules: ValidityRules, state: ValidityState) -> None:
    """After a gap between ticks: every model input whose features read a history (``rules.sig_hist``) needs that
    many ticks again before it counts as good, as after a stale tick, so that no feature reads a row from before
    the gap as one tick old (the tick that follows is the first of them)."""
    rec, hist = state.recover, rules.sig_hist
    for i in range(len(rules.critical)):
        if hist[i] > rec[i]:
            rec[i] = hist[i]


def wheel_status(input_status: int, estimate: float, lo: float, hi: float) -> int:
    """A wheel's status from the input status and its estimate: INVALID when the inputs are INVALID or the
    estimate is not within ``[lo, hi]`` (NaN included), else the input status."""
    if input_status == INVALID or not (lo <= estimate <= hi):
        return INVALID
    return input_status


class FrameOrder:
    """Per input message: are its frames in order on the daemon's clock?

    :meth:`frame` records each frame's time (from the receive path) and reports a *time step back* (a frame
    before the message's previous one); :meth:`tick` finds *future-stamped* latest frames (more than one
    cycle of the message after the tick time) and sets :attr:`in_order`. After either, the message is out of
    order until its frames have run in order for ``timeout_cycles`` cycles (measured from the offending
    frame, on the frames' own times); a message without frames since then stays out of order.

    Attributes:
        last_t: per message, the time of its latest frame (-inf: none yet).
        in_order: per message, the verdict of the latest :meth:`tick` (True before any disorder).
    """

    __slots__ = ("last_t", "in_order", "_run_start", "_counted", "_ahead", "_window", "_min_ahead", "_dirty")

    def __init__(self, cycles_s: Sequence[float], timeout_cycles: float) -> None:
        n = len(cycles_s)
        self.last_t: list[float] = [-_INF] * n
        self.in_order: list[bool] = [True] * n
        self._run_start: list[float] = [-_INF] * n  # first frame of the current in-order run (-inf: always)
        self._counted: list[float] = [math.nan] * n  # the future-stamped frame time already counted
        self._ahead = tuple(float(c) for c in cycles_s)
        # (less 1 us: frames exactly timeout_cycles cycles apart count as far enough, whatever the rounding)
        self._window = tuple(float(timeout_cycles) * c - 1e-6 for c in cycles_s)
        self._min_ahead = min(self._ahead, default=0.0)
        self._dirty = False  # some message out of order, or a step back since the last tick

    def frame(self, j: int, t: float) -> bool:
        """Record a frame of message ``j`` at time ``t``; True when it steps back (then a new run starts)."""
        if t < self.last_t[j]:
            self._dirty = True
            self._run_start[j] = t
            self.last_t[j] = t
            return True
        self.last_t[j] = t
        return False

    def tick(self, t: float) -> int:
        """Update :attr:`in_order` at tick time ``t``; returns how many frames were newly found future-stamped."""
        if not self._dirty and max(self.last_t, default=-_INF) <= t + self._min_ahead:
            return 0  # nothing out of order, no frame ahead: in_order is all True already
        out = self.in_order
        last, run, counted, ahead, window = self.last_t, self._run_start, self._counted, self._ahead, self._window
        n = 0
        for j in range(len(last)):
            lt = last[j]
            if lt > t + ahead[j]:
                if lt != counted[j]:
                    counted[j] = lt
                    n += 1
                run[j] = lt  # in order again only once frames have run timeout_cycles past this one
                out[j] = False
            else:
                rs = run[j]
                out[j] = rs == -_INF or lt - rs >= window[j]
        self._dirty = not all(out)
        return n


@dataclass(frozen=True)
class PlausibilityRule:
    """One check between redundant input signals (indices into the daemon's decoded signals: the model's inputs,
    then the checks' own references), from a catalogue :class:`~virtsensor.signals.Redundancy`: a judged tick
    passes when ``|x - expected| <= tol_abs + tol_rel * |x| + sum(c * |v[i]| for i, c in tol_per)``, ``x =
    v[subject]``, or ``v[subject] - v[minus]`` when ``minus >= 0`` (a failed check then marks both implausible).

    ``expected`` by ``relation``: ``"mean"``, ``scale * mean(v[refs])``; ``"product"``, ``scale * prod(v[refs])``;
    ``"ratio"``, ``scale * v[refs[0]] / v[refs[1]]`` (the rule's ``above`` keeps the divisor positive);
    ``"difference"``, ``scale * (v[refs[0]] - v[refs[1]])``; ``"boost"``, ``boost = (speeds, gains, knee, max)``
    of ``refs = (torque, speed)`` (see :class:`~virtsensor.signals.BoostCurve`). A tick is judged only when no
    signal it reads is stale (compared, gating or scaling the tolerance), every ``(i, max_step)`` of ``steady``
    moved by at most ``max_step`` since the previous tick, every ``(i, bound)`` of ``within`` has ``|v[i]| <=
    bound``, every ``(i, bound)`` of ``above`` has ``v[i] >= bound``, ``min_expected <= |expected| <=
    max_expected`` (a NaN prediction is judged and passes) and, with ``turn = (yaw, vx, steer, k, min_yaw, lo,
    hi)``, ``|r_kin| >= min_yaw`` and ``lo*|r_kin| <= |v[yaw]| <= hi*|r_kin|``, ``r_kin = k * v[vx] * v[steer]``
    (the same sign).

    Debounce. With ``window == 0``, the check fails after ``debounce`` consecutive failing judged ticks and
    passes after as many passing ones; an unjudged tick holds the verdict and restarts the count. With
    ``window > 0``, it fails once ``debounce`` of the last ``window`` judged ticks failed and passes once
    ``debounce`` of them passed; an unjudged tick holds the verdict and the window (it neither counts nor
    restarts), so a check judged on scattered ticks of transient driving still reaches its verdict."""

    name: str
    subject: int
    refs: tuple[int, ...]
    scale: float
    tol_abs: float
    tol_rel: float
    debounce: int
    relation: str = "mean"
    steady: tuple[tuple[int, float], ...] = ()
    within: tuple[tuple[int, float], ...] = ()
    turn: tuple[int, int, int, float, float, float, float] | None = None
    boost: tuple[tuple[float, ...], tuple[float, ...], float, float] | None = None
    above: tuple[tuple[int, float], ...] = ()
    max_expected: float = math.inf
    min_expected: float = 0.0
    window: int = 0
    minus: int = -1
    tol_per: tuple[tuple[int, float], ...] = ()

    def __post_init__(self) -> None:
        if self.debounce < 1 or self.window < 0 or (self.window and self.debounce > self.window):
            raise ValueError(f"{self.name}: debounce {self.debounce} with window {self.window}")


def _boost(curve: tuple[tuple[float, ...], tuple[float, ...], float, float], t: float, v: float) -> float:
    speeds, gains, knee, top = curve
    if v <= speeds[0]:
        g = gains[0]
    elif v >= speeds[-1]:
        g = gains[-1]
    else:
        k = 1
        while speeds[k] < v:
            k += 1
        g = gains[k - 1] + (gains[k] - gains[k - 1]) * (v - speeds[k - 1]) / (speeds[k] - speeds[k - 1])
    a = abs(t)
    y = g * t * a / (a + knee)
    return top if y > top else -top if y < -top else y


def _reads(r: PlausibilityRule) -> tuple[int, ...]:
    """Every signal check ``r`` reads (compared, gating, or scaling its tolerance), once: a check is not judged
    while one of them is stale (a held steering angle looks like a wheel at rest)."""
    turn = r.turn[:3] if r.turn is not None else ()
    return tuple(dict.fromkeys((r.subject, *((r.minus,) if r.minus >= 0 else ()), *r.refs,
                                *(i for i, _ in (*r.steady, *r.within, *r.above, *r.tol_per)), *turn)))


def judge(r: PlausibilityRule, values: Sequence[float], prev: Sequence[float],
          stale: Sequence[bool]) -> tuple[bool, float, float]:
    """One tick of check ``r`` as its docstring states it, interpreted: ``(judged, residual, tolerance)``, the
    residual ``|v[subject] - expected|`` (nan when not judged, or a NaN among the values) and the tolerance at
    ``v[subject]``; the tick fails when judged and ``residual > tolerance``. For tools and tests: the daemon runs
    the same semantics compiled (:func:`compile_checks`), which the tests hold equal to this."""
    judged = not any(stale[i] for i in _reads(r))
    judged = judged and all(abs(values[i] - prev[i]) <= step for i, step in r.steady)
    judged = judged and all(abs(values[i]) <= bound for i, bound in r.within)
    judged = judged and all(values[i] >= bound for i, bound in r.above)
    if judged and r.turn is not None:
        yaw, vx, steer, kk, min_yaw, lo, hi = r.turn
        rk = kk * values[vx] * values[steer]
        judged = abs(rk) >= min_yaw and values[yaw] * rk > 0 and lo * abs(rk) <= abs(values[yaw]) <= hi * abs(rk)
    if not judged:
        return False, math.nan, math.nan
    a = values[r.refs[0]]
    if r.relation == "product":
        e = r.scale * math.prod(values[i] for i in r.refs)
    elif r.relation == "boost" and r.boost is not None:
        e = _boost(r.boost, a, values[r.refs[1]])
    elif r.relation == "ratio":
        e = r.scale * a / values[r.refs[1]]
    elif r.relation == "difference":
        e = r.scale * (a - values[r.refs[1]])
    else:
        e = r.scale * sum(values[i] for i in r.refs) / len(r.refs)
    if abs(e) < r.min_expected or abs(e) > r.max_expected:
        return False, math.nan, math.nan
    v = values[r.subject] - (values[r.minus] if r.minus >= 0 else 0.0)
    return True, abs(v - e), r.tol_abs + r.tol_rel * abs(v) + sum(c * abs(values[i]) for i, c in r.tol_per)


def _lit(x: float, env: dict[str, Any]) -> str:
    """A float as source text (exact: ``repr`` round-trips), or the name of an ``env`` entry when not finite."""
    x = float(x)
    if math.isfinite(x):
        return repr(x)
    name = f"_C{len(env)}"
    env[name] = x
    return name


def _expected_source(k: int, r: PlausibilityRule, env: dict[str, Any]) -> str:
    """Source of check ``k``'s prediction from ``values`` (see :class:`PlausibilityRule`)."""
    v = "values"
    if r.relation == "product":
        return " * ".join([_lit(r.scale, env), *(f"{v}[{i}]" for i in r.refs)])
    if r.relation == "ratio":
        return f"{_lit(r.scale, env)} * {v}[{r.refs[0]}] / {v}[{r.refs[1]}]"
    if r.relation == "difference":
        return f"{_lit(r.scale, env)} * ({v}[{r.refs[0]}] - {v}[{r.refs[1]}])"
    if r.relation == "boost" and r.boost is not None:
        env[f"_B{k}"] = r.boost
        return f"_boost(_B{k}, {v}[{r.refs[0]}], {v}[{r.refs[1]}])"
    if r.relation != "mean":
        raise ValueError(f"{r.name}: unknown relation {r.relation!r}")
    return f"{_lit(r.scale, env)} * ({' + '.join(f'{v}[{i}]' for i in r.refs)}) / {len(r.refs)}"


def _skip_source(k: int, r: PlausibilityRule, env: dict[str, Any]) -> tuple[list[str], str]:
    """The conditions that leave check ``k`` unjudged (any true: not judged), and the name its prediction has
    in the judged branch (``e``, computed once by the bounds on it) or its source when no bound needs it."""
    v = "values"
    skip = [f"stale[{i}]" for i in _reads(r)]
    skip += [f"not abs({v}[{i}] - prev[{i}]) <= {_lit(step, env)}" for i, step in r.steady]
    skip += [f"not abs({v}[{i}]) <= {_lit(bound, env)}" for i, bound in r.within]
    skip += [f"not {v}[{i}] >= {_lit(bound, env)}" for i, bound in r.above]
    if r.turn is not None:
        yaw, vx, steer, kk, min_yaw, lo, hi = r.turn
        skip.append(f"not (abs(rk := {_lit(kk, env)} * {v}[{vx}] * {v}[{steer}]) >= {_lit(min_yaw, env)} "
                    f"and {v}[{yaw}] * rk > 0.0 and {_lit(lo, env)} * abs(rk) <= abs({v}[{yaw}]) "
                    f"<= {_lit(hi, env)} * abs(rk))")
    expected = _expected_source(k, r, env)
    # (a NaN prediction is judged, and passes, as without the bounds)
    if r.min_expected > 0.0 and math.isfinite(r.max_expected):
        skip.append(f"abs(e := {expected}) < {_lit(r.min_expected, env)} or abs(e) > {_lit(r.max_expected, env)}")
    elif r.min_expected > 0.0:
        skip.append(f"abs(e := {expected}) < {_lit(r.min_expected, env)}")
    elif math.isfinite(r.max_expected):
        skip.append(f"abs(e := {expected}) > {_lit(r.max_expected, env)}")
    else:
        return skip, expected
    return skip, "e"


def _rule_source(k: int, r: PlausibilityRule, env: dict[str, Any]) -> list[str]:
    """Straight-line source of check ``k`` inside the generated ``update`` (see :func:`compile_checks`)."""
    skip, expected = _skip_source(k, r, env)
    minus = f" - values[{r.minus}]" if r.minus >= 0 else ""
    per = "".join(f" + {_lit(c, env)} * abs(values[{i}])" for i, c in r.tol_per)
    judge = [f"        v = values[{r.subject}]{minus}",
             f"        ok = not (abs(v - {expected}) > {_lit(r.tol_abs, env)} + {_lit(r.tol_rel, env)} * abs(v){per})"]
    if r.window:  # the failures among the last `window` judged ticks (a ring of 0/1 and its sum)
        return [f"    new[{k}] = False",
                f"    if not ({' or '.join(skip)}):",
                *judge,
                f"        w = ring[{k}]",
                f"        p = pos[{k}]",
                "        b = 0 if ok else 1",
                f"        n = run[{k}] + b - w[p]",
                "        w[p] = b",
                f"        pos[{k}] = p + 1 if p < {int(r.window) - 1} else 0",
                f"        run[{k}] = n",
                f"        if failing[{k}]:",
                f"            if n <= {int(r.window) - int(r.debounce)}:",
                f"                failing[{k}] = False",
                f"        elif n >= {int(r.debounce)}:",
                f"            failing[{k}] = True",
                f"            new[{k}] = True",
                "            n_new += 1"]
    return [f"    new[{k}] = False",
            f"    if {' or '.join(skip)}:",
            f"        run[{k}] = 0",
            "    else:",
            *judge,
            f"        if ok == failing[{k}]:",
            f"            n = run[{k}] + 1",
            f"            if n >= {int(r.debounce)}:",
            f"                failing[{k}] = not ok",
            f"                new[{k}] = not ok",
            "                n_new += not ok",
            "                n = 0",
            f"            run[{k}] = n",
            "        else:",
            f"            run[{k}] = 0"]


def compile_checks(rules: Sequence[PlausibilityRule]) -> Any:
    """The checks as one generated function ``update(values, stale, prev, failing, run, ring, pos, new,
    implausible) -> newly failed``: every rule's judging conditions, expected value and debounce unrolled with its
    constants inlined (the semantics of :class:`PlausibilityRule`, without a per-rule interpretation each tick).
    Per rule ``k``: ``run[k]``, the consecutive judged ticks against its verdict (``window == 0``) or the failures
    in its window; ``ring[k]``, its window's last judged ticks (1: failed), ``pos[k]`` the slot of the next one.
    ``prev`` is then overwritten with ``values``, and each rule subject's ``implausible`` item is whether one of
    its checks fails."""
    env: dict[str, Any] = {"_boost": _boost}
    lines = ["def update(values, stale, prev, failing, run, ring, pos, new, implausible):", "    n_new = 0"]
    for k, r in enumerate(rules):
        lines += _rule_source(k, r, env)
    lines.append("    prev[:] = values")
    subjects: dict[int, list[int]] = {}
    for k, r in enumerate(rules):
        for i in (r.subject, r.minus) if r.minus >= 0 else (r.subject,):
            subjects.setdefault(i, []).append(k)
    for i, ks in subjects.items():
        lines.append(f"    implausible[{i}] = {' or '.join(f'failing[{k}]' for k in ks)}")
    lines.append("    return n_new")
    exec(compile("\n".join(lines), "<virtsensor.daemon.validity checks>", "exec"), env)  # noqa: S102 - from rules
    return env["update"]


class Plausibility:
    """Debounced plausibility checks, fed the latest input values once per tick (:meth:`update`).

    A failing check marks its *subject* implausible (:attr:`implausible`); a NaN among the compared values (an
    input never received) passes, and a check that reads a stale input is not judged: staleness is judged
    elsewhere.

    Attributes:
        rules: the checks. failing: per check, its debounced verdict. implausible: per input signal.
        new: per check, it failed at the latest :meth:`update`.
    """

    __slots__ = ("rules", "failing", "implausible", "new", "_run", "_ring", "_pos", "_prev", "_never", "_update")

    def __init__(self, rules: Sequence[PlausibilityRule], n_signals: int) -> None:
        self.rules = tuple(rules)
        self.failing = [False] * len(self.rules)
        self.implausible = [False] * n_signals
        self.new = [False] * len(self.rules)
        # per check: consecutive judged ticks against its verdict, or (windowed) the failures in its window
        self._run = [0] * len(self.rules)
        self._ring = [[0] * r.window for r in self.rules]  # windowed checks: their last judged ticks (1: failed)
        self._pos = [0] * len(self.rules)
        self._prev = [math.nan] * n_signals  # the values of the previous update (steadiness)
        self._never = [False] * n_signals
        self._update = compile_checks(self.rules)

    @property
    def counts(self) -> Sequence[int]:
        """Per check, its debounce count: consecutive judged ticks against its verdict, or (windowed) the failures
        among its last ``window`` judged ticks (read-only; for tools and tests)."""
        return tuple(self._run)

    def update(self, values: Sequence[float], stale: Sequence[bool] | None = None) -> int:
        """Run every check on ``values`` (per decoded signal, as the rules' indices); returns how many checks
        newly failed. A check that compares a ``stale`` signal (a held value, not news) is not judged at this
        tick. Allocates nothing but float temporaries."""
        return self._update(values, self._never if stale is None else stale, self._prev, self.failing, self._run,
                            self._ring, self._pos, self.new, self.implausible)


@dataclass(frozen=True)
class EnvelopeRules:
    """The model card's envelope laid out on the daemon's input signals (index ``i`` as in :class:`ValidityRules`).

    Attributes:
        lo, hi: per input signal, its range (-inf/inf: not bounded). i_vx, i_ay, i_ax: the speed and
            acceleration inputs (-1: none). band_start, band_width: the speed bands (m/s). ay_max, acc_max: per
            band, the ceilings of ``|ay|`` and ``hypot(ax, ay)`` (m/s^2; nan: outside; empty: no bands).
    """

    lo: tuple[float, ...]
    hi: tuple[float, ...]
    i_vx: int = -1
    i_ay: int = -1
    i_ax: int = -1
    band_start: float = 0.0
    band_width: float = 1.0
    ay_max: tuple[float, ...] = ()
    acc_max: tuple[float, ...] = ()

    @classmethod
    def from_envelope(cls, env: Any, signals: Sequence[str]) -> EnvelopeRules:
        """Lay ``env`` (a :class:`virtsensor.model.envelope.Envelope`) out on ``signals`` (the daemon's inputs);
        a bounded signal the daemon does not read is ignored."""
        lo, hi = [-_INF] * len(signals), [_INF] * len(signals)
        idx = {s: i for i, s in enumerate(signals)}
        for s, a, b in zip(env.signals, env.lo, env.hi, strict=True):
            if s in idx:
                lo[idx[s]], hi[idx[s]] = float(a), float(b)
        if not (env.has_bands and "vx_mps" in idx and "ay_mps2" in idx):
            return cls(tuple(lo), tuple(hi))
        return cls(tuple(lo), tuple(hi), idx["vx_mps"], idx["ay_mps2"], idx.get("ax_mps2", -1),
                   float(env.band_start), float(env.band_width), tuple(float(v) for v in env.ay_max),
                   tuple(float(v) for v in env.acc_max))


def outside_envelope(values: Sequence[float], rules: EnvelopeRules) -> bool:
    """Whether the input ``values`` (per model input, finite; best a list of floats; items after the model's
    inputs, such as the daemon's check references, are not read) lie outside the envelope ``rules``. Allocates
    nothing but float temporaries."""
    lo, hi = rules.lo, rules.hi
    for i in range(len(lo)):
        if not lo[i] <= values[i] <= hi[i]:
            return True
    caps = rules.ay_max
    if not caps:
        return False
    k = math.floor((values[rules.i_vx] - rules.band_start) / rules.band_width)
    if not 0 <= k < len(caps):
        return True
    ay = values[rules.i_ay]
    if not abs(ay) <= caps[k]:  # (a nan ceiling: outside)
        return True
    if rules.i_ax < 0:
        return False
    acc_cap = rules.acc_max[k]
    return not (acc_cap != acc_cap or math.hypot(values[rules.i_ax], ay) <= acc_cap)


class EnvelopeMemory:
    """Whether the features read a row outside the envelope: the latest tick's inputs (:func:`outside_envelope`),
    or those of one of the ``history`` ticks before it, which the features' rates, accelerations and lags still
    read once the inputs are back inside (a kerb strike's deflection, back in range after a tick, still makes
    a deflection rate far beyond any training row at the tick after it).

    Attributes:
        history: the most ticks of history a feature reads (:attr:`ValidityRules.sig_hist`).
    """

    __slots__ = ("history", "_left")

    def __init__(self, history: int) -> None:
        self.history = max(int(history), 0)
        self._left = 0  # ticks the features still read a row from outside

    def update(self, outside: bool) -> bool:
        """This tick's verdict from whether its inputs are ``outside``: True while they are, and for ``history``
        ticks after."""
        if outside:
            self._left = self.history
            return True
        if self._left > 0:
            self._left -= 1
            return True
        return False


def envelope_status(status: int, outside: bool) -> int:
    """A wheel's status once the envelope is judged: VALID becomes DEGRADED when ``outside``; others are kept."""
    return DEGRADED if outside and status == VALID else status
