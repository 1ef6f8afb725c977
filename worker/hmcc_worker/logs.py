"""Structured logs: one JSON object per line on stderr, with the job id when there is one
(given as ``extra={"job_id": ...}``, or the RQ job the worker is running)."""

from __future__ import annotations

import json
import logging
import sys
import time

__all__ = ["configure_logging"]


class _JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        doc = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        job_id = getattr(record, "job_id", None) or _rq_job_id()
        if job_id:
            doc["job_id"] = job_id
        for key in ("event", "status", "duration_ms", "path", "method", "status_code"):
            if (value := getattr(record, key, None)) is not None:
                doc[key] = value
        if record.exc_info and record.levelno >= logging.ERROR:
            doc["exception"] = self.formatException(record.exc_info)
        return json.dumps(doc)


def _rq_job_id() -> str | None:
    rq = sys.modules.get("rq")
    if rq is None:
        return None
    job = rq.get_current_job()
    return None if job is None else str(job.id)


def configure_logging(level: str = "INFO") -> None:
    """Route every logger (ours, RQ's, uvicorn's) through one JSON handler on stderr."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_JsonFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    for name in ("rq.worker", "uvicorn", "uvicorn.error"):
        logger = logging.getLogger(name)
        logger.handlers[:] = []
        logger.propagate = True
