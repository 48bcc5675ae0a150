"""Logging set-up of every gaitmon command: text or JSON lines on stderr, each with the request id."""

from __future__ import annotations

import logging
import sys

from pythonjsonlogger.json import JsonFormatter

from server.ops.request_id import RequestIdFilter

TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s [%(request_id)s]: %(message)s"
JSON_FIELDS = "%(asctime)s %(levelname)s %(name)s %(request_id)s %(message)s"


def setup_logging(level: str, fmt: str = "text") -> None:
    """Configure the root logger (uvicorn's loggers propagate to it: ``gaitmon serve`` passes no log config)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.addFilter(RequestIdFilter())
    if fmt == "json":
        handler.setFormatter(JsonFormatter(JSON_FIELDS, rename_fields={"asctime": "time", "levelname": "level",
                                                                       "name": "logger"}))
    else:
        handler.setFormatter(logging.Formatter(TEXT_FORMAT))
    logging.basicConfig(level=level.upper(), handlers=[handler], force=True)
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        # uvicorn may have attached handlers of its own on an earlier run in this process.
        lg = logging.getLogger(name)
        lg.handlers.clear()
        lg.propagate = True
    # One line per plugin on every start says nothing to an operator.
    logging.getLogger("alembic.runtime.plugins").setLevel(logging.WARNING)
