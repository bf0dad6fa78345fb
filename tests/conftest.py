"""Shared test fixtures."""

from __future__ import annotations

import logging

import pytest


@pytest.fixture(autouse=True)
def _restore_logging():
    """``virtsensor run`` (called in-process) sets up JSON logging on the ``virtsensor`` logger: undo it."""
    lg = logging.getLogger("virtsensor")
    saved = (list(lg.handlers), lg.level, lg.propagate)
    yield
    lg.handlers[:], lg.level, lg.propagate = saved[0], saved[1], saved[2]
