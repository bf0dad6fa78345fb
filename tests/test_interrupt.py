"""A Ctrl-C that scikit-learn swallows still stops the command, and nothing is written after it.

Before: SIGINT during ``train``'s final fit ended the MLP's fit early (scikit-learn catches KeyboardInterrupt
there and only warns), and the command wrote the half-trained network, exit 0; ``evaluate`` put a metric of an
interrupted fit into its JSON.
"""

from __future__ import annotations

import os
import signal
import threading
import warnings

import numpy as np
import pytest

from virtsensor.fileio import staged_files
from virtsensor.interrupt import fitted, sigint_noted


def test_a_fit_that_swallowed_a_ctrl_c_raises_it_again():
    from sklearn.neural_network import MLPRegressor

    rng = np.random.default_rng(0)
    X, y = rng.normal(size=(400, 5)), rng.normal(size=400)
    mlp = MLPRegressor(hidden_layer_sizes=(64, 64), max_iter=100_000, tol=0.0, n_iter_no_change=100_000,
                       random_state=0)
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    with sigint_noted():
        timer.start()
        try:
            with pytest.raises(KeyboardInterrupt):
                fitted(lambda: mlp.fit(X, y))
        finally:
            timer.cancel()
    assert getattr(mlp, "n_iter_", 0) < 100_000  # (the fit returned early, as scikit-learn does, or never began)


def test_the_warning_alone_tells_it_and_other_warnings_pass_on():
    def swallowing():
        warnings.warn("Training interrupted by user.", stacklevel=1)
        return 1

    with pytest.raises(KeyboardInterrupt):  # (no handler noting SIGINTs: library use)
        fitted(swallowing)

    def converging():
        warnings.warn("Stochastic Optimizer: Maximum iterations reached", UserWarning, stacklevel=1)
        return 2

    with pytest.warns(UserWarning, match="Maximum iterations"):
        assert fitted(converging) == 2


def test_no_output_is_put_in_place_after_a_swallowed_ctrl_c(tmp_path):
    target = tmp_path / "model.onnx"
    target.write_bytes(b"before")
    with sigint_noted():
        with pytest.raises(KeyboardInterrupt), staged_files(target) as (tmp,):
            tmp.write_bytes(b"after")
            try:
                os.kill(os.getpid(), signal.SIGINT)
            except KeyboardInterrupt:
                pass  # (swallowed, as a library does)
    assert target.read_bytes() == b"before" and sorted(tmp_path.iterdir()) == [target]
    with staged_files(target) as (tmp,):  # (the note ends with the block: the next command writes)
        tmp.write_bytes(b"next")
    assert target.read_bytes() == b"next"


def test_a_command_that_handles_the_interrupt_still_writes_what_it_has(tmp_path):
    """The demo catches Ctrl-C on purpose and writes its plot, JSON and summary of what ran ("interrupted": true):
    it says so, and its outputs are put in place."""
    from virtsensor.interrupt import handled

    target = tmp_path / "demo.json"
    with sigint_noted():
        try:
            os.kill(os.getpid(), signal.SIGINT)
        except KeyboardInterrupt:
            handled()
        with staged_files(target) as (tmp,):
            tmp.write_text('{"interrupted": true}')
    assert target.read_text() == '{"interrupted": true}'
