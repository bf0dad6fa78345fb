"""A Ctrl-C that a library swallows still stops the command, and nothing is written after it.

scikit-learn's MLP catches ``KeyboardInterrupt`` inside its fit, ends the fit early with a warning and returns
as if done: a command interrupted there went on with a half-trained network and wrote it, exit 0. So the command
line notes every SIGINT it gets (:func:`sigint_noted`, the main thread, for the command's whole run), the fits
raise it again once they return (:func:`fitted`), and every staged output checks it before it is put in place
(:func:`check`, called by :func:`virtsensor.fileio.staged_files` and :func:`~virtsensor.fileio.staged_dir`).
"""

from __future__ import annotations

import signal
import threading
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

__all__ = ["check", "fitted", "handled", "sigint_noted"]

_SEEN = threading.Event()
#: scikit-learn's warning where its MLP swallowed a KeyboardInterrupt
_SWALLOWED = "Training interrupted by user"

T = TypeVar("T")


def check() -> None:
    """Raise ``KeyboardInterrupt`` if a SIGINT was noted since :func:`sigint_noted` began (one some code
    swallowed)."""
    if _SEEN.is_set():
        raise KeyboardInterrupt


def handled() -> None:
    """A command that catches the interrupt on purpose and goes on to write what it has (the demo's summary and
    plot, replay's count) says so: the SIGINT noted so far no longer stops its outputs."""
    _SEEN.clear()


@contextmanager
def sigint_noted() -> Iterator[None]:
    """For the block, a SIGINT is noted (see :func:`check`) and raises ``KeyboardInterrupt`` as Python's own
    handler does. Outside the main thread (no signal handlers there) the block runs as it is."""
    _SEEN.clear()
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_sigint(signum: int, frame: Any) -> None:
        _SEEN.set()
        raise KeyboardInterrupt

    before = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)
        _SEEN.clear()


def fitted(fit: Callable[[], T]) -> T:
    """``fit()`` (an estimator's fit), raising ``KeyboardInterrupt`` if it swallowed one: scikit-learn's warning
    says so (also where no handler notes SIGINTs), or a SIGINT was noted meanwhile. Other warnings pass on to the
    caller's filters."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = fit()
    swallowed = False
    for w in caught:
        if _SWALLOWED in str(w.message):
            swallowed = True
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    if swallowed:
        raise KeyboardInterrupt
    check()
    return out
