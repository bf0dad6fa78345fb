"""The one way the project draws: matplotlib Figures on an Agg canvas, saved atomically as PNG.

No pyplot state and no display: :func:`figure` makes a Figure bound to an Agg canvas, :func:`save` writes it
through :func:`virtsensor.fileio.atomic_write` (a reader never sees half a PNG) and closes nothing global.
matplotlib is the optional extra ``plots``: :func:`require` (called by :func:`figure`) raises
:class:`~virtsensor.extras.MissingExtra` naming it, exit code 2 at the command line.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from virtsensor.extras import require as require_extra
from virtsensor.fileio import atomic_write

__all__ = ["DPI", "available", "colormap", "figure", "require", "save", "shade"]

#: Resolution of every saved figure (dots per inch).
DPI = 110


def available() -> bool:
    """Whether matplotlib can be imported (figures are optional where a command also prints numbers)."""
    import importlib.util

    return importlib.util.find_spec("matplotlib") is not None


def require(what: str = "the figures") -> None:
    """Raise :class:`~virtsensor.extras.MissingExtra` (extra ``plots``) when matplotlib is absent."""
    require_extra("plots", what)


def figure(width: float, height: float, *, what: str = "the figures") -> Any:
    """A ``matplotlib.figure.Figure`` of ``width`` x ``height`` inches, constrained layout, on an Agg canvas."""
    require(what)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def colormap(name: str) -> Any:
    """A registered matplotlib colormap by name (e.g. ``"RdBu_r"``)."""
    import matplotlib

    return matplotlib.colormaps[name]


def save(fig: Any, path: str | os.PathLike[str]) -> Path:
    """Write ``fig`` as PNG to ``path`` atomically (folders created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=DPI))
    return path


def shade(ax: Any, x: Any, mask: Any, *, color: str = "0.85", label: str | None = None) -> int:
    """Shade on ``ax`` the stretches of ``x`` (increasing) where ``mask`` (bool, same length) is True, each
    from its first to its last sample widened by half the median sample step on each side; ``label`` names
    the first in a legend.
    Returns how many stretches were shaded."""
    import numpy as np

    m = np.asarray(mask, dtype=bool)
    xs = np.asarray(x, dtype=float)
    edges = np.flatnonzero(np.diff(np.concatenate(([0], m.view(np.int8), [0]))))
    starts, ends = edges[::2], edges[1::2] - 1
    step = float(np.median(np.diff(xs))) if len(xs) > 1 else 1.0
    for k, (a, b) in enumerate(zip(starts, ends, strict=True)):
        ax.axvspan(xs[a] - 0.5 * step, xs[b] + 0.5 * step, color=color, lw=0, zorder=0,
                   label=label if k == 0 else None)
    return int(len(starts))
