"""The model card: one type, sealed by a digest; tampered cards are refused by the loader and the commands."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from virtsensor import cli
from virtsensor import signals as cat
from virtsensor.errors import UserError
from virtsensor.features import PAPER
from virtsensor.model import ModelCard, OnnxModel, card_path_for
from virtsensor.model.card import DIGEST_KEY, canonical_bytes
from virtsensor.model.onnx import META_OUTPUTS

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "models" / "paper.onnx"


def _copy_shipped(tmp_path: Path, name: str = "paper") -> Path:
    dst = tmp_path / f"{name}.onnx"
    shutil.copyfile(ROOT / "models" / f"{name}.onnx", dst)
    shutil.copyfile(card_path_for(ROOT / "models" / f"{name}.onnx"), card_path_for(dst))
    return dst


def _edit(onnx_path: Path, change, *, reseal: bool = False) -> Path:
    """Apply ``change(dict)`` to the card beside ``onnx_path``; optionally recompute its digest (a careful forger)."""
    card_path = card_path_for(onnx_path)
    data = json.loads(card_path.read_text())
    change(data)
    if reseal:
        data[DIGEST_KEY] = ModelCard(data).digest()
    card_path.write_text(json.dumps(data, indent=2))
    return card_path


def _flip_first_critical(data: dict) -> None:
    entry = data["inputs"][0]
    entry["critical"] = not entry["critical"]


def _swap_outputs(data: dict) -> None:
    data["outputs"] = data["outputs"][::-1]


def _nudge_weight(data: dict) -> None:
    data["weights"]["layers"][-1]["b"][0] += 0.5  # 0.5 Nm on the front-left output


@pytest.mark.parametrize("name", ["paper", "improved"])
def test_shipped_cards_are_sealed_and_their_numpy_weights_match_the_graph(name):
    model = OnnxModel.load(ROOT / "models" / f"{name}.onnx")
    card = model.card
    assert isinstance(card, ModelCard) and card[DIGEST_KEY] == card.digest()
    assert model.numpy_forward is not None and len(card["parity_inputs"]) >= 8
    X = np.asarray(card["parity_inputs"])
    assert np.abs(model.numpy_forward(X) - model.predict(X)).max() < 1e-3
    assert model.input_names == card.feature_names and model.outputs == cat.OUTPUTS


def test_digest_is_over_canonical_content_not_formatting(tmp_path):
    onnx_path = _copy_shipped(tmp_path)
    card_path = card_path_for(onnx_path)
    data = json.loads(card_path.read_text())
    # reordered keys, other indentation: the same content, still accepted
    card_path.write_text(json.dumps(dict(reversed(list(data.items()))), indent=None))
    assert OnnxModel.load(onnx_path).card[DIGEST_KEY] == data[DIGEST_KEY]
    assert canonical_bytes(data) == canonical_bytes(dict(reversed(list(data.items()))))


@pytest.mark.parametrize("change", [_flip_first_critical, _swap_outputs, _nudge_weight,
                                    lambda d: d["inputs"][3].update(valid_range=[-1.0, 1.0]),
                                    lambda d: d.pop("parity_inputs")])
def test_an_edited_card_is_refused_naming_the_file(tmp_path, change):
    onnx_path = _copy_shipped(tmp_path)
    card_path = _edit(onnx_path, change)
    with pytest.raises(UserError, match="edited after export") as e:
        OnnxModel.load(onnx_path)
    assert str(card_path) in str(e.value) and "\n" not in str(e.value)


def test_a_card_without_digest_is_refused_with_the_remedy(tmp_path):
    onnx_path = _copy_shipped(tmp_path)
    _edit(onnx_path, lambda d: d.pop(DIGEST_KEY))
    with pytest.raises(UserError, match="no card_sha256.*seal_cards"):
        OnnxModel.load(onnx_path)


def test_resealed_card_with_other_weights_is_refused_by_the_graph_check(tmp_path):
    """A forger who recomputes the digest is still caught: the numpy weights must reproduce the ONNX."""
    onnx_path = _copy_shipped(tmp_path)
    card_path = _edit(onnx_path, _nudge_weight, reseal=True)
    with pytest.raises(UserError, match="weights differ from the ONNX graph") as e:
        OnnxModel.load(onnx_path)
    assert str(card_path) in str(e.value)
    _edit(onnx_path, lambda d: d.update(parity_inputs=[]), reseal=True)
    with pytest.raises(UserError, match="parity_inputs"):
        OnnxModel.load(onnx_path)


def test_resealed_swapped_outputs_are_refused_by_the_graph_metadata(tmp_path):
    """A fresh export names its columns in the ONNX metadata; a card that swaps them does not load."""
    from sklearn.linear_model import LinearRegression
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import RobustScaler

    from virtsensor.model.export import export_pipeline, pipeline_weights

    rng = np.random.default_rng(0)
    X = rng.normal(size=(200, len(PAPER.names)))
    Y = np.column_stack([X[:, 0] * 3, -X[:, 1]])
    pipe = Pipeline([("s", RobustScaler()), ("m", LinearRegression())]).fit(X, Y)
    path = tmp_path / "lin.onnx"
    card = export_pipeline(pipe, X.shape[1], path, parity_X=X, card_extra=ModelCard.trainer_fields(
        model="t", spec=PAPER, weights=pipeline_weights(pipe)))
    assert card["inputs"] == ModelCard.inputs_for(PAPER) and card[DIGEST_KEY] == card.digest()
    meta = OnnxModel.load(path).session.get_modelmeta().custom_metadata_map
    assert json.loads(meta[META_OUTPUTS]) == list(cat.OUTPUTS)
    _edit(path, _swap_outputs, reseal=True)
    with pytest.raises(UserError, match="differ from the ONNX graph"):
        OnnxModel.load(path)


def test_export_refuses_weights_that_are_not_the_pipelines(tmp_path):
    from sklearn.linear_model import LinearRegression
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import RobustScaler

    from virtsensor.model.export import export_pipeline, pipeline_weights

    X = np.random.default_rng(1).normal(size=(100, 12))
    Y = np.column_stack([X[:, 0], X[:, 1]])
    pipe = Pipeline([("s", RobustScaler()), ("m", LinearRegression())]).fit(X, Y)
    other = Pipeline([("s", RobustScaler()), ("m", LinearRegression())]).fit(X, Y[:, ::-1])
    with pytest.raises(ValueError, match="weights differ"):
        export_pipeline(pipe, 12, tmp_path / "x.onnx", parity_X=X, card_extra=ModelCard.trainer_fields(
            model="t", spec=PAPER, weights=pipeline_weights(other)))
    assert list(tmp_path.iterdir()) == []


def test_trainer_fields_are_the_one_definition_of_the_inputs():
    fields = ModelCard.trainer_fields(model="m", spec=PAPER, seed=3)
    assert [i["name"] for i in fields["inputs"]] == list(PAPER.names)
    assert all(isinstance(i["critical"], bool) and "valid_range" in i for i in fields["inputs"])
    assert fields["seed"] == 3 and "weights" not in fields and fields["signals"] == list(PAPER.signals)


def test_card_read_errors_name_the_file_and_never_quote_it(tmp_path):
    bad = tmp_path / "m.card.json"
    bad.write_bytes(b"SECRET-LINE\x00\xff")
    with pytest.raises(UserError) as e:
        ModelCard.read(bad)
    assert str(bad) in str(e.value) and "SECRET" not in str(e.value)
    bad.write_text('{\n "a": 1,\n SECRET\n}')
    with pytest.raises(UserError, match=r"m\.card\.json:3: model card is not valid JSON") as e:
        ModelCard.read(bad)
    assert "SECRET" not in str(e.value)
    bad.write_text("[1, 2]")
    with pytest.raises(UserError, match="JSON object"):
        ModelCard.read(bad)


def _spec_as_text(data: dict) -> None:
    data["feature_spec"] = "paper"


def _short_center(data: dict) -> None:
    data["weights"]["center"] = data["weights"]["center"][:-1]


@pytest.fixture(params=[(_flip_first_critical, False), (_swap_outputs, False), (_spec_as_text, True),
                        (_short_center, True)],
                ids=["critical-flag", "swapped-outputs", "resealed-spec-as-text", "resealed-short-center"])
def tampered(tmp_path, request) -> Path:
    change, reseal = request.param
    onnx_path = _copy_shipped(tmp_path)
    _edit(onnx_path, change, reseal=reseal)
    return onnx_path


@pytest.mark.parametrize(("change", "needle"), [
    (_spec_as_text, "feature_spec: expected an object with 'name', 'tick_s' and 'features'"),
    (lambda d: d["feature_spec"]["features"].pop(), "feature_spec: its features"),
    (lambda d: d["feature_spec"]["features"][0].update(op="square"), "feature_spec: not a usable feature spec"),
    (_short_center, "weights.center: expected 12 finite numbers (one per feature)"),
    (lambda d: d["weights"].update(scale=[0.0] * 12), "weights.scale: expected non-zero numbers"),
    (lambda d: d["weights"].update(layers="none"), "weights.layers: expected a non-empty list"),
    (lambda d: d["weights"]["layers"][0]["W"].pop(), "weights.layers[0].W: expected 12 rows"),
    (lambda d: d["weights"]["layers"][-1]["b"].pop(), "weights.layers[2].b: expected 2 finite numbers"),
    (lambda d: d["weights"].update(activation="softmax"), "weights.activation: expected one of identity"),
    (lambda d: d.update(parity_inputs=[[0.0] * 11]), "parity_inputs: expected rows of 12 finite numbers"),
    (lambda d: d.update(recipe="paper"), "recipe: expected an object with 'features'"),
    (lambda d: d.update(signals="ax_mps2"), "signals: expected a list of signal names, got str"),
    (lambda d: d.update(metrics=[1]), "metrics: expected a JSON object, got list"),
    (lambda d: d.update(onnx_input=3), "onnx_input: expected a string, got int"),
    (lambda d: d.update(fallback={"file": "x.onnx"}), "fallback: expected an object with file, sha256"),
])
def test_a_resealed_card_of_the_wrong_types_or_shapes_is_refused_naming_the_field(tmp_path, change, needle):
    """A card edited and sealed again with its own digest (as tools/seal_cards.py seals): its types and
    shapes are checked at load, one line naming the card and the field, before any loader reads them."""
    onnx_path = _copy_shipped(tmp_path)
    card_path = _edit(onnx_path, change, reseal=True)
    with pytest.raises(UserError) as e:
        ModelCard.read(card_path)
    msg = str(e.value)
    assert msg.startswith(f"{card_path}: ") and needle in msg and "\n" not in msg, msg


@pytest.mark.parametrize("argv", [
    ["run", "--model", "{m}", "--interface", "virtual", "--channel", "card-test", "--duration", "0.1"],
    ["bench", "--model", "{m}", "--quick", "--json", "{tmp}/b.json"],
    ["evaluate", "--model", "{m}", "--data", "{tmp}/data", "--json", "{tmp}/e.json"],
    ["score", "--model", "{m}", "--data", "{tmp}/data", "--json", "{tmp}/s.json"],
    ["explain", "--model", "{m}", "--data", "{tmp}/data", "--out", "{tmp}/fig"],
    ["demo", "--model", "{m}", "--no-live", "--rate", "max", "--plot", "{tmp}/d.png"],
])
def test_commands_refuse_a_tampered_card_with_exit_2(tampered, argv, capsys):
    tmp = tampered.parent
    (tmp / "data").mkdir()  # (the outputs go beside the data: never inside an input directory)
    args = [a.format(m=tampered, tmp=tmp) for a in argv]
    before = sorted(p.name for p in tmp.iterdir())
    rc = cli.main(args)
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and str(card_path_for(tampered)) in lines[0] and "Traceback" not in err
    assert sorted(p.name for p in tmp.iterdir()) == before  # nothing written


def test_model_package_imports_no_training_stack():
    code = ("import sys, virtsensor.model, virtsensor.model.onnx, virtsensor.model.card; "
            "print(sorted(m for m in ('sklearn', 'skl2onnx', 'onnx', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_export_output_is_a_model_card(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from runtime_support import synthetic_streams, train_model
    from virtsensor.recordings.canlog import simulated_recording

    table = simulated_recording(*synthetic_streams(6.0, seed=2)).table
    card = train_model([table], tmp_path / "t.onnx", spec=PAPER, max_iter=5)
    assert isinstance(card, ModelCard) and card.path == card_path_for(tmp_path / "t.onnx")
    assert ModelCard.read(card.path) == card
