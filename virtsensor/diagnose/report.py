"""The diagnosis as a Markdown report and plots (matplotlib, optional)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from virtsensor import plotting
from virtsensor import signals as cat


def _f(x: Any, nd: int = 4) -> str:
    if x is None:
        return "-"
    if isinstance(x, float) and not math.isfinite(x):
        return "inf" if x > 0 else ("-inf" if x < 0 else "nan")
    return f"{x:.{nd}g}" if isinstance(x, float) else str(x)


def markdown(res: Mapping[str, Any]) -> str:
    """The report of a :func:`virtsensor.diagnose.diagnose` result."""
    out = ["# Sim-to-real diagnosis", ""]
    runs = res["runs"]
    out.append(f"Measured runs for the diagnosis: {len(runs)} ("
               f"{sum(r['duration_s'] for r in runs):.0f} s); held out for the gain: {len(res['holdout_runs'])}. "
               f"{res['simulations']} re-simulation batches (hypotheses) in {res['seconds_identify']:.0f} s.")
    for sk in res.get("skipped_runs", []):
        out.append("")
        out.append(f"Left out: {sk['file']}: {sk['reason']}")
    gaps = [(r["name"], g) for r in runs for g in r["gaps_s"]]
    if gaps:
        out.append("")
        out.append("Gaps (not interpolated; each stretch between them was re-simulated on its own): "
                   + "; ".join(f"{n} {a:.2f}-{b:.2f} s" for n, (a, b) in gaps))
    out += ["", "## Cause", ""]
    out += _cause_lines(res)
    out += _conditions_lines(res)
    out += ["", "## Candidates (best first)", "",
            "| cause | signal | estimate | 95 % interval | BIC gain | misfit explained | significant |",
            "|---|---|---|---|---|---|---|"]
    for c in res["candidates"][:12]:
        out.append(f"| {c['cause']} | {c['signal'] or ''} | {_f(c['estimate'])} | {_f(c['ci95'][0])} .. "
                   f"{_f(c['ci95'][1])} | {c['bic_gain']:.1f} | {100 * c['variance_explained']:.1f} % | "
                   f"{'yes' if c['significant'] else 'no'} |")
    out.append("")
    out.append(f"BIC gain: evidence over the nominal car with the effective sample size "
               f"({res['n_eff_factor']:.3f} x n, from the residuals' autocorrelation); > 10 is decisive.")
    comp = res["comparison"]
    out += ["", "## What the simulation gets wrong, signal by signal", "",
            "Measured minus re-simulated (nominal car): bias, gain (slope about the means), lag "
            "(> 0: measured later), normalised RMS error and R2"
            + ("; and the calibrated car's NRMSE." if comp["calibrated"] else "."), "",
            "| signal | unit | bias | gain | lag [s] | NRMSE | R2 |"
            + (" NRMSE calibrated |" if comp["calibrated"] else ""),
            "|---|---|---|---|---|---|---|" + ("---|" if comp["calibrated"] else "")]
    for n, s in comp["nominal"].items():
        row = (f"| {n} | {cat.SIGNALS[n].unit} | {_f(s['bias'], 3)} | {_f(s['gain'], 3)} | {_f(s['lag_s'], 2)} | "
               f"{_f(s['nrmse'], 3)} | {_f(s['r2'], 3)} |")
        if comp["calibrated"]:
            row += f" {_f(comp['calibrated'][n]['nrmse'], 3)} |"
        out.append(row)
    dep = comp["sat_residual_dependence"]
    if dep:
        out += ["", "## SAT (front left) residual against the operating point", ""]
        for k, d in dep.items():
            out.append(f"- {k} [{d['unit']}]: " + ", ".join(
                f"{c:.3g}: {m:+.2f} Nm" for c, m in zip(d["centre"], d["mean_residual_nm"], strict=True)))
    out += _estimator_lines(res)
    return "\n".join(out) + "\n"


def _estimator_lines(res: Mapping[str, Any]) -> list[str]:
    """The SAT estimator's section: how it was trained, what was calibrated and what was not (the day's conditions),
    and the gain on the held-out runs (nothing without an estimator)."""
    out: list[str] = []
    est = res.get("estimator")
    if est:
        on = res["estimator_on_diagnosis_runs"]
        out += ["", "## The SAT estimator", "",
                f"Trained on the `{est['preset']}` campaign, recipe features `{est['recipe']['features']}`, "
                f"seed {est['seed']}.", "",
                f"- On the diagnosis runs, nominal estimator: MAE {on['measured']['mae_nm']:.2f} Nm on the measured "
                f"data against {on['simulated']['mae_nm']:.2f} Nm on their re-simulation "
                f"(R2 {on['measured']['r2']:.3f} against {on['simulated']['r2']:.3f})."]
        how = [f"retrained on the simulator with {', '.join(est['retrained_with'])}"] \
            if est.get("retrained_with") else []
        how += [f"input {k} corrected ((measured - {v['offset']:.4g}) / {v['gain']:.4g})"
                for k, v in est.get("inputs_corrected", {}).items()]
        if how:
            out.append("- Calibrated estimator: " + "; ".join(how) + ".")
        for k, v in est.get("day_conditions", {}).items():
            out.append(f"- Not retrained for {k} = {v:.4g}: a condition of the test day, not of the car (the "
                       "estimator's campaign spans a range of roads).")
        if res.get("mae_before_nm") is not None:
            out.append(f"- On the held-out measured runs: MAE {res['mae_before_nm']:.2f} -> {res['mae_after_nm']:.2f}"
                       f" Nm, R2 {res['r2_before']:.3f} -> {res['r2_after']:.3f} (before -> after calibration).")
            g = res.get("gain")
            if g:
                out.append(f"- Gain of the calibrated estimator: {g['mae_gain_nm']:+.2f} Nm "
                           f"({100 * g['relative']:+.0f} %), 95 % interval {g['ci95_nm'][0]:+.2f} to "
                           f"{g['ci95_nm'][1]:+.2f} Nm (block bootstrap over {g['blocks']} stretches of 5 s); "
                           f"estimator kept: {res.get('estimator_kept')}.")
            if res.get("gain_note"):
                out.append(f"- {res['gain_note']}")
        else:
            out.append(f"- {res.get('gain_note', 'no gain measured')}")
    return out


def _cause_lines(res: Mapping[str, Any]) -> list[str]:
    """The verdict: the causes named (best first), ``unexplained`` with its signature, or ``none``."""
    out: list[str] = []
    if res["cause"] == "none":
        out.append("**none**: no candidate explains the residual decisively. Residual RMS per signal "
                   "(the signature left unexplained):")
        out.append("")
        out += [f"- {k}: {_f(v)}" for k, v in res["signature"]["residual_rms"].items()]
        return out
    if res["cause"] == "unexplained":
        u = res["unexplained"]
        why = []
        if u["disagreeing_groups"]:
            why.append(f"the best one, `{u['forced_onto']}` at {_f(u['estimate'])}, fits some signals at the "
                       "others' expense: " + "; ".join(
                           f"the {g} signals alone put it at {_f(i['estimate'])} (+-{_f(i['half_width'], 2)})"
                           for g, i in u["disagreeing_groups"].items()))
        if u.get("kinematics"):
            k = u["kinematics"]
            why.append(f"the best one, `{u['forced_onto']}` at {_f(u['estimate'])}, is not the sensor's gain: the "
                       f"car's kinematics (ay - r vx over {k['stretches']} straight-to-straight stretches) put it at "
                       f"{_f(k['estimate'])} (+-{_f(k['half_width'], 2)}, {100 * k['confidence']:.0f} %)")
        if u.get("held_out"):
            h = u["held_out"]
            why.append(f"the best one, `{u['forced_onto']}` at {_f(u['estimate'])}, does not hold on runs it was "
                       f"not fitted on (evidence {_f(h['evidence'])} there; "
                       + (", ".join(h["fold_names"][i] for i in h["contradicted_by"]) + " made worse"
                          if h["contradicted_by"] else "not decisive") + ")")
        if u.get("excess"):
            after = f"with `{u['forced_onto']}` named" if u["forced_onto"] else "with the nominal car"
            why.append(f"{after}, signals stay far above the re-simulation's own error on a control day: "
                       + ", ".join(f"{k} {_f(v, 2)}x" for k, v in u["excess"].items())
                       + f" (limit {_f(u['excess_limit'], 2)}x)")
        out.append("**unexplained**: no effect of the catalogue accounts for the misfit; " + "; ".join(why)
                   + ". No calibration is applied.")
        out.append("")
        out.append("Signature of what remains: " + ", ".join(
            f"{k} ({100 * u['remaining_share'][k]:.0f} % of its misfit left)" for k in u["signals"])
            + f"; largest reference-SAT residual at {u['region']}.")
        return out
    for i, c in enumerate(res["causes"]):
        on = f" on `{c['signal']}`" if c["signal"] else ""
        lead = "" if i == 0 else "and "
        out.append(f"{lead}**{c['cause']}**{on}: estimate {_f(c['estimate'])} {c['unit']} "
                   f"(95 % interval {_f(c['ci95'][0])} to {_f(c['ci95'][1])}; nominal {_f(c['nominal'])}), "
                   f"explaining {100 * c['variance_explained']:.0f} % of the misfit (likelihood-ratio R2)"
                   + (" over the first cause." if i else "."))
        if c.get("kinematics"):
            k = c["kinematics"]
            out.append("")
            out.append(f"The car's kinematics (ay - r vx over {k['stretches']} straight-to-straight stretches, no "
                       f"vehicle model) put this gain at {_f(k['estimate'])} (+-{_f(k['half_width'], 2)}, "
                       f"{100 * k['confidence']:.0f} %): they agree.")
        out.append("")
    sig = res["signature"].get("explains", {})
    if sig:
        out.append("Signature (share of each signal's residual the first cause explains): "
                   + ", ".join(f"{k} {100 * v:.0f} %" for k, v in sig.items()))
    out.append("")
    out.append("The 95 % intervals count the re-simulation's own model error (the catalogue's stated accuracy, "
               "added in quadrature to the statistical half-width from the effective sample size).")
    return out


def _conditions_lines(res: Mapping[str, Any]) -> list[str]:
    """Per-run conditions: the values the re-simulation used and the identified ones with their intervals, then
    the runs' notes (a JSON beside a run that was ignored)."""
    rcs = res.get("run_conditions") or []
    if not any(rc["used"] for rc in rcs):
        return []
    out = ["", "## Per-run conditions", "",
           "| run | " + " | ".join(["used", "identified (95 % interval)"]) + " |", "|---|---|---|"]
    for rc in rcs:
        used = ", ".join(f"{k} {_f(v, 3)}" for k, v in rc["used"].items())
        ident = "; ".join(
            f"{q} {_f(v['estimate'], 3)} ({_f(v['ci95'][0], 3)} to {_f(v['ci95'][1], 3)})"
            + ("" if v["excited"] else ": the run does not excite it")
            for q, v in rc["identified"].items()) or "-"
        out.append(f"| {rc['name']} | {used} | {ident} |")
    notes = [f"- {rc['name']}: {note}" for rc in rcs for note in rc.get("notes", [])]
    return out + (["", *notes] if notes else [])


