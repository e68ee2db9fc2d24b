"""Structured logs: one JSON object per line on stderr, for the daemons and the client.

``event(log, "session_done", sid=..., seconds=...)`` writes
``{"ts": ..., "level": "info", "role": "evaluator", "event": "session_done", ...}``.
"""

from __future__ import annotations

import json
import logging
import sys
from typing import Any

_FIELDS = "snail_fields"


class JsonFormatter(logging.Formatter):
    def __init__(self, role: str) -> None:
        super().__init__()
        self.role = role

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "ts": round(record.created, 6),
            "level": record.levelname.lower(),
            "role": self.role,
            "event": record.getMessage(),
        }
        entry.update(getattr(record, _FIELDS, {}))
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=_jsonable)


def _jsonable(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.hex()
    return str(value)


def setup(role: str, level: str = "info") -> logging.Logger:
    """Route the ``snail`` logger to stderr as JSON lines; returns it."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter(role))
    logger = logging.getLogger("snail")
    logger.handlers[:] = [handler]
    logger.setLevel(level.upper())
    logger.propagate = False
    return logger


def event(logger: logging.Logger, name: str, level: int = logging.INFO,
          **fields: Any) -> None:
    """Log event ``name`` with structured ``fields``."""
    if logger.isEnabledFor(level):
        logger.log(level, name, extra={_FIELDS: fields})


def announce(logger: logging.Logger, name: str, level: int = logging.INFO,
             **fields: Any) -> None:
    """Log event ``name`` (at info ``level`` unless told) whatever the configured level:
    lifecycle lines (``listening``, ``stopped``) that supervisors and the embedded runner
    wait for, and warnings nobody may miss (armed failpoints)."""
    record = logger.makeRecord(logger.name, level, "(snail)", 0, name, (), None,
                               extra={_FIELDS: fields})
    for handler in logger.handlers:
        handler.handle(record)
