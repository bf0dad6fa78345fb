"""What the daemon needs to load and run a model: its card (:mod:`.card`) and the ONNX runtime (:mod:`.onnx`).

Importing this package imports neither scikit-learn, skl2onnx, onnx nor scipy; the export side
(:mod:`virtsensor.model.export`) needs them and is imported only by whoever exports.
"""

from virtsensor.model.card import ModelCard, card_path_for
from virtsensor.model.onnx import NumpyForward, OnnxModel, numpy_forward

__all__ = ["ModelCard", "NumpyForward", "OnnxModel", "card_path_for", "numpy_forward"]
