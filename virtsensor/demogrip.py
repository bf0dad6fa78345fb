"""The grip margin in ``virtsensor demo`` and ``virtsensor explain``: VS_Grip against the truth.

:func:`grip_summary` condenses the daemon's VS_Grip frames of a demo run (one per tick) against the road's friction
the recording states (its ``.json`` sidecar, ``mu``): warning ticks and the first warning, the friction where
given and its error. :func:`plot_grip` draws the utilisation, the warning and the friction estimate with its
interval against the truth on a matplotlib axes (the demo's fourth panel, the explain figure ``grip.png``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["grip_summary", "grip_line", "plot_grip", "GRIP_SIGNALS"]

#: VS_Grip signals a demo listener keeps per tick: utilisation, friction, half-width, warning
GRIP_SIGNALS = ("VS_GripUtil", "VS_GripMu", "VS_GripMuHalfWidth", "VS_GripWarning")


def grip_summary(t: Sequence[float], grips: Sequence[Sequence[float]], road_mu: float | None) -> dict[str, Any]:
    """Figures of a run's VS_Grip values (rows: util, mu, half-width, warning; nan = SNA) at tick times ``t``."""
    g = np.array(grips, dtype=float).reshape(-1, 4)
    tt = np.asarray(t, dtype=float)[: len(g)]
    g = g[: len(tt)]
    warn = g[:, 3] > 0.5
    given = np.isfinite(g[:, 1])
    out: dict[str, Any] = {
        "ticks": int(len(g)), "util_max": float(np.nanmax(g[:, 0])) if np.isfinite(g[:, 0]).any() else None,
        "warning_ticks": int(warn.sum()), "first_warning_s": float(tt[warn][0]) if warn.any() else None,
        "mu_given_ticks": int(given.sum()),
        "mu_median": float(np.median(g[given, 1])) if given.any() else None,
        "road_mu": road_mu,
    }
    if road_mu is not None and given.any():
        err = np.abs(g[given, 1] - road_mu)
        out["mu_within_0_1_share"] = float(np.mean(err <= 0.1))
        out["mu_abs_err_p90"] = float(np.percentile(err, 90))
        out["mu_interval_cover_share"] = float(np.mean(err <= g[given, 2]))
    return out


def grip_line(s: dict[str, Any]) -> str:
    """One line for the demo's summary."""
    fw = "never" if s["first_warning_s"] is None else f"first at {s['first_warning_s']:.2f} s"
    um = "—" if s["util_max"] is None else f"{s['util_max']:.2f}"
    txt = f"grip (VS_Grip): utilisation up to {um}; warning on {s['warning_ticks']} ticks ({fw}); friction given " \
          f"on {s['mu_given_ticks']} ticks"
    if s["mu_median"] is not None:
        txt += f", median {s['mu_median']:.2f}"
        if s["road_mu"] is not None:
            txt += (f" against the road's {s['road_mu']:g} (within +-0.1 on {100 * s['mu_within_0_1_share']:.0f} % "
                    f"of them, inside its interval on {100 * s['mu_interval_cover_share']:.0f} %)")
    return txt


def plot_grip(ax: Any, t: np.ndarray, util: np.ndarray, mu: np.ndarray, halfwidth: np.ndarray, warning: np.ndarray,
              road_mu: np.ndarray | float | None = None, util_true: np.ndarray | None = None) -> None:
    """Utilisation (and its truth), warning (shaded), friction +- half-width (and the road's) on ``ax``."""
    t = np.asarray(t, dtype=float)
    w = np.asarray(warning, dtype=bool)
    if w.any():
        ax.fill_between(t, 0, 1.2, where=w, color="tab:red", alpha=0.15, step="mid", label="grip-limit warning")
    if util_true is not None:
        ax.plot(t, util_true, color="k", lw=1.4, label="utilisation, true (front, more used tyre)")
    ax.plot(t, util, color="tab:purple", lw=1.1, label="utilisation, estimated")
    if road_mu is not None:
        ax.plot(t, np.broadcast_to(np.asarray(road_mu, dtype=float), t.shape), color="k", ls="--", lw=1.2,
                label="road mu, true")
    ax.plot(t, mu, color="tab:green", lw=1.4, label="road mu, estimated (where given)")
    lo, hi = mu - halfwidth, mu + halfwidth
    ax.fill_between(t, lo, hi, where=np.isfinite(mu), color="tab:green", alpha=0.25, label="its interval")
    ax.set_ylim(0.0, 1.2)
    ax.set_ylabel("utilisation / mu")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=7, ncol=2)




def grip_figure(path: Any, runs: Sequence[Any], model: Any) -> dict[str, Any] | None:
    """``virtsensor explain``'s grip figure: the grip estimate against the truth over the run (of ``runs``, with
    the grip truth) whose front utilisation gets highest (ties: the most samples where the friction is given).
    Returns that run's name and figures, or None (no figure) when no run carries the grip truth."""
    from virtsensor import plotting
    from virtsensor.learning import gripscore as gs

    cands = [r for r in runs if gs.has_grip_truth(r.table)]
    if not cands:
        return None
    best = max(cands, key=lambda r: float(np.max(gs.true_front_util(r.table))))
    fl, fr = gs.model_sats(model, best.table)
    res = gs.grip_of_run(best.table, fl, fr, sat_reads_pressure=gs.model_reads_pressure(model),
                         outside=gs.model_outside(model, best.table))
    assert res is not None
    m, est = res
    t = np.asarray(best.table["time_s"], dtype=float)
    fig = plotting.figure(11, 5, what="the grip figure")
    ax = fig.subplots(1, 1)
    plot_grip(ax, t, est["util"], est["mu"], est["halfwidth"], est["warning"],
              np.asarray(best.table["road_mu"], dtype=float), gs.true_front_util(best.table))
    ax.set_xlabel("time [s]")
    lead = "—" if m["warning_lead_s"] is None else f"{m['warning_lead_s']:.2f} s"
    share = "—" if m["mu_within_0_1_share"] is None else f"{100 * m['mu_within_0_1_share']:.0f} %"
    fig.suptitle(f"grip margin (VS_Grip) on {best.name}: warning lead before 95 % {lead}; mu within +-0.1 on {share}"
                 f" of {m['mu_scored']} samples given", fontsize=10)
    plotting.save(fig, path)
    return {"run": best.name, **gs.public(m)}
