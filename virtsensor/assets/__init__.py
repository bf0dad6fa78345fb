"""The files the package ships: the trained models, the CAN matrix and the demo recording.

They are package data, found through :mod:`importlib.resources`, so an installed wheel and a source
checkout (editable install) resolve them the same way, from any working directory:

* ``virtsensor.assets.models`` is the repository's ``models/`` folder (``*.onnx`` with their
  ``*.card.json``, ``evaluation.md``/``.json``);
* ``virtsensor.assets.dbc`` is the repository's ``dbc/`` folder (``virtsensor.dbc``);
* the demo recording lives with the simulator's data, ``sim/data/recordings/``;
* ``bench_inputs.npz`` (beside this module): the input frames ``virtsensor bench`` replays, those of its
  simulated manoeuvre (:data:`virtsensor.daemon.bench.MANOEUVRE`), so the bench runs on the base install,
  without the simulator (``python tools/bench_inputs.py`` writes it; a test checks it against the simulator).

A path given on the command line always wins over these defaults; these functions only name the
bundled files. Each returns a :class:`pathlib.Path` of a file that exists, or raises
:class:`~virtsensor.errors.UserError` naming what is missing (a broken install).
"""

from __future__ import annotations

from importlib.resources import as_file, files
from pathlib import Path

from virtsensor.errors import UserError

__all__ = ["DEFAULT_MODEL_NAME", "BENCH_INPUTS", "bench_inputs_path", "bundled_models", "bundled_recordings_dir",
           "dbc_path", "model_path", "recording_path"]

#: The model the daemon, the bench and the demo use when no ``--model`` is given.
DEFAULT_MODEL_NAME = "improved"
#: The bench's input frames, package data of this package.
BENCH_INPUTS = "bench_inputs.npz"


def _file(package: str, name: str, what: str) -> Path:
    try:
        ref = files(package) / name
    except ModuleNotFoundError:
        raise UserError(f"the installed virtsensor has no {package} (a broken install: reinstall it)") from None
    # Both an editable install and a wheel keep package data as plain files on disk; as_file is the
    # documented way to get a path and costs nothing then.
    with as_file(ref) as path:
        if not Path(path).is_file():
            raise UserError(f"the bundled {what} {name} is missing from {package} (a broken install: reinstall it)")
        return Path(path)


def model_path(name: str = DEFAULT_MODEL_NAME) -> Path:
    """The shipped ONNX model ``name`` (``improved``, ``paper``, ...); its ``.card.json`` lies beside it."""
    return _file("virtsensor.assets.models", f"{name}.onnx", "model")


def bundled_models() -> tuple[str, ...]:
    """Names of the shipped models (without ``.onnx``), sorted."""
    root = files("virtsensor.assets.models")
    return tuple(sorted(p.name[: -len(".onnx")] for p in root.iterdir() if p.name.endswith(".onnx")))


def dbc_path() -> Path:
    """The bundled CAN matrix ``virtsensor.dbc`` (generated from :mod:`virtsensor.signals`)."""
    return _file("virtsensor.assets.dbc", "virtsensor.dbc", "CAN matrix")


def bench_inputs_path() -> Path:
    """The input frames ``virtsensor bench`` replays (:data:`BENCH_INPUTS`)."""
    return _file("virtsensor.assets", BENCH_INPUTS, "bench input frames")


def bundled_recordings_dir() -> Path:
    """The folder of the bundled recordings, ``sim/data/recordings`` (package data of :mod:`sim`)."""
    with as_file(files("sim") / "data" / "recordings") as path:
        return Path(path)


def recording_path(name: str) -> Path:
    """A bundled recording of the simulator's data folder (``sim/data/recordings/<name>``)."""
    return _file("sim", f"data/recordings/{name}", "recording")
