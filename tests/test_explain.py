"""``virtsensor explain``: Section IV.B figures and SHAP importance of the shipped ONNX model.

A tiny synthetic data set whose front-left SAT is a known function of the inputs
in which one input dominates (``sat_fl = 30 * assist_torque + 2 * ay``); a model
trained on it with the CLI must be explained with that input first.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from virtsensor import signals as cat
from virtsensor.cli import main
from virtsensor.recordings.canlog import write_csv

pytest.importorskip("shap")
pytest.importorskip("matplotlib")

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
DOMINANT = "assist_torque_nm"
ALL_FIGURES = ("fig2_correlation.png", "fig8_shap_importance.png", "fig9_shap_dependence.png",
               "fig5_track_dry.png", "fig6_track_wet.png", "fig7_axle_total.png")


def _table(rng: np.random.Generator, n: int, t0: float = 0.0) -> dict[str, np.ndarray]:
    """A 20 Hz table of independent, smooth-ish inputs and SATs that are a known function of them."""
    t = t0 + np.arange(n) / cat.TABLE_RATE_HZ
    table: dict[str, np.ndarray] = {"time_s": t}
    for name in cat.INPUTS:
        s = cat.SIGNALS[name]
        span = 0.2 * (s.maximum - s.minimum) / 2
        centre = 0.5 * (s.maximum + s.minimum)
        walk = np.cumsum(rng.normal(size=n))
        walk = (walk - walk.mean()) / (walk.std() + 1e-12)
        table[name] = centre + span * 0.3 * (walk + rng.normal(size=n))
    a = table[DOMINANT] / 20.0  # about unit scale
    ay = table["ay_mps2"] / 4.0
    table["sat_fl_nm"] = 30.0 * a + 2.0 * ay
    table["sat_fr_nm"] = 25.0 * a - 3.0 * ay
    return table


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("explain")
    data = root / "data"
    data.mkdir()
    rng = np.random.default_rng(7)
    for i in range(4):
        write_csv(data / f"run{i}.csv", _table(rng, 300))
    track = _table(rng, 400)
    track["road_mu"] = np.where(np.arange(400) < 200, 1.0, 0.7)  # dry lap, then wet lap
    write_csv(root / "track.csv", track)
    model = root / "tiny.onnx"
    assert main(["train", "--data", str(data), "--out", str(model), "--quiet"]) == 0
    return root, data, model


def _explain(setup, out, *extra):
    root, data, model = setup
    return main(["explain", "--model", str(model), "--data", str(data), "--track", str(root / "track.csv"),
                 "--out", str(out), "--samples", "60", "--background", "30", "--quiet", *extra])


@pytest.mark.slow
def test_figures_json_ranking_and_reproducibility(setup, tmp_path, capsys):
    out1, out2 = tmp_path / "a" / "figs", tmp_path / "b"
    assert _explain(setup, out1, "--seed", "3") == 0  # nested directory is created
    for name in ALL_FIGURES:
        blob = (out1 / name).read_bytes()
        assert blob[:8] == PNG_MAGIC, name
        assert len(blob) > 10_000, name  # a real picture, not an empty canvas
    doc = json.loads((out1 / "explain.json").read_text())
    assert doc["figures"] == list(ALL_FIGURES)
    assert doc["ranking"]["sat_fl_nm"][0] == DOMINANT
    assert doc["ranking"]["sat_fr_nm"][0] == DOMINANT
    imp = doc["mean_abs_shap_nm"]["sat_fl_nm"]
    assert set(imp) == set(cat.INPUTS)
    assert imp[DOMINANT] > 5 * sorted(imp.values())[-2]
    assert doc["ranking"]["sat_fl_nm"] == sorted(imp, key=lambda f: -imp[f])
    shap_info = doc["shap"]
    assert shap_info["method"] == "exact" and shap_info["exact"] is True  # 12 features, 60 rows: affordable
    assert shap_info["explained_rows"] == 60
    assert shap_info["additivity_max_abs_nm"] < 1e-6  # values add up to prediction - base value
    assert set(doc["track"]) == {"dry", "wet"}
    corr = np.array(doc["correlation"]["pearson"])
    assert corr.shape == (14, 14) and np.allclose(np.diag(corr), 1.0)
    assert DOMINANT in capsys.readouterr().out

    # same seed -> the same numbers, byte for byte (no timings in the file)
    assert _explain(setup, out2, "--seed", "3") == 0
    assert (out2 / "explain.json").read_text() == (out1 / "explain.json").read_text()


@pytest.mark.slow
def test_permutation_explainer_is_seeded(setup, tmp_path):
    root, data, model = setup
    docs = []
    for sub, seed in (("a", "1"), ("b", "1"), ("c", "2")):
        out = tmp_path / sub
        assert main(["explain", "--model", str(model), "--data", str(data), "--out", str(out), "--samples", "20",
                     "--background", "20", "--method", "permutation", "--seed", seed, "--quiet"]) == 0
        docs.append(json.loads((out / "explain.json").read_text()))
        assert not (out / "fig5_track_dry.png").exists()  # no --track, no track figures
    assert docs[0]["shap"]["method"] == "permutation" and docs[0]["shap"]["antithetic_permutations"] >= 10
    assert docs[0]["mean_abs_shap_nm"] == docs[1]["mean_abs_shap_nm"]
    assert docs[0]["mean_abs_shap_nm"] != docs[2]["mean_abs_shap_nm"]  # another seed: other rows
    assert docs[0]["ranking"]["sat_fl_nm"][0] == DOMINANT
    se = docs[0]["mean_abs_shap_stderr_nm"]["sat_fl_nm"][DOMINANT]
    assert 0 < se < docs[0]["mean_abs_shap_nm"]["sat_fl_nm"][DOMINANT]  # (a standard error, small against the mean)


def test_choose_method_budget():
    from virtsensor.learning.explain import MIN_PERMUTATIONS, choose_method

    assert choose_method(500, 12, 100) == ("exact", None)
    method, perms = choose_method(500, 20, 100)
    assert method == "permutation" and perms >= MIN_PERMUTATIONS
    assert choose_method(500, 20, 100, "exact") == ("exact", None)
    assert choose_method(10, 4, 10, "permutation")[0] == "permutation"


def test_errors_are_one_line_exit_2(setup, tmp_path, capsys, monkeypatch):
    root, data, model = setup
    base = ["explain", "--data", str(data), "--samples", "5", "--quiet"]
    # missing model
    assert main([*base, "--model", str(tmp_path / "nope.onnx"), "--out", str(tmp_path / "o1")]) == 2
    # data lacking a signal
    bad = tmp_path / "bad"
    bad.mkdir()
    table = _table(np.random.default_rng(0), 50)
    del table["ay_mps2"]
    write_csv(bad / "r.csv", table)
    assert main(["explain", "--data", str(bad), "--model", str(model), "--out", str(tmp_path / "o2"), "--quiet"]) == 2
    # output directory not creatable (its parent is a file)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main([*base, "--model", str(model), "--out", str(blocker / "sub")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("virtsensor explain: error:") for line in err)
    assert "ay_mps2" in err[1]
    # shap not installed
    monkeypatch.setitem(sys.modules, "shap", None)
    assert main([*base, "--model", str(model), "--out", str(tmp_path / "o3")]) == 2
    assert "pip install 'virtsensor[explain]'" in capsys.readouterr().err


def _tree(d):
    """Every entry under ``d`` (hidden ones too) with its bytes: what a failed run must leave unchanged."""
    return {str(p.relative_to(d)): (p.read_bytes() if p.is_file() else None) for p in sorted(d.rglob("*"))}


def test_a_bad_circuit_is_refused_before_any_figure(setup, tmp_path, capsys):
    """A circuit with missing rows (read last) is refused with nothing written: no new directory, an existing
    one unchanged."""
    root, data, model = setup
    gap = _table(np.random.default_rng(1), 120)
    keep = np.r_[0:50, 80:120]  # rows 51-80 deleted
    write_csv(tmp_path / "gap.csv", {k: v[keep] for k, v in gap.items()})
    old = tmp_path / "old"
    old.mkdir()
    (old / "fig2_correlation.png").write_bytes(b"previous figure")
    (old / "notes.txt").write_text("mine")
    before = _tree(tmp_path)
    for out in (tmp_path / "new", old):
        assert main(["explain", "--model", str(model), "--data", str(data), "--circuits", str(tmp_path / "gap.csv"),
                     "--out", str(out), "--samples", "5", "--background", "5", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("gap.csv" in line for line in err), err
    assert _tree(tmp_path) == before


@pytest.mark.parametrize("existing", [False, True])
def test_an_interrupt_leaves_the_output_as_it_was(setup, tmp_path, monkeypatch, capsys, existing):
    """Ctrl-C after the first figure: no new directory (nor staging one) is left, an existing one is unchanged;
    a complete run then replaces the old figures and leaves other files alone."""
    import virtsensor.learning.explain as ex

    root, data, model = setup
    out = tmp_path / "figs"
    if existing:
        out.mkdir()
        (out / "fig2_correlation.png").write_bytes(b"previous figure")
        (out / "notes.txt").write_text("mine")
    before = _tree(tmp_path)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(ex, "plot_importance", interrupted)
    argv = ["explain", "--model", str(model), "--data", str(data), "--out", str(out), "--samples", "5",
            "--background", "5", "--quiet"]
    assert main(argv) == 130
    assert _tree(tmp_path) == before
    monkeypatch.undo()
    assert main(argv) == 0
    assert (out / "fig2_correlation.png").read_bytes()[:8] == PNG_MAGIC
    assert not [p for p in tmp_path.rglob(".partial-*")]
    if existing:
        assert (out / "notes.txt").read_text() == "mine"


def test_a_full_disk_is_one_line_exit_1_and_leaves_nothing(setup, tmp_path, monkeypatch, capsys):
    """A figure that cannot be written (the disk full) is the machine's error, not the request's: exit 1, one line
    naming the output, no directory left."""
    import errno

    import virtsensor.learning.explain as ex

    root, data, model = setup

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", "fig1.png")

    monkeypatch.setattr(ex, "plot_importance", full)
    out = tmp_path / "figs"
    capsys.readouterr()
    assert main(["explain", "--model", str(model), "--data", str(data), "--out", str(out), "--samples", "5",
                 "--background", "5", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "No space left on device" in err and str(out) in err, err
    assert not out.exists() and not [p for p in tmp_path.rglob(".partial-*")]
