"""Job queues behind the API: one interface, two backends.

* :class:`~hmcc_service.embedded.EmbeddedQueue` (no ``REDIS_URL``): jobs run in child processes
  of the API (:class:`hmcc_worker.pool.ComputePool`), results are kept in memory. One command,
  nothing else to install.
* :class:`~hmcc_service.rq_queue.RQQueue` (``REDIS_URL`` set): RQ on Redis, run by
  ``hmcc worker`` processes anywhere.

A job verifies a :class:`hmcc.flight.Flight`: one pair (``JobKind.pair``) or a chunk of a
batch (``JobKind.chunk``). Both backends answer with the same :class:`JobRecord`, so the
routes (and the responses) do not know which one they talk to. A record never holds the input,
and holds a finished job's per-pair outcomes only when they are asked for
(:meth:`JobQueue.outcomes`): stored bytes, spliced into the answer as they are.
"""

from __future__ import annotations

import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Protocol

from hmcc.flight import Flight, FlightImage
from hmcc_worker.metrics import JobMetricsSnapshot
from hmcc_worker.protocol import JobKind, JobStatus

__all__ = [
    "JobQueue",
    "JobRecord",
    "NotCancelable",
    "QueueFull",
    "QueueUnavailable",
    "ShuttingDown",
    "new_id",
    "utcnow",
]


@dataclass
class JobRecord:
    """A job as the API sees it. ``pairs``: how many pairs it verifies; ``failed``: how many of
    them failed (known once it finished); ``error``: set when the job itself failed (its worker
    was lost, its input expired) as ``{"code", "message"}`` without internals."""

    job_id: str
    kind: JobKind
    status: JobStatus
    submitted_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    pairs: int = 1
    failed: int | None = None
    error: dict[str, str] | None = None


class QueueUnavailable(Exception):
    """The queue backend cannot be reached, or cannot run jobs (-> 503 + Retry-After; the
    message, if any, says why)."""


class ShuttingDown(Exception):
    """The API is shutting down and takes no new job (-> 503 + Retry-After)."""


class QueueFull(Exception):
    """More queued jobs than ``max_queue_depth`` (-> 429 + Retry-After)."""


class NotCancelable(Exception):
    """Only a queued job can be cancelled (-> 409)."""

    def __init__(self, status: JobStatus) -> None:
        super().__init__(status)
        self.status = status


class JobQueue(Protocol):
    mode: str

    async def submit(
        self,
        kind: JobKind,
        flights: Sequence[Flight],
        *,
        batch_id: str | None = None,
        images: Mapping[str, FlightImage] | None = None,
        ttl_s: int | None = None,
    ) -> list[JobRecord]:
        """Queue one job per flight (all or none); raises QueueFull/QueueUnavailable. A batch's
        chunks pass its id and all its ``images``, stored once for them; their results live
        ``ttl_s`` (the batch's lifetime) instead of the result TTL."""

    async def fetch(self, job_ids: Sequence[str]) -> list[JobRecord | None]:
        """The jobs (None: unknown or expired), without their outcomes."""

    async def outcomes(self, ranges: Sequence[tuple[str, int, int]]) -> list[list[bytes] | None]:
        """Stored outcomes ``start:stop`` of each finished ``(job_id, start, stop)`` (see
        :func:`hmcc_worker.outcomes.unpack`); None where they are gone."""

    async def wait(
        self, job_id: str, timeout_s: float, *, pending: bool = False
    ) -> JobRecord | None:
        """The job once it is finished/failed/canceled, or as it is after ``timeout_s``
        (``pending``: the caller just submitted it, a hint to skip the first look)."""

    async def wait_any(self, job_ids: Sequence[str], timeout_s: float) -> None:
        """Return when one of the jobs ends, or after ``timeout_s``."""

    async def cancel(self, job_id: str) -> JobRecord | None:
        """Cancel a queued job (None: unknown); raises NotCancelable once it started."""

    async def readiness(self) -> dict[str, Any]:
        """``{"ready": bool, ...details}``; never raises."""

    async def workers(self) -> int:
        """How many jobs run at once (embedded: its children; RQ: the live workers, as
        :meth:`readiness` counts them); raises QueueUnavailable."""

    async def put_batch(self, batch_id: str, meta: dict[str, Any]) -> None:
        """Keep a batch's description (its chunks' job ids) for ``meta["ttl_s"]`` seconds."""

    async def get_batch(self, batch_id: str) -> dict[str, Any] | None: ...

    async def batch_ended(self, batch_id: str) -> None:
        """Every job of the batch has ended: drop the input its jobs shared (its images); a
        no-op when there is none or it is gone."""

    def job_metrics(self) -> JobMetricsSnapshot:
        """Aggregated per-stage durations and failures (called from a worker thread)."""

    def compute_cpu_s(self) -> float | None:
        """CPU seconds of this process's compute children (embedded mode), ended ones too;
        None where the compute runs elsewhere (RQ workers)."""

    def depth_sync(self) -> int:
        """Jobs waiting (for ``/metrics``, called from a worker thread)."""

    async def close(self) -> None: ...


def new_id() -> str:
    return uuid.uuid4().hex


def utcnow() -> datetime:
    return datetime.now(UTC)
