"""A Ctrl-C that a library swallows still stops the command, and nothing is written after it.

scikit-learn's MLP catches ``KeyboardInterrupt`` inside its fit, ends the fit early with a warning and returns
as if done: a command interrupted there went on with a half-trained network and wrote it, exit 0. So the command
line notes every SIGINT it gets (:func:`sigint_noted`, the main thread, for the command's whole run), the fits
raise it again once they return (:func:`fitted`), and every staged output checks it before it is put in place
(:func:`check`, called by :func:`virtsensor.fileio.staged_files` and :func:`~virtsensor.fileio.staged_dir`).
A command that starts processes of its own ends them with it: :func:`sigterm_interrupts` turns a SIGTERM into the
same unwinding as Ctrl-C (:class:`~virtsensor.errors.Terminated`, exit 143).
"""

from __future__ import annotations

import signal
import threading
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

__all__ = ["check", "fitted", "handled", "sigint_noted", "sigterm_interrupts"]

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
def _handler(signum: int, handler: Callable[[int, Any], None]) -> Iterator[None]:
    """``handler`` for ``signum`` for the block, the previous one after; outside the main thread (no signal
    handlers there) nothing is installed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.signal(signum, handler)
    try:
        yield
    finally:
        signal.signal(signum, before)


@contextmanager
def sigint_noted() -> Iterator[None]:
    """For the block, a SIGINT is noted (see :func:`check`) and raises ``KeyboardInterrupt`` as Python's own
    handler does. Outside the main thread (no signal handlers there) the block runs as it is."""
    def on_sigint(signum: int, frame: Any) -> None:
        _SEEN.set()
        raise KeyboardInterrupt

    _SEEN.clear()
    try:
        with _handler(signal.SIGINT, on_sigint):
            yield
    finally:
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


@contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """For the block, SIGTERM raises :class:`~virtsensor.errors.Terminated` (a ``KeyboardInterrupt``: the command
    unwinds as on Ctrl-C, its children ended and its files removed; exit 143). Outside the main thread the block
    runs as it is."""
    from virtsensor.errors import Terminated

    def on_sigterm(signum: int, frame: Any) -> None:
        raise Terminated

    with _handler(signal.SIGTERM, on_sigterm):
        yield
