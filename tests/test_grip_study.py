"""tools/grip_study.py: the fit of the trail's utilisation curve and the command line (no campaign is run)."""

from __future__ import annotations

import importlib.util
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("grip_study", ROOT / "tools" / "grip_study.py")
study = importlib.util.module_from_spec(_spec)
sys.modules["grip_study"] = study
_spec.loader.exec_module(study)
grip = study.grip


def test_utilisation_curve_is_the_weighted_isotonic_fit():
    """A sparse bin at the collapsed end (a few samples, a low median) is pooled with its heavy neighbour rather
    than capping the whole curve (as a running minimum from that end would); the result never increases with the
    trail, keeps a curve that already does not, and is the weighted mean over each pooled block."""
    y = np.array([0.80, 0.92, 0.90, 0.70, 0.75, 0.40])
    w = np.array([10.0, 300.0, 300.0, 500.0, 100.0, 400.0])
    fit = study._non_increasing(y, w)
    assert np.all(np.diff(fit) <= 0)
    assert fit[0] == pytest.approx((0.80 * 10 + 0.92 * 300) / 310)
    assert fit[0] > 0.9 > np.minimum.accumulate(y)[0]
    assert fit[3] == pytest.approx(fit[4]) == pytest.approx((0.70 * 500 + 0.75 * 100) / 600)
    assert fit[5] == pytest.approx(0.40)
    mono = np.array([0.9, 0.8, 0.8, 0.3])
    assert np.array_equal(study._non_increasing(mono, np.ones(4)), mono)


def test_counts_bin_as_the_curve_does():
    """Samples per trail knot: within half a spacing of it, the end knots taking everything beyond."""
    k = np.asarray(study.TRAIL_KNOTS)
    trail = np.array([k[0] - 1.0, k[0], k[3] + 0.001, k[3] - 0.001, k[-1] + 1.0])
    c = study._counts(trail)
    assert len(c) == len(k) and c.sum() == len(trail)
    assert c[0] == 2 and c[3] == 2 and c[-1] == 1


@pytest.mark.parametrize("argv", [["accept", "--warning-only"], ["fit", "--warning-only", "--evidence-only"],
                                  ["accept", "--evidence-only"], ["bound", "--evidence-gate-only"],
                                  ["fit", "--evidence-gate-only", "--interval-only"]])
def test_fit_options_are_refused_where_they_do_not_apply(argv, capsys):
    with pytest.raises(SystemExit) as e:
        study.main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert all(f in err[-1] for f in argv if f.startswith("--"))  # (the message names each option given)


def test_oracle_warning_is_the_perfect_sensor_with_the_estimators_hysteresis():
    """The bound's perfect sensor: on the tick the true utilisation reaches the threshold (the lead then is the time
    the truth takes from there to 0.95), earlier by the look-ahead along its rate, off only after the hold below the
    threshold less 0.1; an onset at 0.7 or above is never a false warning."""
    t = np.arange(120) * 0.05
    u = np.clip(0.3 + 0.35 * (t - 1.5), 0.3, 1.0)  # calm 1.5 s, then 0.35 per second: 0.7 at 2.64 s, 0.95 at 3.36 s
    u = np.where(t < 4.5, u, 0.3)
    w = study.oracle_warning(u, 0.7, 0.0, 0.5)
    first = int(np.flatnonzero(w)[0])
    assert u[first] >= 0.7 > u[first - 1]
    m = study.gs.grip_metrics(t, u, u, np.full(len(t), np.nan), w)
    assert m["warning_lead_s"] == pytest.approx(t[np.flatnonzero(u >= 0.95)[0]] - t[first])
    assert m["false_warnings"] == 0
    ahead = study.oracle_warning(u, 0.7, 0.3, 0.5)
    assert np.flatnonzero(ahead)[0] < first and u[np.flatnonzero(ahead)[0]] >= 0.5
    off = np.flatnonzero(~w & (t > 4.5))[0]  # below 0.6 from 4.5 s: off after the 0.5 s hold
    assert t[off] == pytest.approx(4.5 + 0.5, abs=0.06)


def test_rise_time_to_the_limit():
    """From the last rise through a level to the first rise through 0.95 after the start-up (None: no limit)."""
    t = np.arange(100) * 0.05
    u = np.where(t < 2.0, 0.4, np.where(t < 2.5, 0.75, 0.97))
    assert study._rise_s(t, u, 0.7) == pytest.approx(0.5)
    assert study._rise_s(t, u, 0.5) == pytest.approx(0.5)
    assert study._rise_s(t, u, 0.3) == pytest.approx(2.5)  # never below: from the run's start
    assert study._rise_s(t, np.full(100, 0.5), 0.7) is None


