"""Queue records -> the bytes the API answers (shapes in :mod:`hmcc_service.models`).

A pair's result or error was encoded once, by the process that verified it; here it is
spliced into the answer as it is (``orjson.Fragment``), never parsed again.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime, timedelta
from typing import Any

import orjson

from hmcc_worker.outcomes import unpack
from hmcc_worker.protocol import ItemStatus, JobStatus

from .queue import JobRecord

__all__ = ["ITEM_STATUSES", "batch_counts", "batch_item", "job_view"]

#: A batch item's statuses: a job's, and ``expired`` for a result no longer kept.
ITEM_STATUSES = tuple(s.value for s in ItemStatus)


def _iso(t: datetime | None) -> str | None:
    return None if t is None else t.isoformat().replace("+00:00", "Z")


def _ms(a: datetime | None, b: datetime | None) -> float | None:
    """Milliseconds from ``a`` to ``b``, to the microsecond the times hold (0.001 ms): rounded,
    since ``timedelta.total_seconds() * 1e3`` reads 12.300000000000001 for 12.3."""
    if a is None or b is None:
        return None
    return max(0.0, round((b - a) / timedelta(microseconds=1)) / 1e3)


def _outcome(
    record: JobRecord | None, stored: bytes | None
) -> tuple[str, orjson.Fragment | None, Any]:
    """``(status, result, error)`` of one pair of a job."""
    if record is None:
        return ItemStatus.expired.value, None, None
    if record.status is JobStatus.finished:
        if stored is None:
            return ItemStatus.expired.value, None, None
        status, body = unpack(stored)
        if status is JobStatus.finished:
            return status.value, orjson.Fragment(body), None
        return status.value, None, orjson.Fragment(body)
    return record.status.value, None, record.error


def job_view(record: JobRecord, stored: bytes | None) -> bytes:
    """A pair job as ``JobView``; ``stored``: its outcome once it finished (the caller answers
    404 for a finished job whose outcome is gone)."""
    status, result, error = _outcome(record, stored)
    return orjson.dumps(
        {
            "job_id": record.job_id,
            "status": status,
            "submitted_at": _iso(record.submitted_at),
            "started_at": _iso(record.started_at),
            "finished_at": _iso(record.finished_at),
            "timings_ms": {
                "queue_wait": _ms(record.submitted_at, record.started_at),
                "run": _ms(record.started_at, record.finished_at),
                "turnaround": _ms(record.submitted_at, record.finished_at),
            },
            "result": result,
            "error": error,
        }
    )


def batch_item(
    index: int, pair_id: str | None, record: JobRecord | None, stored: bytes | None
) -> dict[str, Any]:
    """One pair of a batch as ``BatchItem`` (a dict holding fragments, for orjson)."""
    status, result, error = _outcome(record, stored)
    return {"index": index, "id": pair_id, "status": status, "result": result, "error": error}


def batch_counts(
    chunks: Sequence[dict[str, Any]], records: Sequence[JobRecord | None]
) -> dict[str, int]:
    """Pairs per state, from the chunks' job records (outcomes not needed)."""
    counts = dict.fromkeys(ITEM_STATUSES, 0)
    for chunk, record in zip(chunks, records, strict=True):
        n = chunk["count"]
        if record is None:
            counts[ItemStatus.expired.value] += n
        elif record.status is JobStatus.finished:
            failed = record.failed or 0
            counts["failed"] += failed
            counts["finished"] += n - failed
        elif record.status is JobStatus.failed:
            counts["failed"] += n
        else:
            counts[record.status.value] += n
    return counts
