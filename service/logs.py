"""Structured log lines: one JSON object per line for anything that carries request input.

A client controls site ids, paths, frame ids and device ids; written raw into a text log, a CR/LF in one of them
forges a line of its own. `json.dumps` escapes every control character, so a line written by `log_event` is always
exactly one line and always parses:

    log_event(log, "http_request", request_id=rid, method="GET", path=path, status=404, code="unknown_site")
    -> {"event": "http_request", "request_id": "...", "method": "GET", "path": "...", "status": 404, ...}

Values that are not JSON (paths, exceptions) are written as their `str`. Both front ends (HTTP, zenoh) use this.
"""

from __future__ import annotations

import json
import logging
from typing import Any


def event_line(event: str, **fields: Any) -> str:
    """The one-line JSON text of an event: {"event": event, **fields}; control characters escaped, never raises."""
    doc = {"event": event, **fields}
    try:
        return json.dumps(doc, default=str, allow_nan=False)
    except ValueError:  # NaN or infinity somewhere: keep the line valid JSON
        return json.dumps({k: (v if isinstance(v, (str, int, bool)) or v is None else str(v)) for k, v in doc.items()},
                          default=str)


def log_event(logger: logging.Logger, event: str, level: int = logging.INFO, **fields: Any) -> None:
    """Write one JSON object (see `event_line`) to `logger` at `level`."""
    if logger.isEnabledFor(level):
        # passed as an argument, not as the format string: a '%' in client input stays text
        logger.log(level, "%s", event_line(event, **fields))