def test_a_partial_fit_keeps_the_provenance_of_the_parts_it_does_not_fit():
    """A warning-only fit names the full fit, the utilisation curve's fit it keeps and itself (not the curve's fit
    dropped, as the warning-only fit once did); again the same; an evidence fit names itself for the curve and the
    warning; an interval fit adds itself and is kept by a later warning fit (the older "curve and warning" form
    read)."""
    full = "tools/grip_study.py fit --seed 1901: campaigns"
    evc = "tools/grip_study.py fit --evidence-only --seed 1901"
    wc = "tools/grip_study.py fit --warning-only --seed 1901"
    ev = study._source(full, ("utilisation curve", "warning"), "--evidence-only", 1901)
    assert ev == f"{full}; utilisation curve: {evc}; warning: {evc}"
    w = study._source(ev, ("warning",), "--warning-only", 1901)
    assert w == f"{full}; utilisation curve: {evc}; warning: {wc}"
    assert study._source(w, ("warning",), "--warning-only", 1901) == w
    assert study._source(full, ("warning",), "--warning-only", 1901) == f"{full}; warning: {wc}"
    old_form = f"{full}; utilisation curve and warning: {evc}"
    iv = study._source(old_form, ("interval",), "--interval-only", 1901)
    ic = "tools/grip_study.py fit --interval-only --seed 1901"
    assert iv == f"{full}; utilisation curve: {evc}; warning: {evc}; interval: {ic}"
    assert study._source(iv, ("warning",), "--warning-only", 1901) == (
        f"{full}; utilisation curve: {evc}; warning: {wc}; interval: {ic}")
    gc = "tools/grip_study.py fit --evidence-gate-only --seed 1901"
    assert study._source(iv, ("evidence gate",), "--evidence-gate-only", 1901) == (
        f"{full}; utilisation curve: {evc}; warning: {evc}; evidence gate: {gc}; interval: {ic}")
    note = "pressure_nominal_pa and trail_pressure_coeff: the car's and its tyre's (not fitted)"
    assert study._source(f"{iv}; {note}", ("warning",), "--warning-only", 1901) == (
        f"{full}; utilisation curve: {evc}; warning: {wc}; interval: {ic}; {note}")  # (a note it does not know: kept)


def test_the_pressure_terms_are_the_cars_and_its_tyres():
    """The shipped pressure terms are the car's pressure and its tyre file's, not fitted: at the calibration's
    pressure the tyre's own knots are the calibration's and its peak ratio 1; a harder tyre's trail is shorter in
    every slip state and its knots still ascend."""
    from sim.params import car_parameters

    t = study.pressure_terms(car_parameters())
    assert (t["pressure_nominal_pa"], t["trail_pressure_coeff"]) == (220000.0, 0.8521928)
    shipped = study.grip.load_params()
    for k, v in t.items():
        np.testing.assert_allclose(np.array(getattr(shipped, k), float), np.array(v, float), rtol=0, atol=1e-9)
    grid, rows = t["pressure_grid_pa"], t["trail_at_pressure"]
    i0 = grid.index(220000.0)
    assert rows[i0] == pytest.approx(shipped.trail_m, abs=1e-6) and t["peak_at_pressure"][i0] == 1.0
    for lo, hi in zip(rows, rows[1:], strict=False):
        assert all(b > a for a, b in zip(hi, hi[1:], strict=False))
        assert all(b <= a for a, b in zip(lo[6:], hi[6:], strict=False))  # (from the collapsed trail, 0 m, up; the
    assert all(b < a for a, b in zip(rows[0][6:], rows[-1][6:], strict=False))  # tyre file holds below its range)


def _fake_measure(monkeypatch, table: dict, field: str) -> None:
    """The study's ``measure`` replaced: figures ``(false per 10 min, median lead, share warned)`` by the value of the
    calibration's ``field``, the same for every run and for the acceptance's driving."""
    def measure(runs, q):
        false, lead, warned = table[getattr(q, field)]
        o = {"false_warnings_per_10min": false, "warning_lead_s_median": lead, "limit_warned_share": warned}
        return {"overall": o, "acceptance": o}
    monkeypatch.setattr(study, "measure", measure)


