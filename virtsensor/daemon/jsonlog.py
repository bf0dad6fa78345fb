"""JSON-lines logging of the daemon: one object per line on stderr.

Each line holds ``ts`` (UTC ISO 8601, ms), ``level``, ``logger``, ``event`` and the record's ``fields``
(``logger.info("event", extra={"fields": {...}})``, or :func:`event`). Non-finite floats become null.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from collections.abc import Mapping
from typing import Any

from virtsensor.errors import UserError
from virtsensor.fileio import json_safe

__all__ = ["LOG_LEVELS", "JsonFormatter", "configure_logging", "event", "log"]

#: the daemon's logger (its events: ``started``, ``status_change``, ``bus_error``, ``shutdown``, ...)
log = logging.getLogger("virtsensor.daemon")

LOG_LEVELS = ("debug", "info", "warning", "error")


class JsonFormatter(logging.Formatter):
    """One JSON object per line: ``ts`` (UTC ISO 8601, ms), ``level``, ``logger``, ``event`` and the
    record's ``fields`` (``logger.info("event", extra={"fields": {...}})``). Non-finite floats become null."""

    def format(self, record: logging.LogRecord) -> str:
        ts = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z"
        out: dict[str, Any] = {"ts": ts, "level": record.levelname.lower(), "logger": record.name,
                               "event": record.getMessage()}
        extra = getattr(record, "fields", None)
        if isinstance(extra, Mapping):
            out.update(extra)
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        return json.dumps(json_safe(out), default=str, separators=(",", ":"))


class _StderrHandler(logging.StreamHandler):
    """A stream handler that writes to whatever ``sys.stderr`` is at emit time."""

    @property  # type: ignore[override]
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ assigns it
        pass


def configure_logging(level: str = "info") -> None:
    """JSON-lines logs of the ``virtsensor`` loggers on stderr at ``level`` (replaces earlier set-ups)."""
    lv = str(level).lower()
    if lv not in LOG_LEVELS:
        raise UserError(f"log level {level!r} is not one of {', '.join(LOG_LEVELS)}")
    root = logging.getLogger("virtsensor")
    for h in list(root.handlers):
        if isinstance(h, _StderrHandler):
            root.removeHandler(h)
    handler = _StderrHandler()
    handler.setFormatter(JsonFormatter())
    root.addHandler(handler)
    root.setLevel(lv.upper())
    root.propagate = False


def event(level: int, name: str, **data: Any) -> None:
    """Log event ``name`` with ``data`` as its fields on the daemon's logger (nothing when the level is off)."""
    if log.isEnabledFor(level):
        log.log(level, name, extra={"fields": data})
