"""tools/diagnose_study.py: how a case's answer is scored against what was hidden (no case is simulated)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("diagnose_study", ROOT / "tools" / "diagnose_study.py")
study = importlib.util.module_from_spec(_spec)
sys.modules["diagnose_study"] = study
_spec.loader.exec_module(study)


def _mu(est: float, lo: float, hi: float) -> dict:
    return {"mu": {"estimate": est, "ci95": [lo, hi], "range": [0.2, 1.2], "excited": True}}


def test_per_run_friction_is_scored_against_the_run_of_the_same_name_when_a_run_was_left_out():
    """A mixed day whose fourth run (the wet sine with dwell) spun and was left out by the loader: the
    diagnosis answers for four runs, and its fourth answer is the fifth run's (a dry double lane change).
    Paired by position it would be scored against the wet run's friction (and miss); by name it is the dry
    run's, and the wet run is not scored."""
    from virtsensor.diagnose.hidden import Case

    paths = [Path(f"day/run{i:02d}.csv") for i in range(1, 6)]
    case = Case(hidden=None, diagnosis=paths, holdout=[], mu=[1.0, 0.7, 0.3, 0.6, 0.95])
    answers = [(1.01, 0.95, 1.07), (0.71, 0.66, 0.76), (0.31, 0.27, 0.35), (0.97, 0.91, 1.02)]
    kept = [p.stem for i, p in enumerate(paths) if i != 3]
    res = {"cause": "none", "causes": [], "run_conditions": [
        {"name": name, "used": {}, "identified": _mu(*a)} for name, a in zip(kept, answers, strict=True)]}
    row = study.score_case({"case": 0, "kind": "control"}, 0, case, res, 0.0, 0.0)
    assert [m["run"] for m in row["mu"]] == kept
    assert [m["true"] for m in row["mu"]] == [1.0, 0.7, 0.3, 0.95]
    assert all(m["covered"] for m in row["mu"])
    assert row["right"]


def test_a_second_cause_that_was_not_hidden_is_counted_even_where_the_first_is_right():
    """A day with one hidden tyre pressure answered with the pressure and an assist-torque gain (diagnose study seed
    61000, case 0): scored right (the first cause), but it names a cause that is not there, which the engineer would
    change on the car for nothing; the row and the summary say so. A control answering `none` names nothing."""
    from sim.effects import Hidden
    from virtsensor.diagnose.hidden import Case

    hidden = Hidden("tyre_pressure", 1.73)
    case = Case(hidden=hidden, diagnosis=[], holdout=[], effects=[hidden], mu=[])
    res = {"cause": "tyre_pressure", "causes": [
        {"cause": "tyre_pressure", "signal": None, "estimate": 1.6, "ci95": [1.2, 1.8]},
        {"cause": "sensor_gain", "signal": "assist_torque_nm", "estimate": 1.05, "ci95": [1.02, 1.08]}]}
    row = study.score_case({"case": 0, "kind": "single"}, 0, case, res, 0.0, 0.0)
    assert row["right"] and row["not_there"] == [("sensor_gain", "assist_torque_nm")]
    control = study.score_case({"case": 1, "kind": "control"}, 0, Case(hidden=None, diagnosis=[], holdout=[], mu=[]),
                               {"cause": "none", "causes": []}, 0.0, 0.0)
    assert control["right"] and control["not_there"] == []
    row.update(seconds_diagnose=1.0)
    control.update(seconds_diagnose=1.0)
    assert study.figures([row, control])["named_not_there"] == (1, 2)
    md = study.summary([row, control])
    assert "names a cause that was not hidden" in md and "(names sensor_gain[assist_torque_nm], not there)" in md
