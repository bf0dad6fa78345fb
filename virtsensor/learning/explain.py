"""Section IV.B of the paper: what the estimator looks at, and how it does on the track.

Figures (PNG, matplotlib's Agg canvas: no display, no pyplot state):

* ``fig2_correlation.png``: Pearson correlation of the 12 inputs and the 2 SATs
  over every finite row of the recordings (the paper's Fig. 2);
* ``fig8_shap_importance.png``: global SHAP importance, mean |SHAP| (Nm) per
  feature, front-left and front-right SAT (the paper's Fig. 8);
* ``fig9_shap_dependence.png``: SHAP value against feature value for the three
  most important features of the front-left SAT (the paper's Fig. 9);
* ``fig5_track_dry.png``, ``fig6_track_wet.png``: estimated (red) and true
  (blue) front SATs on the dry and wet Magny-Cours laps (Figs. 5 and 6);
* ``fig7_axle_total.png``: the axle total FL + FR on the wet lap (Fig. 7);
* ``circuit_<name>.png``: estimated and true front SATs on each recording given as a circuit the model
  never saw (``circuits``).

On the lap and circuit figures, the stretches where the inputs lie outside the validity envelope of the
model card (:mod:`virtsensor.model.envelope`) are shaded grey: there the model extrapolates, and
``explain.json`` gives the error inside and outside the envelope.

What is explained
-----------------
The shipped ONNX graph itself, through :meth:`virtsensor.model.onnx.OnnxModel.predict`,
on rows of the test side of the paper's random 70/30 split
(:func:`virtsensor.learning.evaluation.random_split`), against a background of
:data:`BACKGROUND_ROWS` rows drawn from the training side. Both draws and the
explainer's permutations derive from one seed: the same seed gives the same numbers.

The SHAP values are *interventional* Shapley values: a feature left out of a
coalition takes its values from the background rows (``shap.maskers.Independent``),
and the game's value is the model's mean output over them. Values are in Nm and
add up, row by row, to the prediction minus the mean background prediction.

Explainer (``method``)
----------------------
* ``exact``: ``shap.explainers.Exact``, the model on all ``2**d`` coalitions of
  the ``d`` features over the ``B`` background rows: ``n * 2**d * B`` model rows
  for ``n`` explained rows.
* ``permutation``: ``shap.explainers.Permutation`` with antithetic permutations
  (each ordering walked forward and backward, ``2d + 1`` coalitions): exact for
  models whose interactions are at most of second order, otherwise unbiased with
  an error shrinking as 1/sqrt(permutations). As many permutations as
  :data:`PERMUTATION_BUDGET_ROWS` allows, at least :data:`MIN_PERMUTATIONS`.
* ``auto``: ``exact`` when ``n * 2**d * B <= EXACT_BUDGET_ROWS``, else
  ``permutation``.

``explain.json`` records the method, the permutation count and the standard
error of each mean |SHAP|. Cost and accuracy of each method on the shipped
models: README, "Measured figures".
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from virtsensor import plotting
from virtsensor import signals as cat
from virtsensor.demogrip import grip_figure
from virtsensor.errors import UserError
from virtsensor.fileio import staged_dir, write_json

#: Background rows of the independent masker (drawn with the seed from the training side).
BACKGROUND_ROWS = 100
#: Largest model-row count (n * 2**d * B) for which ``method="auto"`` computes exact Shapley values.
EXACT_BUDGET_ROWS = 2.5e8
#: Model rows the permutation explainer may spend (n * permutations * (2d + 1) * B) under ``auto``.
PERMUTATION_BUDGET_ROWS = 1.0e8
#: Fewest / most antithetic permutations the permutation explainer runs.
MIN_PERMUTATIONS = 10
MAX_PERMUTATIONS = 200
#: Rows per ONNX call: large enough to amortise the call, small enough to stay in cache.
PREDICT_CHUNK_ROWS = 16384

FIGURES = {
    "correlation": "fig2_correlation.png",
    "importance": "fig8_shap_importance.png",
    "dependence": "fig9_shap_dependence.png",
    "track_dry": "fig5_track_dry.png",
    "track_wet": "fig6_track_wet.png",
    "axle": "fig7_axle_total.png",
}
WHEEL_LABEL = {"sat_fl_nm": "front-left SAT", "sat_fr_nm": "front-right SAT"}
TRUE_COLOUR, ESTIMATE_COLOUR = "tab:blue", "tab:red"

SHAP_MISSING = "the SHAP figures need the shap library: install the 'explain' extra: pip install 'virtsensor[explain]'"


def require_shap() -> Any:
    """Import and return ``shap``, or raise a one-line :class:`UserError` naming the extra to install."""
    try:
        import shap
    except ImportError:
        raise UserError(SHAP_MISSING) from None
    return shap


# ---------------------------------------------------------------------------------------------------------------
# numbers
# ---------------------------------------------------------------------------------------------------------------
def correlation_matrix(columns: np.ndarray) -> np.ndarray:
    """Pearson correlation (d, d) of the columns of ``columns`` (n, d); NaN where a column is constant."""
    A = np.asarray(columns, dtype=np.float64)
    A = A - A.mean(axis=0)
    norm = np.sqrt((A * A).sum(axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        C = (A.T @ A) / np.outer(norm, norm)
    C[:, norm == 0] = np.nan
    C[norm == 0, :] = np.nan
    return np.clip(C, -1.0, 1.0)


def table_columns(tables: Sequence[Mapping[str, np.ndarray]], names: Sequence[str]) -> np.ndarray:
    """The rows (n, len(names)) of every table where all ``names`` are finite, tables concatenated."""
    blocks = []
    for t in tables:
        M = np.column_stack([np.asarray(t[n], dtype=np.float64) for n in names])
        blocks.append(M[np.isfinite(M).all(axis=1)])
    return np.concatenate(blocks) if blocks else np.zeros((0, len(names)))


def choose_method(n_rows: int, n_features: int, n_background: int, method: str = "auto") -> tuple[str, int | None]:
    """The explainer (``exact`` or ``permutation``) and, for the latter, its antithetic permutation count.

    ``auto`` picks ``exact`` when ``n_rows * 2**n_features * n_background <= EXACT_BUDGET_ROWS``;
    otherwise ``permutation`` with as many permutations as :data:`PERMUTATION_BUDGET_ROWS` pays for,
    within [:data:`MIN_PERMUTATIONS`, :data:`MAX_PERMUTATIONS`]. ``permutation`` forced uses the same count.
    """
    if method not in ("auto", "exact", "permutation"):
        raise ValueError(f"unknown SHAP method {method!r} (auto, exact or permutation)")
    exact_rows = n_rows * 2.0**n_features * n_background
    if method == "exact" or (method == "auto" and exact_rows <= EXACT_BUDGET_ROWS):
        return "exact", None
    per_perm = max(1, n_rows * (2 * n_features + 1) * n_background)
    k = int(PERMUTATION_BUDGET_ROWS // per_perm)
    return "permutation", min(MAX_PERMUTATIONS, max(MIN_PERMUTATIONS, k))


@dataclass
class ShapResult:
    """SHAP values of a multi-output model on explained rows.

    Attributes:
        values: (n, d, k) SHAP values, in the outputs' unit (Nm).
        base_values: (k,) mean model output over the background (Nm).
        data: (n, d) the explained rows.
        feature_names, output_names: column names of ``data`` and of the outputs.
        method: ``exact`` or ``permutation``; permutations: antithetic permutation count (permutation only).
        error_std: (n, d, k) spread of the per-direction estimates (permutation only), else None.
        background_rows: rows of the independent masker.
        model_rows: model rows evaluated; seconds: wall time of the explainer.
    """

    values: np.ndarray
    base_values: np.ndarray
    data: np.ndarray
    feature_names: tuple[str, ...]
    output_names: tuple[str, ...]
    method: str
    permutations: int | None
    error_std: np.ndarray | None
    background_rows: int
    model_rows: int
    seconds: float

    def mean_abs(self) -> np.ndarray:
        """Global importance: mean |SHAP| per feature and output, (d, k), Nm."""
        return np.abs(self.values).mean(axis=0)

    def mean_abs_stderr(self) -> np.ndarray | None:
        """Approximate standard error (d, k) of :meth:`mean_abs` from the permutation sampling (None when exact).

        Each row's value is a mean of ``2 * permutations`` directional estimates with spread
        ``error_std`` (shap's); taking them as independent, and the rows' errors as independent,
        the mean over ``n`` rows has ``sqrt(sum(error_std**2) / (2 * permutations)) / n``
        (|.| is 1-Lipschitz). It ignores the small upward bias of |value + noise|.
        """
        if self.error_std is None or not self.permutations:
            return None
        n = len(self.values)
        return np.sqrt((self.error_std**2).sum(axis=0) / (2 * self.permutations)) / n

    def ranking(self, output: int = 0) -> list[str]:
        """Feature names by decreasing mean |SHAP| for output ``output`` (ties keep the feature order)."""
        imp = self.mean_abs()[:, output]
        return [self.feature_names[i] for i in np.argsort(-imp, kind="stable")]


def _chunked(predict: Callable[[np.ndarray], np.ndarray], counter: list[int]) -> Callable[[np.ndarray], np.ndarray]:
    """``predict`` in chunks of :data:`PREDICT_CHUNK_ROWS` rows, counting the rows it sees."""

    def f(X: np.ndarray) -> np.ndarray:
        counter[0] += len(X)
        if len(X) <= PREDICT_CHUNK_ROWS:
            return predict(X)
        return np.concatenate([predict(X[i:i + PREDICT_CHUNK_ROWS]) for i in range(0, len(X), PREDICT_CHUNK_ROWS)])

    return f


def shap_values(predict: Callable[[np.ndarray], np.ndarray], X: np.ndarray, background: np.ndarray, *,
                seed: int, feature_names: Sequence[str], output_names: Sequence[str],
                method: str = "auto") -> ShapResult:
    """Interventional SHAP values of ``predict`` (rows (N, d) -> (N, k)) on the rows ``X``.

    Args:
        predict: the model, e.g. :meth:`OnnxModel.predict` (called on batches of masked rows).
        X: (n, d) rows to explain.
        background: (B, d) rows the independent masker draws left-out features from.
        seed: seed of the permutation explainer's orderings (the exact one has no randomness).
        feature_names, output_names: names of the d columns and k outputs.
        method: ``auto``, ``exact`` or ``permutation`` (see :func:`choose_method` and the module docstring).
    """
    shap = require_shap()
    X = np.asarray(X, dtype=np.float64)
    background = np.asarray(background, dtype=np.float64)
    n, d = X.shape
    B = len(background)
    chosen, perms = choose_method(n, d, B, method)
    masker = shap.maskers.Independent(background, max_samples=B)  # all B rows: no internal subsampling
    counter = [0]
    f = _chunked(predict, counter)
    batch = max(1, PREDICT_CHUNK_ROWS // max(1, B))  # coalitions per model call
    t0 = time.perf_counter()
    # shap's permutation explainer seeds numpy's legacy global generator: restore it afterwards
    state = np.random.get_state()  # noqa: NPY002
    try:
        if chosen == "exact":
            explainer = shap.explainers.Exact(f, masker, feature_names=list(feature_names))
            exp = explainer(X, max_evals=2**d, batch_size=batch, silent=True)
            error_std = None
        else:
            explainer = shap.explainers.Permutation(f, masker, feature_names=list(feature_names), seed=int(seed))
            exp = explainer(X, max_evals=perms * (2 * d + 1), batch_size=max(batch, 2 * d + 1),
                            error_bounds=True, silent=True)
            error_std = None if exp.error_std is None else np.asarray(exp.error_std, dtype=np.float64)
    finally:
        np.random.set_state(state)  # noqa: NPY002
    seconds = time.perf_counter() - t0
    values = np.asarray(exp.values, dtype=np.float64)
    if values.ndim == 2:  # single-output model
        values = values[:, :, None]
        error_std = None if error_std is None else error_std.reshape(values.shape)
    base = np.asarray(exp.base_values, dtype=np.float64).reshape(n, -1)[0]
    return ShapResult(values, base, X, tuple(feature_names), tuple(output_names), chosen, perms, error_std, B,
                      int(counter[0]), seconds)


# ---------------------------------------------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------------------------------------------
def _label(name: str) -> str:
    """Axis label of a feature or catalogue signal: its name and unit (``steer_angle_rad@rate [rad/s]``)."""
    base, _, op = name.partition("@")
    if base not in cat.SIGNALS:
        return name
    unit = cat.SIGNALS[base].unit
    suffix = {"rate": "/s", "accel": "/s^2"}.get(op, "")
    return f"{name} [{unit}{suffix}]"


def plot_correlation(path: Path, names: Sequence[str], C: np.ndarray, subtitle: str = "") -> None:
    """Annotated heat map of the correlation matrix ``C`` (the paper's Fig. 2)."""
    from matplotlib.colors import to_rgba

    k = len(names)
    fig = plotting.figure(1.6 + 0.62 * k, 1.2 + 0.55 * k)
    ax = fig.add_subplot()
    cmap = plotting.colormap("RdBu_r").with_extremes(bad=to_rgba("0.85"))  # grey: undefined (a constant column)
    im = ax.imshow(np.ma.masked_invalid(C), cmap=cmap, vmin=-1.0, vmax=1.0)
    ax.set_xticks(range(k), names, rotation=50, ha="right", rotation_mode="anchor", fontsize=8)
    ax.set_yticks(range(k), names, fontsize=8)
    for i in range(k):
        for j in range(k):
            c = C[i, j]
            text = "n/a" if not np.isfinite(c) else f"{c:.2f}"
            colour = "white" if np.isfinite(c) and abs(c) > 0.6 else "black"
            ax.text(j, i, text, ha="center", va="center", fontsize=6.5, color=colour)
    n_in = sum(n in cat.INPUTS for n in names)
    if 0 < n_in < k:  # separate inputs and outputs
        for pos in (n_in - 0.5,):
            ax.axhline(pos, color="black", lw=1.0)
            ax.axvline(pos, color="black", lw=1.0)
    fig.colorbar(im, ax=ax, shrink=0.8, label="Pearson correlation coefficient")
    ax.set_title("Correlation of the 12 inputs and the 2 front SATs" + (f"\n{subtitle}" if subtitle else ""),
                 fontsize=10)
    plotting.save(fig, path)


def plot_importance(path: Path, result: ShapResult, subtitle: str = "") -> None:
    """Horizontal bars of mean |SHAP| per feature, descending, one panel per output (the paper's Fig. 8)."""
    imp = result.mean_abs()
    se = result.mean_abs_stderr()
    d, k = imp.shape
    fig = plotting.figure(6.0 * k, 1.4 + 0.36 * d)
    for j in range(k):
        ax = fig.add_subplot(1, k, j + 1)
        order = np.argsort(-imp[:, j], kind="stable")[::-1]  # largest at the top
        y = np.arange(d)
        ax.barh(y, imp[order, j], color="tab:red" if j == 0 else "tab:orange",
                xerr=None if se is None else se[order, j], ecolor="0.3", capsize=2)
        ax.set_yticks(y, [result.feature_names[i] for i in order], fontsize=8)
        top = float(imp[:, j].max()) if d else 1.0
        for yi, i in zip(y, order, strict=True):
            ax.text(imp[i, j] + 0.01 * top, yi, f"{imp[i, j]:.2f}", va="center", fontsize=7)
        ax.set_xlim(0, top * 1.18 if top > 0 else 1.0)
        ax.set_xlabel("mean |SHAP value| [Nm]")
        name = result.output_names[j]
        ax.set_title(f"{WHEEL_LABEL.get(name, name)} ({name})", fontsize=10)
        ax.grid(axis="x", alpha=0.3)
    what = "exact Shapley values" if result.method == "exact" else f"{result.permutations} antithetic permutations"
    fig.suptitle(f"Global SHAP importance ({what}, {len(result.values)} test rows, "
                 f"{result.background_rows} background rows)" + (f"\n{subtitle}" if subtitle else ""), fontsize=10)
    plotting.save(fig, path)


def interaction_partner(shap_module: Any, result: ShapResult, feature: int, output: int = 0) -> int | None:
    """The feature that seems to interact most with ``feature`` (shap's binning heuristic), or None."""
    if result.values.shape[1] < 2:
        return None
    order = shap_module.utils.approximate_interactions(feature, result.values[:, :, output], result.data)
    order = [int(i) for i in order if int(i) != feature]
    return order[0] if order else None


def plot_dependence(path: Path, result: ShapResult, features: Sequence[int], partners: Sequence[int | None],
                    output: int = 0) -> None:
    """SHAP value against feature value, coloured by the strongest interacting feature (the paper's Fig. 9)."""
    m = len(features)
    fig = plotting.figure(5.0 * m, 4.4)
    name = result.output_names[output]
    for p, (i, partner) in enumerate(zip(features, partners, strict=True)):
        ax = fig.add_subplot(1, m, p + 1)
        x, s = result.data[:, i], result.values[:, i, output]
        if partner is None:
            ax.scatter(x, s, s=9, color="tab:red", alpha=0.7, linewidths=0)
        else:
            c = result.data[:, partner]
            lo, hi = np.percentile(c, [2.0, 98.0])  # robust colour limits: a few outliers do not wash it out
            if hi <= lo:
                lo, hi = float(c.min()), float(c.max()) + 1e-12
            sc = ax.scatter(x, s, s=9, c=c, cmap="coolwarm", vmin=lo, vmax=hi, alpha=0.8, linewidths=0)
            fig.colorbar(sc, ax=ax, label=_label(result.feature_names[partner]), shrink=0.9)
        ax.axhline(0.0, color="0.5", lw=0.7)
        ax.set_xlabel(_label(result.feature_names[i]))
        ax.set_ylabel(f"SHAP value for {name} [Nm]")
        ax.set_title(f"#{p + 1}: {result.feature_names[i]}", fontsize=10)
        ax.grid(alpha=0.3)
    fig.suptitle(f"SHAP dependence of the {WHEEL_LABEL.get(name, name)}: top {m} features", fontsize=10)
    plotting.save(fig, path)


def plot_track(path: Path, t: np.ndarray, Y: np.ndarray, P: np.ndarray, metrics: Mapping[str, Any],
               lap: str, outside: np.ndarray | None = None) -> None:
    """Estimated (red) and true (blue) front SATs over a lap (``lap``: its title, e.g. "dry lap"), one panel per
    wheel (the paper's Figs. 5 and 6); rows ``outside`` the validity envelope (bool per row; None: no envelope)
    shaded."""
    fig = plotting.figure(12.0, 6.4)
    for j, (wheel, name) in enumerate((("fl", "sat_fl_nm"), ("fr", "sat_fr_nm"))):
        ax = fig.add_subplot(2, 1, j + 1)
        if outside is not None:
            plotting.shade(ax, t, outside, label="outside the validity envelope")
        ax.plot(t, Y[:, j], color=TRUE_COLOUR, lw=0.9, label="true")
        ax.plot(t, P[:, j], color=ESTIMATE_COLOUR, lw=0.8, label="estimated (ONNX)")
        m = metrics[wheel]
        ax.set_title(f"{lap}, {WHEEL_LABEL[name]}: R2 = {m['r2']:.3f}, MAE = {m['mae_nm']:.2f} Nm", fontsize=10)
        ax.set_ylabel(f"{name} [Nm]")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8, framealpha=0.8)
    ax.set_xlabel("time in the lap [s]")
    plotting.save(fig, path)


def plot_axle(path: Path, t: np.ndarray, Y: np.ndarray, P: np.ndarray, metrics: Mapping[str, Any],
              lap: str, outside: np.ndarray | None = None) -> None:
    """Estimated (red) and true (blue) axle total FL + FR over a lap (the paper's Fig. 7), rows ``outside``
    the validity envelope shaded."""
    fig = plotting.figure(12.0, 3.8)
    ax = fig.add_subplot()
    if outside is not None:
        plotting.shade(ax, t, outside, label="outside the validity envelope")
    ax.plot(t, Y.sum(axis=1), color=TRUE_COLOUR, lw=0.9, label="true")
    ax.plot(t, P.sum(axis=1), color=ESTIMATE_COLOUR, lw=0.8, label="estimated (ONNX)")
    m = metrics["axle"]
    ax.set_title(f"{lap}, axle total SAT (FL + FR): R2 = {m['r2']:.3f}, MAE = {m['mae_nm']:.2f} Nm", fontsize=10)
    ax.set_xlabel("time in the lap [s]")
    ax.set_ylabel("sat_fl_nm + sat_fr_nm [Nm]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8, framealpha=0.8)
    plotting.save(fig, path)


# ---------------------------------------------------------------------------------------------------------------
# the whole report
# ---------------------------------------------------------------------------------------------------------------
def _round(x: Any) -> Any:
    """JSON-friendly floats (full precision: the file doubles as a reproducibility check)."""
    if isinstance(x, dict):
        return {k: _round(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_round(v) for v in x]
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def check_out_dir(out: str | os.PathLike[str]) -> Path:
    """``out`` as a path, checked for :func:`explain` to write into (nothing is created here).

    Raises:
        UserError: ``out`` exists and is not a directory, or it (or its nearest existing ancestor, for a new
            one) is not a writable directory.
    """
    p = Path(out)
    if p.exists() and not p.is_dir():
        raise UserError(f"--out {p}: exists and is not a directory")
    nearest = next(a for a in (p, *p.parents) if a.exists())
    if not nearest.is_dir() or not os.access(nearest, os.W_OK | os.X_OK):
        raise UserError(f"--out {p}: {'directory' if nearest == p else nearest} is not writable")
    return p


def _lap_figures(out_dir: Path, model: Any, ds: Any, lap: str, name: str, axle_name: str | None,
                 figures: list[str], say: Callable[[str], None]) -> dict[str, Any]:
    """Estimate vs truth over one lap or circuit (:func:`plot_track`, and :func:`plot_axle` when ``axle_name``),
    out-of-envelope rows shaded; appends the file names to ``figures``; returns the metrics, with
    ``envelope`` (:func:`virtsensor.learning.scoring.envelope_split`; None without an envelope in the card)."""
    from virtsensor.learning.scoring import envelope_split
    from virtsensor.metrics import metrics as fit_metrics
    from virtsensor.model.envelope import Envelope

    P = model.predict(ds.X)
    m = fit_metrics(ds.Y, P)
    env_doc = model.card.get("envelope")
    env = None if env_doc is None else Envelope.from_json(env_doc, str(model.card_path))
    outside = None if env is None else env.outside_rows(ds.X, ds.feature_names)
    m["envelope"] = envelope_split(ds.Y, P, outside)
    t = ds.time_s - ds.time_s[0]
    plot_track(out_dir / name, t, ds.Y, P, m, lap, outside)
    figures.append(name)
    if axle_name is not None:
        plot_axle(out_dir / axle_name, t, ds.Y, P, m, lap, outside)
        figures.append(axle_name)
    share = "" if outside is None else f", {100 * m['envelope']['outside_share']:.1f} % outside the envelope"
    say(f"{lap}: R2 {m['r2']:.3f}, MAE {m['mae_nm']:.2f} Nm, axle R2 {m['axle']['r2']:.3f}{share}")
    return m


@dataclass
class _Inputs:
    """Everything :func:`explain` reads, loaded and checked before any figure is drawn."""

    model: Any
    spec: Any
    outputs: tuple[str, ...]
    runs: list[Any]
    cols: np.ndarray  # finite rows of the catalogue inputs and outputs, for the correlation
    ds: Any  # the features of ``runs``
    train_idx: np.ndarray  # the paper's random 70/30 split of ``ds``
    test_idx: np.ndarray
    laps: dict[str, Any]  # "dry"/"wet" -> the lap's features (with --track)
    circuits: dict[str, Any]  # run name -> its features (with --circuits)


def _load_inputs(model_path: str | os.PathLike[str], data: Sequence[str | os.PathLike[str]],
                 track: str | os.PathLike[str] | None, circuits: Sequence[str | os.PathLike[str]],
                 seed: int) -> _Inputs:
    """The model, the data, the track's laps and the circuits, each checked (see :func:`explain`'s Raises)."""
    from virtsensor.learning.dataset import build_dataset, check_disjoint, load_runs, refuse_trained_on
    from virtsensor.learning.evaluation import random_split

    model, spec, outputs = _load_model(model_path)
    needed = sorted(set(cat.INPUTS) | set(spec.signals) | set(outputs))
    runs = load_runs(data, needed=needed)
    track_run = load_runs([track], needed=sorted(set(spec.signals) | set(outputs)))[0] if track else None
    circuit_runs = load_runs(circuits, needed=sorted(set(spec.signals) | set(outputs))) if circuits else []
    unseen = [("--track", [track_run] if track_run is not None else []), ("--circuits", circuit_runs)]
    check_disjoint([("--data", runs), *unseen], "the track's laps and the circuits are runs the model never saw")
    refuse_trained_on(model.card, unseen, str(model_path), "its figures there are of runs it never saw")
    cols = table_columns([r.table for r in runs], (*cat.INPUTS, *cat.OUTPUTS))
    if len(cols) < 2:
        raise UserError("the data hold fewer than 2 finite rows: nothing to correlate")
    ds = build_dataset(runs, spec, targets=outputs)
    train_idx, test_idx = random_split(len(ds.X), seed)
    if len(test_idx) == 0 or len(train_idx) == 0:
        raise UserError(f"the data hold {len(ds.X)} usable rows: too few for a 70/30 split")
    laps = _track_laps(track_run, track, spec, outputs) if track_run is not None else {}
    return _Inputs(model, spec, outputs, runs, cols, ds, train_idx, test_idx, laps,
                   _circuit_sets(circuit_runs, spec, outputs))


def explain(model_path: str | os.PathLike[str], data: Sequence[str | os.PathLike[str]], out: str | os.PathLike[str],
            *, track: str | os.PathLike[str] | None = None,
            circuits: Sequence[str | os.PathLike[str]] = (), seed: int = 0, samples: int = 500,
            background: int = BACKGROUND_ROWS, method: str = "auto",
            log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Write the Section IV.B figures and ``explain.json`` to ``out``; return the JSON document.

    All or nothing: every input is read and checked before anything is written, and the files are written into
    a staging directory beside ``out`` (:func:`virtsensor.fileio.staged_dir`), moved into place only once all
    are written; on a refusal, a failure or an interrupt ``out`` is left as it was (not created when new).

    Args:
        model_path: the shipped ``.onnx`` (its model card beside it names the features).
        data: recordings (files or directories) of the data set, as for ``virtsensor train``.
        out: output directory (created with its parents when new; in an existing one, files of the same names
            are replaced and any other file is left alone).
        track: optional Magny-Cours recording (dry lap then wet lap) for Figs. 5-7.
        circuits: recordings of circuits the model never saw: one estimate-vs-truth figure each.
        seed: seed of the 70/30 split, of the explained and background rows and of the permutations.
        samples: test rows to explain (fewer if the test side is smaller).
        background: rows of the independent masker.
        method: ``auto`` (exact when affordable, else permutation), ``exact`` or ``permutation``.
        log: progress messages (default: none).

    Raises:
        UserError: missing/invalid model, data lacking a signal, a track lap or a circuit with fewer than 2
            usable rows, a track or circuit run that is also in the data or that the model was trained on (its
            card lists it), output directory not writable (or a directory where explain.json goes), shap or
            matplotlib not installed, nothing to explain.
        OSError: the figures cannot be written (a full disk), naming ``out``; nothing of them is left.
    """
    say = log or (lambda _msg: None)
    _check_options(samples, background, method)
    out_path = check_out_dir(out)
    if (out_path / "explain.json").is_dir():  # (found before the work, not when the files are moved into place)
        raise UserError(f"{out_path / 'explain.json'} is a directory: explain writes its JSON there; move it or "
                        "choose another --out")
    shap = require_shap()
    plotting.require("this command")
    inp = _load_inputs(model_path, data, track, circuits, seed)
    try:
        with staged_dir(out_path) as stage:
            doc = _write_all(stage, inp, shap, model_path=model_path, data=data, seed=seed, samples=samples,
                             background=background, method=method, say=say)
    except OSError as exc:  # (the machine, not the request: a full disk is exit 1, as for every command)
        raise OSError(exc.errno, f"cannot write the figures: {exc.strerror or exc}", str(out_path)) from None
    say(f"wrote {len(doc['figures'])} figures and explain.json to {out_path}")
    return doc


def _write_all(out_dir: Path, inp: _Inputs, shap: Any, *, model_path: str | os.PathLike[str],
               data: Sequence[str | os.PathLike[str]], seed: int, samples: int, background: int, method: str,
               say: Callable[[str], None]) -> dict[str, Any]:
    """Draw every figure of :func:`explain` from the checked inputs into ``out_dir``, write ``explain.json``
    there, and return its document."""
    model, spec, outputs, ds = inp.model, inp.spec, inp.outputs, inp.ds
    # ---- Fig. 2: correlation of the raw catalogue signals --------------------------------------------------
    corr_names = (*cat.INPUTS, *cat.OUTPUTS)
    C = correlation_matrix(inp.cols)
    figures: list[str] = []
    plot_correlation(out_dir / FIGURES["correlation"], corr_names, C, f"{len(inp.cols)} rows of {len(inp.runs)} runs")
    figures.append(FIGURES["correlation"])
    say(f"correlation of {len(corr_names)} signals over {len(inp.cols)} rows")

    # ---- Figs. 8 and 9: SHAP of the ONNX model on the paper's test rows ----------------------------------
    rng = np.random.default_rng(seed)
    explained = np.sort(rng.choice(inp.test_idx, min(samples, len(inp.test_idx)), replace=False))
    bg_idx = np.sort(rng.choice(inp.train_idx, min(background, len(inp.train_idx)), replace=False))
    shap_doc = _shap_figures(shap, out_dir, model, spec, outputs, ds.X[explained], ds.X[bg_idx],
                             seed=seed, method=method, figures=figures, say=say)
    doc: dict[str, Any] = {
        "model": {"file": str(model_path), "sha256": model.card["sha256"], "feature_spec": spec.name,
                  "features": list(spec.names), "outputs": list(outputs)},
        "data": {"sources": [str(p) for p in data], "runs": len(inp.runs), "rows": int(len(ds.X)),
                 "dropped_nonfinite": int(ds.dropped_nonfinite)},
        "seed": int(seed),
        "correlation": {"signals": list(corr_names), "rows": int(len(inp.cols)), "pearson": C.tolist()},
        **shap_doc,
    }

    # ---- Figs. 5-7: the Magny-Cours laps; the circuits; the grip margin --------------------------------------
    if inp.laps:
        doc["track"] = {lap: _lap_figures(out_dir, model, lds, f"{lap} lap", FIGURES[f"track_{lap}"],
                                          FIGURES["axle"] if lap == "wet" else None, figures, say)
                        for lap, lds in inp.laps.items()}
    if inp.circuits:
        doc["circuits"] = {name: _lap_figures(out_dir, model, cds, f"circuit {name}", f"circuit_{name}.png",
                                              None, figures, say) for name, cds in inp.circuits.items()}
    doc["grip"] = _grip_doc(out_dir, inp.runs, model, figures, say)  # (where runs carry the grip margin's truth)
    doc["figures"] = figures
    doc = _round(doc)
    write_json(out_dir / "explain.json", doc)
    return doc


def _grip_doc(out_dir: Path, runs: Sequence[Any], model: Any, figures: list[str],
              say: Callable[[str], None]) -> dict[str, Any] | None:
    """``grip.png``: the grip margin against its truth over the run that gets nearest the limit (None without
    a run carrying the grip truth)."""
    doc = grip_figure(out_dir / "grip.png", runs, model)
    if doc is not None:
        figures.append("grip.png")
        say(f"grip margin on {doc['run']}")
    return doc


def _check_options(samples: int, background: int, method: str) -> None:
    """Raise :class:`UserError` for a row count below 1 or an unknown method."""
    if samples < 1:
        raise UserError(f"--samples {samples}: must be at least 1")
    if background < 1:
        raise UserError(f"--background {background}: must be at least 1")
    if method not in ("auto", "exact", "permutation"):
        raise UserError(f"--method {method!r}: choose auto, exact or permutation")


def _load_model(model_path: str | os.PathLike[str]) -> tuple[Any, Any, tuple[str, ...]]:
    """``(model, feature spec, output names)`` of the shipped ``.onnx`` and its model card.

    Raises:
        UserError: no usable feature_spec in the card, its names differ from the graph's inputs, or an
            output is not a catalogue signal.
    """
    from virtsensor.features import FeatureSpec
    from virtsensor.model.onnx import OnnxModel

    model = OnnxModel.load(model_path)
    try:
        spec = FeatureSpec.from_json(model.card["feature_spec"])
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{model.card_path}: no usable feature_spec in the model card ({exc})") from None
    if spec.names != model.input_names:
        raise UserError(f"{model.card_path}: feature_spec names {list(spec.names)} differ from the graph's "
                        f"feature_names {list(model.input_names)}")
    outputs = tuple(model.outputs)
    missing_out = [o for o in outputs if o not in cat.SIGNALS]
    if missing_out:
        raise UserError(f"{model.card_path}: outputs {missing_out} are not catalogue signals")
    return model, spec, outputs


def _shap_figures(shap: Any, out_dir: Path, model: Any, spec: Any, outputs: tuple[str, ...], X: np.ndarray,
                  X_background: np.ndarray, *, seed: int, method: str, figures: list[str],
                  say: Callable[[str], None]) -> dict[str, Any]:
    """Figs. 8 and 9: SHAP values of ``model`` on the rows ``X`` against ``X_background`` (``method`` as in
    :func:`explain`); appends the file names to ``figures``; returns the ``explain.json`` entries
    ``shap``, ``mean_abs_shap_nm``, ``mean_abs_shap_stderr_nm``, ``ranking`` and ``dependence``."""
    chosen, perms = choose_method(len(X), len(spec.names), len(X_background), method)
    say(f"SHAP ({chosen}{'' if perms is None else f', {perms} antithetic permutations'}) of {model.path.name} "
        f"on {len(X)} test rows, {len(X_background)} background rows...")
    res = shap_values(model.predict, X, X_background, seed=seed, feature_names=spec.names,
                      output_names=outputs, method=method)
    say(f"SHAP: {res.model_rows:,} model rows in {res.seconds:.1f} s")
    # local accuracy: the values add up to the prediction minus the mean background prediction
    additivity = float(np.abs(res.values.sum(axis=1) + res.base_values - model.predict(res.data)).max())
    plot_importance(out_dir / FIGURES["importance"], res, f"model {model.path.name}, seed {seed}")
    figures.append(FIGURES["importance"])
    top = [int(i) for i in np.argsort(-res.mean_abs()[:, 0], kind="stable")[:3]]
    partners = [interaction_partner(shap, res, i, 0) for i in top]
    plot_dependence(out_dir / FIGURES["dependence"], res, top, partners, 0)
    figures.append(FIGURES["dependence"])

    imp, se = res.mean_abs(), res.mean_abs_stderr()
    return {
        "shap": {
            "library": f"shap {shap.__version__}",
            "explainer": "shap.explainers.Exact" if res.method == "exact" else "shap.explainers.Permutation",
            "method": res.method,
            "exact": res.method == "exact",
            "antithetic_permutations": res.permutations,
            "masker": "shap.maskers.Independent (interventional Shapley values)",
            "background_rows": res.background_rows,
            "background_from": "training side of the random 70/30 split",
            "explained_rows": int(len(X)),
            "explained_from": "test side of the random 70/30 split (evaluation.random_split)",
            "model_rows_evaluated": res.model_rows,
            "model": "the ONNX graph through OnnxModel.predict",
            "base_value_nm": dict(zip(outputs, res.base_values.tolist(), strict=True)),
            "additivity_max_abs_nm": additivity,
        },
        "mean_abs_shap_nm": {o: {f: float(imp[i, j]) for i, f in enumerate(spec.names)}
                             for j, o in enumerate(outputs)},
        "mean_abs_shap_stderr_nm": None if se is None else {
            o: {f: float(se[i, j]) for i, f in enumerate(spec.names)} for j, o in enumerate(outputs)},
        "ranking": {o: res.ranking(j) for j, o in enumerate(outputs)},
        "dependence": {"output": outputs[0], "features": [spec.names[i] for i in top],
                       "colour_by": [None if p is None else spec.names[p] for p in partners]},
    }


def _track_laps(track_run: Any, track: str | os.PathLike[str] | None, spec: Any,
                outputs: tuple[str, ...]) -> dict[str, Any]:
    """The features of the dry and wet laps of ``track_run``, in that order (for Figs. 5-7).

    Raises:
        UserError: a lap is missing or has fewer than 2 usable rows.
    """
    from virtsensor.learning.dataset import build_dataset, split_track_laps

    laps = split_track_laps(track_run)
    out: dict[str, Any] = {}
    for lap in ("dry", "wet"):
        if lap not in laps:
            raise UserError(f"--track {track}: no {lap} lap found (road_mu must drop for the wet lap)")
        out[lap] = build_dataset([laps[lap]], spec, targets=outputs)
        if len(out[lap].X) < 2:
            raise UserError(f"--track {track}: the {lap} lap has {len(out[lap].X)} usable rows")
    return out


def _circuit_sets(circuits: Sequence[Any], spec: Any, outputs: tuple[str, ...]) -> dict[str, Any]:
    """The features of each run of ``circuits`` (loaded), by run name (one estimate-vs-truth figure each).

    Raises:
        UserError: a run has fewer than 2 usable rows, or two have the same name.
    """
    from virtsensor.learning.dataset import build_dataset

    out: dict[str, Any] = {}
    for r in circuits:
        if r.name in out:
            raise UserError(f"--circuits {r.path}: a second circuit named {r.name} (its figure would replace the "
                            "first one's); rename one")
        out[r.name] = build_dataset([r], spec, targets=outputs)
        if len(out[r.name].X) < 2:
            raise UserError(f"--circuits {r.path}: {len(out[r.name].X)} usable rows")
    return out