def test_the_evidence_gate_is_the_longest_lead_within_the_false_warning_limit(monkeypatch):
    """The fit of the evidence's longitudinal-force gate: the longest median lead first, then the most limits warned,
    among the gates within FALSE_BUDGET (or the warning's own false warnings without the gate, where more: a wide
    gate already in the calibration cannot justify itself); the narrower gate at a tie; a gate over the limit is not
    taken however long its lead; none qualifying keeps the calibration as it is."""
    figures = {0.0: (0.1, 0.1, 0.7), 0.25: (0.1, 0.1, 0.8), 0.35: (0.1, 0.1, 0.8), 0.5: (3.0, 0.5, 1.0)}

    def use(table: dict) -> None:
        _fake_measure(monkeypatch, table, "evidence_long_ratio")

    def gate(start: float) -> float:
        return study.fit_evidence_gate([], replace(grip.load_params(), evidence_long_ratio=start)).evidence_long_ratio

    use(figures)
    assert gate(0.0) == 0.25  # (more warned at the same lead; 0.35 ties it: the narrower)
    assert gate(0.5) == 0.25  # (the wide gate's own false warnings do not raise the limit)
    use({**figures, 0.25: (0.6, 0.4, 0.9), 0.0: (0.7, 0.1, 0.7)})
    assert gate(0.0) == 0.25  # (over the budget, but within the warning's own 0.7 without the gate)
    use({**figures, 0.25: (0.6, 0.4, 0.9)})
    assert gate(0.0) == 0.35
    use({**figures, 0.25: (0.1, 0.3, 0.75), 0.35: (0.1, 0.2, 0.9)})
    assert gate(0.0) == 0.25  # (the longer lead before the more warned)
    use({0.0: (0.1, 0.1, 0.7), **{g: (0.9, 0.5, 1.0) for g in (0.25, 0.35, 0.5)}})
    assert gate(0.0) == 0.0
    use({g: (0.9, 0.1, 0.7) for g in (0.0, 0.25, 0.35, 0.5)})  # (the limit is then the warning's own 0.9)
    assert gate(0.5) == 0.0
    monkeypatch.setattr(study, "EVIDENCE_LONG_RATIO", (0.25,))  # (a grid without 0, every gate over the limit)
    use({0.0: (0.1, 0.1, 0.7), 0.25: (0.9, 0.5, 1.0)})
    assert gate(0.35) == 0.35


def test_the_warning_fit_ends_with_the_evidence_gate(monkeypatch):
    """Every warning fit chooses the evidence gate last, with the warning it chose and the same false-warning count."""
    seen = []
    monkeypatch.setattr(study, "_load_transfer", lambda runs: 0.3)
    monkeypatch.setattr(study, "measure", lambda runs, q: {o: {"false_warnings_per_10min": 0.1,
                                                               "warning_lead_s_median": 0.1, "limit_warned_share": 0.5}
                                                           for o in ("overall", "acceptance")})
    monkeypatch.setattr(study, "WARN_ON", (0.75,))
    monkeypatch.setattr(study, "DEMAND_WEIGHT", (0.0,))
    monkeypatch.setattr(study, "EVIDENCE_MU_HELD", (0.0,))
    monkeypatch.setattr(study, "KAPPA_LIMIT", (0.05,))

    def gate(runs, p, false_on="all"):
        seen.append((p.warn_on, false_on))
        return replace(p, evidence_long_ratio=0.35)

    monkeypatch.setattr(study, "fit_evidence_gate", gate)
    p = study._fit_warning([], grip.load_params(), "acceptance")
    assert seen == [(0.75, "acceptance")] and p.evidence_long_ratio == 0.35


