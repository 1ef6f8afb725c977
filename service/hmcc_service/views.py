"""Queue records -> the JSON the API answers (shapes in :mod:`hmcc_service.models`)."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from .queue import JobRecord, JobState

__all__ = ["batch_counts", "batch_item", "job_view"]


def _iso(t: datetime | None) -> str | None:
    return None if t is None else t.isoformat().replace("+00:00", "Z")


def _ms(a: datetime | None, b: datetime | None) -> float | None:
    return None if a is None or b is None else (b - a).total_seconds() * 1e3


def _with_service_timings(result: dict[str, Any], record: JobRecord) -> dict[str, Any]:
    timings = dict(result["timings_ms"])
    if (wait := _ms(record.submitted_at, record.started_at)) is not None:
        timings["queue_wait"] = max(0.0, wait)
    if (total := _ms(record.submitted_at, record.finished_at)) is not None:
        timings["total"] = max(0.0, total)
    return {**result, "timings_ms": timings}


def _outcome_fields(
    status: JobState, outcome: dict[str, Any] | None, error: dict[str, Any] | None,
    record: JobRecord,
) -> tuple[str, dict[str, Any] | None, dict[str, Any] | None]:
    if status is JobState.finished and outcome is not None:
        if outcome["status"] == "failed":
            return "failed", None, outcome["error"]
        return "finished", _with_service_timings(outcome["result"], record), None
    return status.value, None, error


def job_view(record: JobRecord) -> dict[str, Any]:
    """A pair job as ``JobView``."""
    status, result, error = _outcome_fields(record.status, record.outcome, record.error, record)
    return {
        "job_id": record.job_id,
        "status": status,
        "submitted_at": _iso(record.submitted_at),
        "started_at": _iso(record.started_at),
        "finished_at": _iso(record.finished_at),
        "result": result,
        "error": error,
    }


def batch_item(
    index: int, pair_id: str | None, record: JobRecord | None, position: int
) -> dict[str, Any]:
    """Pair ``position`` of a chunk job as ``BatchItem``."""
    if record is None:
        return {
            "index": index, "id": pair_id, "status": "failed", "result": None,
            "error": {"code": "expired", "message": "the job's record has expired"},
        }
    outcome = None
    if record.status is JobState.finished and isinstance(record.outcome, list):
        outcome = record.outcome[position]
    status, result, error = _outcome_fields(record.status, outcome, record.error, record)
    return {"index": index, "id": pair_id, "status": status, "result": result, "error": error}


def batch_counts(chunks: list[dict[str, Any]], records: list[JobRecord | None]) -> dict[str, int]:
    """Pairs per state, from the chunks' job records (outcomes not needed)."""
    counts = dict.fromkeys(("queued", "started", "finished", "failed", "canceled"), 0)
    for chunk, record in zip(chunks, records, strict=True):
        n = chunk["count"]
        if record is None:
            counts["failed"] += n
        elif record.status is JobState.finished:
            failed = record.failed_items or 0
            counts["failed"] += failed
            counts["finished"] += n - failed
        else:
            counts[record.status.value] += n
    return counts
