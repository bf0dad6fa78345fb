"""Helpers shared by the runtime daemon's tests (tiny models, synthetic CAN streams, sync frames)."""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

import can
import numpy as np

from virtsensor import signals as cat
from virtsensor.daemon.layout import SYNC_ID, sync_frames
from virtsensor.features import HISTORY, FeatureSpec
from virtsensor.model import ModelCard
from virtsensor.model.envelope import Envelope
from virtsensor.model.export import export_pipeline, pipeline_weights


def card_inputs(spec: FeatureSpec) -> list[dict]:
    """The card's ``inputs`` entries, as ``virtsensor train`` writes them (:meth:`ModelCard.inputs_for`)."""
    return ModelCard.inputs_for(spec)


def train_model(tables: Sequence[Mapping[str, np.ndarray]], path: Path, spec: FeatureSpec = HISTORY,
                hidden: tuple[int, ...] = (8,), max_iter: int = 200, seed: int = 0, envelope: bool = False,
                extra: Mapping | None = None) -> dict:
    """Fit RobustScaler + a small MLP on 20 Hz tables (features by ``spec.transform``) and export it (with the
    validity envelope of its training rows in the card when ``envelope``, as ``virtsensor train`` does; ``extra``:
    more card fields, e.g. a ``fallback``)."""
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.neural_network import MLPRegressor
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import RobustScaler
    from threadpoolctl import threadpool_limits

    xs, ys = [], []
    for t in tables:
        x = spec.transform(t)
        y = np.column_stack([t[o] for o in cat.OUTPUTS])
        ok = np.isfinite(x).all(1) & np.isfinite(y).all(1)
        xs.append(x[ok])
        ys.append(y[ok])
    X, Y = np.concatenate(xs), np.concatenate(ys)
    mlp = MLPRegressor(hidden_layer_sizes=hidden, max_iter=max_iter, random_state=seed, learning_rate_init=3e-3)
    pipe = Pipeline([("scaler", RobustScaler()), ("mlp", mlp)])
    with warnings.catch_warnings(), threadpool_limits(1):
        warnings.simplefilter("ignore", ConvergenceWarning)
        pipe.fit(X, Y)
    return export_pipeline(pipe, X.shape[1], path, parity_X=X[:200], card_extra=ModelCard.trainer_fields(
        model="virtsensor-test", spec=spec, weights=pipeline_weights(pipe),
        envelope=Envelope.fit(X, spec.names) if envelope else None) | dict(extra or {}))


def synthetic_streams(duration_s: float, seed: int = 0, rate_hz: float = 100.0):
    """Smooth in-range input signals and SAT-like outputs on a ``rate_hz`` grid (no simulator needed); the
    front wheel speeds agree with the vehicle speed (``signals.REDUNDANCIES``)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    sig: dict[str, np.ndarray] = {}
    for name in cat.INPUTS:
        s = cat.SIGNALS[name]
        mid, half = (s.minimum + s.maximum) / 2, (s.maximum - s.minimum) / 2
        f1, f2 = rng.uniform(0.1, 0.6, 2)
        p1, p2 = rng.uniform(0, 2 * np.pi, 2)
        sig[name] = mid + 0.3 * half * (0.7 * np.sin(2 * np.pi * f1 * t + p1) + 0.3 * np.sin(2 * np.pi * f2 * t + p2))
    # the front wheels roll at the vehicle speed (the catalogue's redundancy check holds), within 1 %
    for w in ("fl", "fr"):
        sig[f"wheel_speed_{w}_radps"] = sig["vx_mps"] / cat.ROLLING_RADIUS_M * (1.0 + 0.01 * np.sin(0.7 * t + len(w)))
    steer = sig["steer_angle_rad"] / 4.0
    sig["sat_fl_nm"] = -60.0 * np.tanh(steer) + 2.0 * sig["ay_mps2"]
    sig["sat_fr_nm"] = -50.0 * np.tanh(steer) - 2.0 * sig["ay_mps2"]
    return t, sig


def with_sync(frames: Iterable[can.Message], t_first: float, t_last: float, sync_id: int = SYNC_ID,
              period: float = cat.TABLE_TICK_S) -> tuple[list[can.Message], np.ndarray]:
    """``frames`` with a sync frame (:func:`~virtsensor.daemon.layout.sync_frames`) after each grid instant
    ``t_first + k * period``.

    Returns the merged frames (time order) and the tick times.
    """
    frames = list(frames)
    n = int(np.floor((t_last - t_first) / period + 1e-9)) + 1
    ticks = t_first + np.arange(n) * period
    syncs = sync_frames(ticks, sync_id)
    merged = sorted(frames + syncs, key=lambda m: m.timestamp)  # stable; no ties by construction
    return merged, ticks


class LogEvents(logging.Handler):
    """Collects the daemon's log events (name and fields)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.events: list[dict] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.events.append({"event": record.getMessage(), **getattr(record, "fields", {})})


@contextmanager
def daemon_events() -> Iterator[LogEvents]:
    """The daemon's log events at INFO while the block runs (the logger's level restored after)."""
    handler, logger = LogEvents(), logging.getLogger("virtsensor.daemon")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


class CaptureBus(can.BusABC):
    """A bus that keeps what the daemon sends (a copy of each frame) and receives nothing: a daemon driven by hand."""

    def __init__(self) -> None:
        super().__init__(channel="capture")
        self.sent: list[can.Message] = []

    def send(self, msg, timeout=None) -> None:
        self.sent.append(can.Message(arbitration_id=msg.arbitration_id, data=bytes(msg.data), is_extended_id=False))

    def _recv_internal(self, timeout):
        return None, False