def test_the_warning_fit_breaks_a_tie_of_lead_and_limits_warned_by_fewer_false_warnings(monkeypatch):
    """Two settings with the same median lead and share of limits warned: the one with fewer false warnings is taken,
    whatever the grid's order; a longer lead within the budget still wins over fewer false warnings."""
    monkeypatch.setattr(study, "_load_transfer", lambda runs: 0.3)
    monkeypatch.setattr(study, "WARN_ON", (0.7,))
    monkeypatch.setattr(study, "DEMAND_LEAD_S", (0.0,))
    monkeypatch.setattr(study, "DEMAND_MU_HELD", (0.0,))
    monkeypatch.setattr(study, "EVIDENCE_MU_HELD", (0.0,))
    monkeypatch.setattr(study, "KAPPA_LIMIT", (0.05,))
    monkeypatch.setattr(study, "fit_evidence_gate", lambda runs, p, false_on="all": p)

    def use(table: dict) -> float:
        _fake_measure(monkeypatch, table, "demand_weight")
        monkeypatch.setattr(study, "DEMAND_WEIGHT", tuple(table))
        return study._fit_warning([], grip.load_params()).demand_weight

    assert use({0.9: (0.33, 0.35, 0.78), 0.8: (0.27, 0.35, 0.78)}) == 0.8
    assert use({0.9: (0.33, 0.35000000000000053, 0.78), 0.8: (0.27, 0.34999999999999964, 0.78)}) == 0.8  # (the
    # same lead, differences of 20 Hz tick times rounded differently)
    assert use({0.8: (0.27, 0.35, 0.78), 0.9: (0.33, 0.35, 0.78)}) == 0.8
    assert use({0.8: (0.27, 0.35, 0.78), 0.9: (0.45, 0.40, 0.78)}) == 0.9  # (longer lead within the budget)
    assert use({0.8: (0.27, 0.35, 0.78), 0.9: (0.60, 0.40, 0.78)}) == 0.8  # (over the budget)


def test_combined_bias_bands_the_curve_error_by_longitudinal_force_and_direction():
    """Each sample counts in its band of |Fx| / Fz and its direction only; the figures are the curve minus the truth
    (median, 90th percentile) and the share reading the threshold while the truth is calm; an empty band is null."""
    rows = np.array([[0.2, 1.0, 0.8, 0.6], [0.2, 1.0, 0.7, 0.7], [0.2, 1.0, 0.6, 0.9],  # drive, 0.15-0.25
                     [0.3, -1.0, 0.5, 0.9]])  # braking, 0.25-0.35
    res = {(r["band"], r["direction"]): r for r in study.combined_bias(rows)}
    d = res[("0.15-0.25", "drive")]
    assert d["n"] == 3 and d["median"] == pytest.approx(0.0) and d["false_share"] == pytest.approx(1 / 3)
    assert d["p90"] == pytest.approx(np.percentile([0.2, 0.0, -0.3], 90))
    b = res[("0.25-0.35", "braking")]
    assert b["n"] == 1 and b["median"] == pytest.approx(-0.4) and b["false_share"] == 0.0
    e = res[("0.35-0.50", "drive")]
    assert e["n"] == 0 and e["median"] is None and e["false_share"] is None
    assert sum(r["n"] for r in res.values()) == len(rows)
    assert "| 0.15-0.25 | drive | 3 |" in study.combined_md(study.combined_bias(rows), 1901)


def test_the_published_interval_is_the_worst_roads_not_the_pooled_one():
    """Per band and trail knot the 90th percentile of the error on the worst road: a small hard road is not
    drowned by a large easy one (the pooled percentile is), a road with fewer than 20 samples at a knot does not
    count there, and the curve never narrows at a longer trail."""
    rng = np.random.default_rng(3)
    k = np.asarray(study.TRAIL_KNOTS)
    t_easy, t_hard = np.repeat(k[4:8], 500), np.repeat(k[4:8], 60)
    err_easy, err_hard = rng.uniform(0, 0.02, len(t_easy)), rng.uniform(0, 0.3, len(t_hard))
    est = np.full(len(t_easy) + len(t_hard), 0.5)  # (one band: 0.35 .. 0.6)
    T = np.concatenate([t_easy, t_hard])
    MU = est - np.concatenate([err_easy, err_hard])
    grp = np.array(["circuits 0.45"] * len(t_easy) + ["paper 0.5"] * len(t_hard), dtype=object)
    # a third road: 40 well-read samples at a short trail, 5 far off at a longer one (too few there to count)
    T = np.concatenate([T, np.full(40, k[4]), np.full(5, k[10])])
    est = np.append(est, [0.5] * 45)
    MU = np.concatenate([MU, np.full(40, 0.5), np.full(5, 0.5 - 0.9)])
    grp = np.append(grp, ["paper 1"] * 45)
    iv = study._worst_road_interval(T, est, MU, grp)
    band = iv[1]
    for j in range(4, 8):
        hard = np.quantile(err_hard[t_hard == k[j]], 0.9)
        assert band[j] >= hard - 1e-4
        pooled = np.quantile(np.concatenate([err_easy, err_hard])[T[:len(err_easy) + len(err_hard)] == k[j]], 0.9)
        assert band[j] > pooled + 0.15
    assert np.all(np.diff(band) >= 0)
    assert max(band) < 0.9  # (the third road's 5 samples did not count)
    assert iv[0] == tuple([1.0] * len(k))  # (a band with no samples: never given)
