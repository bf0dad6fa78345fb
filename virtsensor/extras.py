"""Optional extras: which commands need which optional packages, and the one-line refusal when absent.

The base install is the runtime (numpy, onnxruntime, python-can, cantools). Everything else comes with an
extra of ``pyproject.toml``; :data:`EXTRAS` lists the importable top-level modules each one provides.
A command that needs an extra calls :func:`require` before it starts work; a missing module found later
(an optional path inside a command) is mapped back to its extra by :func:`extra_for_module`.
"""

from __future__ import annotations

import importlib.util

from virtsensor.errors import UserError

__all__ = ["EXTRAS", "PIP_NAMES", "MissingExtra", "as_user_error", "extra_for_module", "missing_extra",
           "missing_modules", "require"]

_TRAIN = ("scipy", "sklearn", "skl2onnx", "joblib", "threadpoolctl", "tqdm")

#: extra name -> the top-level modules it makes importable (what ``import`` needs, not the PyPI names)
EXTRAS: dict[str, tuple[str, ...]] = {
    "train": _TRAIN,
    "plots": ("matplotlib",),
    "explain": (*_TRAIN, "matplotlib", "shap"),
    "mdf": ("asammdf",),
    "distributed": ("ray",),
    "dask": ("dask", "distributed"),
}


#: importable module -> the distribution pip installs it from, where the two names differ
PIP_NAMES: dict[str, str] = {"sklearn": "scikit-learn"}


class MissingExtra(UserError):
    """An optional extra that the requested work needs is not installed (exit code 2)."""


def missing_modules(extra: str) -> list[str]:
    """The modules of ``extra`` that cannot be imported here (empty when the extra is installed)."""
    return [m for m in EXTRAS[extra] if importlib.util.find_spec(m) is None]


def _message(what: str, extra: str, missing: list[str]) -> str:
    names = ", ".join(PIP_NAMES.get(m, m) for m in missing)  # (what pip installs, not what ``import`` names)
    return f"{what} needs the optional extra '{extra}' (missing: {names}): pip install 'virtsensor[{extra}]'"


def missing_extra(extra: str, what: str) -> MissingExtra | None:
    """The :class:`MissingExtra` naming ``extra``, its modules missing here and the install command (None when the
    extra is installed): what :func:`require` raises."""
    absent = missing_modules(extra)
    return MissingExtra(_message(what, extra, absent)) if absent else None


def require(extra: str, what: str) -> None:
    """Raise :class:`MissingExtra` naming ``extra`` and the install command when any of its modules is absent.

    Args:
        extra: a key of :data:`EXTRAS`.
        what: what needs it, for the message after the command's own name (e.g. ``"this command"``, ``"--plot"``).
    """
    err = missing_extra(extra, what)
    if err is not None:
        raise err


def extra_for_module(module: str | None) -> str | None:
    """The smallest extra that provides top-level module ``module`` (``"sklearn.pipeline"`` -> ``train``)."""
    if not module:
        return None
    top = module.split(".", 1)[0]
    for name in ("train", "plots", "mdf", "distributed", "dask", "explain"):
        if top in EXTRAS[name]:
            return name
    return None


def as_user_error(exc: ModuleNotFoundError, what: str) -> MissingExtra | None:
    """The :class:`MissingExtra` for an import that failed on an optional module, None for any other."""
    extra = extra_for_module(exc.name)
    return None if extra is None else MissingExtra(_message(what, extra, [str(exc.name).split(".", 1)[0]]))
