"""The model card: what an exported estimator is, in one JSON file beside its ONNX graph.

One :class:`ModelCard` type builds the trainer's part of a card (:meth:`ModelCard.trainer_fields`,
:meth:`ModelCard.inputs_for`), seals it with a digest (:meth:`ModelCard.sealed`), writes it
(:meth:`ModelCard.write`) and reads it back, validated (:meth:`ModelCard.read`), for ``train``,
``diagnose``, ``explain``, ``evaluate``, the daemon and the tests.

Integrity: a card carries ``sha256`` (of its ONNX file's bytes) and ``card_sha256``, the SHA-256 of
its own *canonical content*: every key except ``card_sha256``, serialised as UTF-8 JSON with the keys
sorted at every level, no insignificant whitespace (separators ``,`` and ``:``), non-ASCII characters
kept as they are, and numbers written as Python's :mod:`json` writes them (integers in decimal, floats
in their shortest round-trip form). Any edit of a loaded card (a flipped ``critical`` flag, swapped
``outputs``, changed weights) changes that digest, and :meth:`ModelCard.read` refuses the card.
A card re-sealed after an edit still has its types and shapes checked (:func:`check_fields`: a
``feature_spec`` that is a feature spec of the card's features, ``weights`` whose scaler and layers fit
its features and outputs, ``parity_inputs`` rows of its features...), so no loader meets a field it cannot
read. The ONNX side of the checks (sha256 of the graph, output names, the numpy weights against the graph)
is in :class:`virtsensor.model.onnx.OnnxModel`.

A card may state the validity envelope of its training rows (``envelope``,
:mod:`virtsensor.model.envelope`); it is covered by the digest, checked by :meth:`ModelCard.validate`
and read by :attr:`ModelCard.envelope`. Cards without one load as before and have no envelope check.

This module needs nothing beyond the base install (the daemon imports it).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from virtsensor.errors import UserError
from virtsensor.fileio import atomic_write_bytes, json_default, read_user_text
from virtsensor.model.envelope import Envelope

#: Card key holding the digest of the card's canonical content.
DIGEST_KEY = "card_sha256"
#: Keys every card has (the ONNX side and the digest); :meth:`ModelCard.validate` checks their types.
REQUIRED_KEYS = ("sha256", "feature_names", "n_features", "outputs", DIGEST_KEY)
_HEX64 = re.compile(r"[0-9a-f]{64}")


def card_path_for(onnx_path: str | os.PathLike[str]) -> Path:
    """The model-card path beside ``onnx_path``: ``models/sat.onnx`` -> ``models/sat.card.json``."""
    p = Path(onnx_path)
    return p.with_name(f"{p.stem if p.suffix == '.onnx' else p.name}.card.json")


def canonical_bytes(content: Mapping[str, Any]) -> bytes:
    """The canonical serialisation the digest is computed over (``card_sha256`` left out).

    Raises:
        ValueError: a value JSON cannot hold (NaN, infinity, a non-JSON type).
    """
    body = {k: v for k, v in content.items() if k != DIGEST_KEY}
    try:
        text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    except TypeError as exc:
        raise ValueError(f"model card content is not JSON: {exc}") from None
    return text.encode("utf-8")


class ModelCard(Mapping[str, Any]):
    """A model card: a read-only mapping of its JSON content, plus where it came from.

    Values are the parsed JSON objects themselves (dicts, lists, str, numbers): treat them as
    read-only; :meth:`to_dict` gives a private copy to modify.

    Attributes:
        path: the file it was read from or last written to (None for a card built in memory).
    """

    def __init__(self, content: Mapping[str, Any], *, path: str | os.PathLike[str] | None = None) -> None:
        # a JSON round trip: the card holds JSON values only, whatever the caller passed
        self._data: dict[str, Any] = json.loads(json.dumps(dict(content), allow_nan=False, default=json_default))
        self.path = None if path is None else Path(path)

    # -- Mapping ----------------------------------------------------------------------------------------------
    def __getitem__(self, key: str) -> Any:
        return self._data[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    def __repr__(self) -> str:
        where = f", path={str(self.path)!r}" if self.path else ""
        return f"ModelCard({self._data.get('model', '?')!r}, sha256={str(self._data.get('sha256', ''))[:12]}{where})"

    def to_dict(self) -> dict[str, Any]:
        """A deep copy of the content (a plain dict)."""
        return json.loads(json.dumps(self._data))

    # -- typed views ------------------------------------------------------------------------------------------
    @property
    def feature_names(self) -> tuple[str, ...]:
        """Ordered input feature names (the graph's input columns)."""
        return tuple(str(n) for n in self._data["feature_names"])

    @property
    def outputs(self) -> tuple[str, ...]:
        """Ordered output names (catalogue names, Nm): the graph's output columns."""
        return tuple(str(o["name"] if isinstance(o, Mapping) else o) for o in self._data["outputs"])

    @property
    def n_features(self) -> int:
        return int(self._data["n_features"])

    @property
    def envelope(self) -> Envelope | None:
        """The validity envelope of the training rows (:mod:`virtsensor.model.envelope`); None when the card
        states none (cards written before envelopes existed): then nothing is checked against one."""
        doc = self._data.get("envelope")
        return None if doc is None else Envelope.from_json(doc, self._where())

    # -- digest -----------------------------------------------------------------------------------------------
    def digest(self) -> str:
        """SHA-256 (hex) of the canonical content (see the module docstring)."""
        return hashlib.sha256(canonical_bytes(self._data)).hexdigest()

    def sealed(self) -> ModelCard:
        """A copy carrying ``card_sha256`` = :meth:`digest` (after :meth:`validate` of everything else)."""
        data = self.to_dict()
        data[DIGEST_KEY] = self.digest()
        card = ModelCard(data, path=self.path)
        card.validate()
        return card

    def verify(self) -> None:
        """Raise :class:`UserError` naming the file unless the card is valid and its digest matches."""
        self.validate()
        got = self.digest()
        if got != self._data[DIGEST_KEY]:
            raise UserError(f"{self._where()}: model card content has sha256 {got}, its card_sha256 says "
                            f"{self._data[DIGEST_KEY]}: the card was edited after export; refusing it "
                            "(re-export the model, or restore the card)")

    def validate(self) -> None:
        """Check the card's structure (not its digest).

        Raises:
            UserError: a required key missing or of the wrong type, feature names and ``inputs``
                disagreeing, non-boolean ``critical`` flags, duplicate names, an optional field of the
                wrong type or shape (:func:`check_fields`); the message names the file and the field.
        """
        where, d = self._where(), self._data
        missing = [k for k in REQUIRED_KEYS if k not in d]
        if missing:
            hint = (" (written before cards carried a digest: re-export it, or run tools/seal_cards.py)"
                    if missing == [DIGEST_KEY] else "")
            raise UserError(f"{where}: not a valid model card: no {', '.join(missing)}{hint}")
        for key in ("sha256", DIGEST_KEY):
            if not isinstance(d[key], str) or not _HEX64.fullmatch(d[key]):
                raise UserError(f"{where}: {key} must be 64 lower-case hex digits")
        names, n = d["feature_names"], d["n_features"]
        if (not isinstance(names, list) or not all(isinstance(x, str) for x in names) or isinstance(n, bool)
                or not isinstance(n, int) or len(names) != n or len(set(names)) != n or n < 1):
            raise UserError(f"{where}: feature_names must be {n!r} distinct names (n_features)")
        outs = d["outputs"]
        if (not isinstance(outs, list) or not outs
                or not all(isinstance(o, str) or (isinstance(o, dict) and isinstance(o.get("name"), str))
                           for o in outs)):
            raise UserError(f"{where}: outputs must be a non-empty list of names or {{'name': ...}} entries")
        if len(set(self.outputs)) != len(outs) or d.get("n_outputs", len(outs)) != len(outs):
            raise UserError(f"{where}: outputs {list(self.outputs)} are not distinct or disagree with n_outputs")
        self._validate_inputs(where)
        check_fields(d, where, self.feature_names, len(outs))
        if self._data.get("envelope") is not None:
            env = Envelope.from_json(self._data["envelope"], where)
            stray = sorted(set(env.signals) - set(self._data.get("signals") or env.signals))
            if stray:
                raise UserError(f"{where}: envelope bounds {', '.join(stray)}, which the model does not read")

    def _validate_inputs(self, where: str) -> None:
        inputs = self._data.get("inputs")
        if inputs is None:
            return
        if not isinstance(inputs, list) or len(inputs) != self.n_features:
            raise UserError(f"{where}: inputs must list the {self.n_features} features")
        got = [i if isinstance(i, str) else i.get("name") if isinstance(i, dict) else None for i in inputs]
        if got != list(self.feature_names):
            raise UserError(f"{where}: inputs {got} are not feature_names {list(self.feature_names)} in order")
        for i in inputs:
            if isinstance(i, dict) and "critical" in i and not isinstance(i["critical"], bool):
                raise UserError(f"{where}: input {i['name']}: critical must be true or false")

    def _where(self) -> str:
        return str(self.path) if self.path is not None else "model card"

    # -- files ------------------------------------------------------------------------------------------------
    def text(self) -> str:
        """The card as written to disk: indented JSON, keys in insertion order, a final newline."""
        return json.dumps(self._data, indent=2, ensure_ascii=False, allow_nan=False) + "\n"

    def write(self, path: str | os.PathLike[str]) -> None:
        """Write the card to ``path`` atomically (the card must be sealed and valid)."""
        self.verify()
        atomic_write_bytes(Path(path), self.text().encode("utf-8"))
        self.path = Path(path)

    @classmethod
    def read(cls, path: str | os.PathLike[str], *, verify: bool = True) -> ModelCard:
        """Read and check a card file.

        Args:
            path: the ``.card.json`` file.
            verify: check the structure and the digest (default); False only for migration tools.

        Raises:
            UserError: unreadable file, invalid JSON (with its line), not an object, invalid structure,
                or a digest mismatch; the message names ``path`` and never quotes the file's content.
        """
        path = Path(path)
        text = read_user_text(path, "model card")
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise UserError(f"{path}:{exc.lineno}: model card is not valid JSON: {exc.msg}") from None
        except RecursionError:
            raise UserError(f"{path}: model card is nested too deeply") from None
        if not isinstance(data, dict):
            raise UserError(f"{path}: not a model card (a JSON object is expected)")
        try:
            card = cls(data, path=path)
        except ValueError:
            raise UserError(f"{path}: model card holds NaN or infinite numbers") from None
        if verify:
            card.verify()
        return card

    # -- what the trainer writes ------------------------------------------------------------------------------
    @staticmethod
    def inputs_for(spec: Any) -> list[dict[str, Any]]:
        """The card's ``inputs``: one entry per feature of ``spec`` (a :class:`~virtsensor.features.FeatureSpec`).

        Each entry: name, catalogue signal, op (value/lag/rate/accel), lag (ticks), unit, DBC message
        and signal, the catalogue's ``critical`` flag, and ``valid_range`` (the catalogue's physical
        range, for value and lag features; None for derived rates).
        """
        from virtsensor import signals as cat

        out = []
        for f in spec.features:
            s = cat.SIGNALS[f.signal]
            out.append({
                "name": f.name, "signal": f.signal, "op": f.op, "lag": f.lag, "unit": f.unit,
                "dbc_message": s.message, "dbc_signal": s.dbc_signal, "critical": s.critical,
                "valid_range": [s.minimum, s.maximum] if f.op in ("value", "lag") else None,
            })
        return out

    @classmethod
    def trainer_fields(cls, *, model: str, spec: Any, recipe: Mapping[str, Any] | None = None,
                       training_data: Mapping[str, Any] | None = None, metrics: Mapping[str, Any] | None = None,
                       seed: int | None = None, weights: Mapping[str, Any] | None = None,
                       envelope: Envelope | None = None) -> dict[str, Any]:
        """What the trainer knows, as the ``card_extra`` of :func:`virtsensor.model.export.export_pipeline`.

        Args:
            model: the model's name, e.g. ``virtsensor-improved``.
            spec: the :class:`~virtsensor.features.FeatureSpec` the model reads.
            recipe, training_data, metrics, seed: recorded as given (omitted when None).
            weights: the pipeline's plain weights (:func:`virtsensor.model.export.pipeline_weights`),
                for the numpy back-end; checked against the graph at export and at every load.
            envelope: the validity envelope of the training rows (:meth:`Envelope.fit`), as ``envelope``.
        """
        fields: dict[str, Any] = {"model": model}
        if recipe is not None:
            fields["recipe"] = dict(recipe)
        fields.update(feature_spec=spec.to_json(), inputs=cls.inputs_for(spec), signals=list(spec.signals))
        for key, value in (("training_data", training_data), ("metrics", metrics), ("seed", seed),
                           ("weights", weights)):
            if value is not None:
                fields[key] = value
        if envelope is not None:
            fields["envelope"] = envelope.to_json()
        return fields


#: activations the numpy back-end computes (:class:`virtsensor.model.onnx.NumpyForward`)
ACTIVATIONS = ("identity", "tanh", "relu", "logistic")
#: optional keys that hold a JSON object, a string, a list of strings
_OBJECT_KEYS = ("training_data", "metrics", "opset", "target_opset", "tool_versions")
_STRING_KEYS = ("model", "onnx_file", "onnx_input", "onnx_output", "created_utc")


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _numbers(value: Any, n: int | None = None) -> bool:
    """Whether ``value`` is a list of finite numbers (of length ``n`` when given)."""
    return isinstance(value, list) and all(_is_number(x) for x in value) and (n is None or len(value) == n)


def _matrix(value: Any) -> tuple[int, int] | None:
    """The (rows, columns) of a non-empty list of equally long, non-empty rows of finite numbers; None if not."""
    if not isinstance(value, list) or not value or not all(_numbers(r) and r for r in value):
        return None
    width = len(value[0])
    return (len(value), width) if all(len(r) == width for r in value) else None


def check_fields(d: Mapping[str, Any], where: str, feature_names: tuple[str, ...], n_outputs: int) -> None:
    """The types and shapes of a card's optional fields that loaders read, when present: ``feature_spec``
    (a feature spec whose names are ``feature_names``), ``weights`` (scaler of one entry per feature, layers
    chaining the features to the outputs), ``parity_inputs`` (rows of one finite number per feature),
    ``recipe``, ``signals``, ``fallback``, ``input_dtype`` and the keys of objects and strings.

    Raises:
        UserError: ``<where>: <field>: expected ..., got ...`` for the first field that is wrong.
    """
    def bad(field: str, expected: str, got: Any = None) -> UserError:
        shown = type(got).__name__ if got is not None else "something else"
        return UserError(f"{where}: {field}: expected {expected}, got {shown}")

    for key in _OBJECT_KEYS:
        if key in d and not isinstance(d[key], dict):
            raise bad(key, "a JSON object", d[key])
    for key in _STRING_KEYS:
        if key in d and not isinstance(d[key], str):
            raise bad(key, "a string", d[key])
    if "input_dtype" in d and d["input_dtype"] not in ("float32", "float64"):
        raise UserError(f"{where}: input_dtype: expected float32 or float64, got {d['input_dtype']!r}")
    if "signals" in d and not (isinstance(d["signals"], list) and all(isinstance(x, str) for x in d["signals"])):
        raise bad("signals", "a list of signal names", d["signals"])
    recipe = d.get("recipe")
    if recipe is not None and not (isinstance(recipe, dict) and isinstance(recipe.get("features"), str)
                                   and isinstance(recipe.get("params"), dict)):
        raise bad("recipe", "an object with 'features' (a name) and 'params' (an object)", recipe)
    if d.get("feature_spec") is not None:
        _check_feature_spec(d["feature_spec"], where, feature_names)
    if d.get("weights") is not None:
        _check_weights(d["weights"], where, len(feature_names), n_outputs)
    rows = d.get("parity_inputs")
    if rows is not None and (_matrix(rows) or (0, 0))[1] != len(feature_names):
        raise UserError(f"{where}: parity_inputs: expected rows of {len(feature_names)} finite numbers "
                        f"(one per feature)")
    fb = d.get("fallback")
    if fb is not None and not (isinstance(fb, dict) and isinstance(fb.get("file"), str)
                               and isinstance(fb.get("sha256"), str) and isinstance(fb.get("n_features"), int)
                               and not isinstance(fb.get("n_features"), bool)
                               and 1 <= fb["n_features"] <= len(feature_names)
                               and isinstance(fb.get("optional"), list)
                               and all(isinstance(x, str) for x in fb["optional"])):
        raise bad("fallback", f"an object with file, sha256, n_features (1 to {len(feature_names)}) and "
                              f"optional (names)", fb)


def _check_feature_spec(doc: Any, where: str, feature_names: tuple[str, ...]) -> None:
    from virtsensor.features import FeatureSpec

    if not isinstance(doc, dict) or not isinstance(doc.get("features"), list) or not all(
            isinstance(f, dict) and isinstance(f.get("lag", 0), int) and not isinstance(f.get("lag", 0), bool)
            for f in doc["features"]):
        raise UserError(f"{where}: feature_spec: expected an object with 'name', 'tick_s' and 'features' (a list "
                        f"of {{signal, op, lag}} objects), got {type(doc).__name__}")
    try:
        spec = FeatureSpec.from_json(doc)
    except (AttributeError, KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{where}: feature_spec: not a usable feature spec ({type(exc).__name__}: {exc})") from None
    if spec.names != feature_names:
        raise UserError(f"{where}: feature_spec: its features {list(spec.names)} are not feature_names "
                        f"{list(feature_names)}")


def _check_weights(w: Any, where: str, n_features: int, n_outputs: int) -> None:
    if not isinstance(w, dict):
        raise UserError(f"{where}: weights: expected a JSON object, got {type(w).__name__}")
    for key in ("center", "scale"):
        if w.get(key) is not None and not _numbers(w[key], n_features):
            raise UserError(f"{where}: weights.{key}: expected {n_features} finite numbers (one per feature)")
    if w.get("scale") is not None and any(x == 0 for x in w["scale"]):
        raise UserError(f"{where}: weights.scale: expected non-zero numbers")
    for key in ("activation", "out_activation"):
        if w.get(key, "identity") not in ACTIVATIONS:
            raise UserError(f"{where}: weights.{key}: expected one of {', '.join(ACTIVATIONS)}")
    layers = w.get("layers")
    if not isinstance(layers, list) or not layers or not all(isinstance(x, dict) for x in layers):
        raise UserError(f"{where}: weights.layers: expected a non-empty list of {{W, b}} objects")
    width = n_features
    for i, layer in enumerate(layers):
        shape = _matrix(layer.get("W"))
        if shape is None or shape[0] != width:
            raise UserError(f"{where}: weights.layers[{i}].W: expected {width} rows of equally many finite numbers")
        if not _numbers(layer.get("b"), shape[1]):
            raise UserError(f"{where}: weights.layers[{i}].b: expected {shape[1]} finite numbers")
        width = shape[1]
    if width != n_outputs:
        raise UserError(f"{where}: weights.layers: the last layer gives {width} outputs, the card has {n_outputs}")


def seal_file(path: str | os.PathLike[str], extra: Mapping[str, Any] | None = None) -> ModelCard:
    """Migration: add ``extra`` keys (only those the card lacks) and a fresh ``card_sha256`` to a card file.

    For cards written before digests existed; the caller checks the result against its ONNX
    (e.g. with :meth:`virtsensor.model.onnx.OnnxModel.load`). The ONNX file is not touched.
    """
    card = ModelCard.read(path, verify=False)
    data = card.to_dict()
    for k, v in (extra or {}).items():
        data.setdefault(k, v)
    sealed = ModelCard(data, path=path).sealed()
    sealed.write(path)
    return sealed