def plots(art: Mapping[str, Any], res: Mapping[str, Any], out_dir: Path) -> list[Path]:
    """PNG figures into ``out_dir`` (:mod:`virtsensor.plotting`); returns the files written (none without the
    ``plots`` extra)."""
    if not plotting.available():
        return []
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    comp = art["comparison"]
    series = comp.series
    shown = ("sat_fl_nm", "steer_torque_nm", "ay_mps2", "yaw_rate_radps")
    fig = plotting.figure(4.5 * len(series), 2.2 * len(shown), what="--report")
    axes = fig.subplots(len(shown), len(series), squeeze=False)
    for j, s in enumerate(series):
        for i, n in enumerate(shown):
            ax = axes[i][j]
            ax.plot(s["time_s"], s["measured"][n], "k", lw=1, label="measured")
            ax.plot(s["time_s"], s["nominal"][n], "C0", lw=0.9, label="nominal sim")
            if s["calibrated"] is not None:
                ax.plot(s["time_s"], s["calibrated"][n], "C3--", lw=0.9, label="calibrated sim")
            ax.set_ylabel(f"{n} [{cat.SIGNALS[n].unit}]", fontsize=7)
            if i == 0:
                ax.set_title(f"{s['run']} #{s['segment']}" + (" (left out)" if s.get("excluded") else ""), fontsize=8)
            ax.tick_params(labelsize=7)
    axes[0][0].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]", fontsize=7)
    written.append(plotting.save(fig, out_dir / "diagnose_timeseries.png"))
    cands = res["candidates"][:10]
    fig = plotting.figure(7, 3.5, what="--report")
    ax = fig.subplots()
    labels = [c["cause"] + (f"[{c['signal']}]" if c["signal"] else "") for c in cands]
    ax.barh(range(len(cands))[::-1], [max(c["bic_gain"], 0.0) for c in cands],
            color=["C3" if c["significant"] else "C7" for c in cands])
    ax.set_yticks(range(len(cands))[::-1], labels, fontsize=7)
    ax.axvline(10.0, color="k", lw=0.8, ls=":")
    ax.set_xlabel("BIC gain over the nominal car (> 10: decisive)")
    written.append(plotting.save(fig, out_dir / "diagnose_candidates.png"))
    dep = comp.dependence
    if dep:
        fig = plotting.figure(3.2 * len(dep), 2.8, what="--report")
        axes = fig.subplots(1, len(dep), squeeze=False)
        for ax, (k, d) in zip(axes[0], dep.items(), strict=True):
            ax.plot(d["centre"], d["mean_residual_nm"], "o-", label="mean")
            ax.plot(d["centre"], d["mean_abs_residual_nm"], "s--", label="mean |.|")
            ax.set_xlabel(f"{k} [{d['unit']}]", fontsize=8)
            ax.axhline(0.0, color="k", lw=0.6)
        axes[0][0].set_ylabel("SAT FL residual [Nm]")
        axes[0][0].legend(fontsize=7)
        written.append(plotting.save(fig, out_dir / "diagnose_dependence.png"))
    if comp.spectra:
        fig = plotting.figure(3.6 * len(comp.spectra), 2.8, what="--report")
        axes = fig.subplots(1, len(comp.spectra), squeeze=False)
        for ax, (n, d) in zip(axes[0], comp.spectra.items(), strict=True):
            ax.semilogy(d["f_hz"], d["psd_measured"], "k", label="measured")
            ax.semilogy(d["f_hz"], d["psd_simulated"], "C0", label="nominal sim")
            ax.set_title(n, fontsize=8)
            ax.set_xlabel("f [Hz]", fontsize=8)
        axes[0][0].legend(fontsize=7)
        written.append(plotting.save(fig, out_dir / "diagnose_spectra.png"))
    return written
