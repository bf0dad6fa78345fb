"""Hold back what a library logs while a step runs, to fold it into that step's one error line or pass it on.

python-can logs its interfaces' notes while a bus opens, cantools a message that replaces another while a DBC
loads: printed at once, they would come before the one line that says what went wrong. :func:`held_records`
keeps them instead; the caller decides afterwards (the records are handed on with ``logger.handle`` as they would
have been, or dropped once folded into an error).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["held_records"]


class _Held(logging.Handler):
    """Keeps the records it is handed."""

    def __init__(self, level: int) -> None:
        super().__init__(level)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@contextmanager
def held_records(name: str, level: int = logging.DEBUG) -> Iterator[list[logging.LogRecord]]:
    """For the block, the records of logger ``name`` (and its children) at ``level`` or above go into the list
    yielded and nowhere else (the logger does not propagate them). It changes the process's logger for that
    moment: use it where no other thread logs through ``name``."""
    log = logging.getLogger(name)
    held, propagate = _Held(level), log.propagate
    log.addHandler(held)
    log.propagate = False
    try:
        yield held.records
    finally:
        log.removeHandler(held)
        log.propagate = propagate
