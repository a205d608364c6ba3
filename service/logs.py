"""Structured logs: one JSON object per line, with the job and project ids steps attach, so a
job's whole history can be grepped across the API and every worker."""

from __future__ import annotations

import json
import logging
import os
import sys
from datetime import UTC, datetime

_FIELDS = ("job_id", "project_id", "tenant_id")


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out = {
            "ts": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
            "pid": record.process,
        }
        for f in _FIELDS:
            if hasattr(record, f):
                out[f] = getattr(record, f)
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


def configure(level: str | None = None) -> None:
    """GEOMATCH_LOG_FORMAT=text gives plain lines for humans; JSON is the default."""
    handler = logging.StreamHandler(sys.stderr)
    if os.environ.get("GEOMATCH_LOG_FORMAT", "json") == "text":
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s %(message)s"))
    else:
        handler.setFormatter(JsonFormatter())
    root = logging.getLogger("geomatch")
    root.handlers[:] = [handler]
    root.setLevel((level or os.environ.get("GEOMATCH_LOG_LEVEL", "INFO")).upper())
    root.propagate = False
