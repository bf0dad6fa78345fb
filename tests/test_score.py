"""``virtsensor score``: the shipped model file on recordings, its JSON, and its refusals."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from virtsensor.cli import main
from virtsensor.recordings.canlog import read_csv, write_csv

MODEL = Path(__file__).resolve().parent.parent / "models" / "improved.onnx"


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("runs")
    assert main(["simulate", "steering-pulse", "--speed", "50", "--mu", "1.0", "--seed", "1",
                 "--out", str(d / "pulse.csv")]) == 0
    assert main(["simulate", "single-sine", "--speed", "60", "--mu", "0.5", "--seed", "2",
                 "--out", str(d / "sine.blf")]) == 0
    return d


def test_score_json_per_run_and_overall(recordings: Path, tmp_path: Path) -> None:
    out, md = tmp_path / "score.json", tmp_path / "score.md"
    runs = [recordings / "pulse.csv", recordings / "sine.blf"]
    assert main(["score", "--model", str(MODEL), "--data", *map(str, runs), "--json", str(out),
                 "--markdown", str(md)]) == 0
    res = json.loads(out.read_text())
    overall = res["overall"]
    for key in ("r2", "mae_nm", "fl", "fr", "axle", "n"):
        assert key in overall
    assert overall["r2"] == pytest.approx(0.5 * (overall["fl"]["r2"] + overall["fr"]["r2"]))
    assert overall["mae_nm"] == pytest.approx(0.5 * (overall["fl"]["mae_nm"] + overall["fr"]["mae_nm"]))
    assert [r["file"] for r in res["runs"]] == [str(p) for p in runs]
    assert sum(r["n"] for r in res["runs"]) == overall["n"] > 200
    for r in res["runs"]:
        assert 0.0 < r["mae_nm"] < 20.0 and r["r2"] <= 1.0
    assert res["model"]["sha256"] == json.loads(MODEL.with_name("improved.card.json").read_text())["sha256"]
    assert "pulse.csv" in md.read_text() and "all runs" in md.read_text()


def test_scores_match_the_trainers_metrics_and_the_model_file(recordings: Path, tmp_path: Path) -> None:
    """score gives scikit-learn's R2 and MAE of the model file's own predictions."""
    from sklearn.metrics import mean_absolute_error, r2_score

    from virtsensor.features import FeatureSpec
    from virtsensor.learning.dataset import build_dataset, load_runs
    from virtsensor.model.onnx import OnnxModel

    def metrics(Y, P):
        wheels = {w: {"r2": r2_score(Y[:, j], P[:, j]), "mae_nm": mean_absolute_error(Y[:, j], P[:, j])}
                  for j, w in enumerate(("fl", "fr"))}
        axle = {"r2": r2_score(Y.sum(1), P.sum(1)), "mae_nm": mean_absolute_error(Y.sum(1), P.sum(1))}
        return {**wheels, "axle": axle, "n": len(Y), **{k: (wheels["fl"][k] + wheels["fr"][k]) / 2
                                                        for k in ("r2", "mae_nm")}}

    out = tmp_path / "score.json"
    assert main(["score", "--model", str(MODEL), "--data", str(recordings / "pulse.csv"), "--json", str(out)]) == 0
    res = json.loads(out.read_text())["overall"]
    model = OnnxModel.load(MODEL)
    ds = build_dataset(load_runs([recordings / "pulse.csv"]), FeatureSpec.from_json(model.card["feature_spec"]))
    ref = metrics(ds.Y, model.predict(ds.X))
    for key in ("r2", "mae_nm"):
        assert res[key] == pytest.approx(ref[key], rel=1e-9)
        assert res["axle"][key] == pytest.approx(ref["axle"][key], rel=1e-9)
        assert res["fl"][key] == pytest.approx(ref["fl"][key], rel=1e-9)
    assert res["n"] == ref["n"]


def test_score_runs_on_the_base_install(recordings: Path, tmp_path: Path) -> None:
    """No extra is imported: scikit-learn, scipy and the rest of the training stack are blocked; without
    ``--model`` the shipped improved model is scored."""
    out = tmp_path / "score.json"
    blocked = ("sklearn", "skl2onnx", "scipy", "joblib", "tqdm", "threadpoolctl", "shap", "matplotlib")
    code = (
        "import sys\n"
        f"for name in {blocked!r}:\n"
        "    sys.modules[name] = None\n"
        "from virtsensor.cli import main\n"
        f"sys.exit(main(['score', '--data', {str(recordings / 'pulse.csv')!r}, "
        f"{str(recordings / 'sine.blf')!r}, '--json', {str(out)!r}]))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(out.read_text())
    assert len(res["runs"]) == 2
    assert res["model"]["sha256"] == json.loads(MODEL.with_name("improved.card.json").read_text())["sha256"]


def _refused(argv: list[str], capsys, fragment: str, out: Path) -> None:
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and fragment in err, err
    assert not out.exists()


def test_refuses_a_missing_model(recordings: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "s.json"
    _refused(["score", "--model", str(tmp_path / "none.onnx"), "--data", str(recordings / "pulse.csv"),
              "--json", str(out)], capsys, "none", out)


def test_refuses_a_recording_without_the_reference_sats(recordings: Path, tmp_path: Path, capsys) -> None:
    table = read_csv(recordings / "pulse.csv")
    del table["sat_fr_nm"]
    bad = tmp_path / "no_sat.csv"
    write_csv(bad, table)
    out = tmp_path / "s.json"
    _refused(["score", "--model", str(MODEL), "--data", str(bad), "--json", str(out)], capsys, "sat_fr_nm", out)


def test_refuses_a_recording_with_no_finite_sample(recordings: Path, tmp_path: Path, capsys) -> None:
    table = read_csv(recordings / "pulse.csv")
    table["sat_fl_nm"] = np.full_like(table["sat_fl_nm"], np.nan)
    bad = tmp_path / "nan.csv"
    write_csv(bad, table)
    out = tmp_path / "s.json"
    _refused(["score", "--model", str(MODEL), "--data", str(bad), "--json", str(out)], capsys, "finite", out)


def test_refuses_missing_data_and_output_directory(recordings: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "s.json"
    _refused(["score", "--model", str(MODEL), "--data", str(tmp_path / "nothing.csv"), "--json", str(out)],
             capsys, "no such file", out)
    out2 = tmp_path / "missing_dir" / "s.json"
    _refused(["score", "--model", str(MODEL), "--data", str(recordings / "pulse.csv"), "--json", str(out2)],
             capsys, "does not exist", out2)


def test_refuses_a_model_whose_card_does_not_match(recordings: Path, tmp_path: Path, capsys) -> None:
    onnx = tmp_path / "m.onnx"
    onnx.write_bytes(MODEL.read_bytes() + b"x")
    (tmp_path / "m.card.json").write_text(MODEL.with_name("improved.card.json").read_text())
    out = tmp_path / "s.json"
    _refused(["score", "--model", str(onnx), "--data", str(recordings / "pulse.csv"), "--json", str(out)],
             capsys, "sha256", out)


def test_refuses_an_empty_trc_log_in_one_line(tmp_path: Path, capsys, caplog) -> None:
    """(python-can's TRC reader warned about the empty file on stderr, a second line; pytest holds such log
    records in caplog instead)"""
    empty = tmp_path / "empty.trc"
    empty.write_bytes(b"")
    out = tmp_path / "s.json"
    _refused(["score", "--model", str(MODEL), "--data", str(empty), "--json", str(out)], capsys, "empty.trc", out)
    assert "TRCReader" not in caplog.text


def test_a_card_without_a_usable_feature_spec_is_named():
    from virtsensor.errors import UserError
    from virtsensor.learning.scoring import needed_signals
    from virtsensor.model.card import ModelCard

    with pytest.raises(UserError, match=r"^x\.card\.json: model card has no usable feature_spec \('name'\)$"):
        needed_signals(ModelCard({"feature_spec": {"x": 1}}, path="x.card.json"))
    with pytest.raises(UserError, match=r"^model card has no usable feature_spec "):  # (a card built in memory)
        needed_signals({"feature_spec": 3})
