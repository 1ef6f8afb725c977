"""Job queues behind the API: one interface, two backends.

* :class:`EmbeddedQueue` (no ``REDIS_URL``): a thread pool in the API process; jobs and
  results live in memory for ``result_ttl_s``. One command, nothing else to install.
* :class:`hmcc_service.rq_queue.RQQueue` (``REDIS_URL`` set): RQ on Redis, JSON-serialised,
  run by ``hmcc worker`` processes anywhere.

Both run the same job functions (:mod:`hmcc_worker.jobs`) and answer with the same
:class:`JobRecord`, so the routes (and the responses) do not know which one they talk to.
A job's ``outcome`` is what the job function returned: one pair outcome dict, or a list of
them for a batch chunk. ``error`` is set when the job itself failed (crash, timeout, worker
lost), as ``{"code", "message"}`` without internals.
"""

from __future__ import annotations

import asyncio
import enum
import logging
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, Literal, Protocol

from hmcc.schema import BatchRequest, PairRequest
from hmcc_worker.jobs import run_chunk, run_pair
from hmcc_worker.metrics import JobMetricsSnapshot, MemoryJobMetrics

from .settings import Settings

__all__ = [
    "EmbeddedQueue",
    "JobKind",
    "JobQueue",
    "JobRecord",
    "JobState",
    "NotCancelable",
    "Payload",
    "QueueFull",
    "QueueUnavailable",
    "new_id",
]

log = logging.getLogger("hmcc.queue")

JobKind = Literal["pair", "chunk"]


class JobState(enum.StrEnum):
    queued = "queued"
    started = "started"
    finished = "finished"
    failed = "failed"
    canceled = "canceled"


TERMINAL = {JobState.finished, JobState.failed, JobState.canceled}


#: A job's input: the validated request (the RQ queue stores it as a binary payload, the
#: embedded queue runs it as is).
Payload = PairRequest | BatchRequest


@dataclass
class JobRecord:
    job_id: str
    kind: JobKind
    status: JobState
    submitted_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    outcome: Any = None
    error: dict[str, str] | None = None
    #: Chunks: how many of its pairs failed (known once finished, even without the outcome).
    failed_items: int | None = None


class QueueUnavailable(Exception):
    """The queue backend cannot be reached (-> 503 + Retry-After)."""


class QueueFull(Exception):
    """More queued jobs than ``max_queue_depth`` (-> 429 + Retry-After)."""


class NotCancelable(Exception):
    """Only a queued job can be cancelled (-> 409)."""

    def __init__(self, status: JobState) -> None:
        super().__init__(status)
        self.status = status


class JobQueue(Protocol):
    mode: str

    async def submit(self, kind: JobKind, payloads: Sequence[Payload]) -> list[JobRecord]:
        """Queue one job per payload (all or none); raises QueueFull/QueueUnavailable."""

    async def fetch(
        self, job_ids: list[str], with_outcome: bool = True
    ) -> list[JobRecord | None]:
        """The jobs (None: unknown or expired); ``with_outcome=False`` may leave out the
        finished jobs' outcomes (cheaper; ``failed_items`` is still set for chunks)."""

    async def wait(
        self, job_id: str, timeout_s: float, *, pending: bool = False
    ) -> JobRecord | None:
        """The job once it is finished/failed/canceled, or as it is after ``timeout_s``
        (``pending``: the caller just submitted it, a hint to skip the first look)."""

    async def cancel(self, job_id: str) -> JobRecord | None: ...

    async def readiness(self) -> dict[str, Any]:
        """``{"ready": bool, ...details}``; never raises."""

    async def put_batch(self, batch_id: str, meta: dict[str, Any]) -> None:
        """Keep a batch's description (its chunks' job ids) for ``meta["ttl_s"]`` seconds."""

    async def get_batch(self, batch_id: str) -> dict[str, Any] | None: ...

    def job_metrics(self) -> JobMetricsSnapshot:
        """Aggregated per-stage durations and failures (called from a worker thread)."""

    def depth_sync(self) -> int:
        """Jobs waiting (for ``/metrics``, called from a worker thread)."""

    async def close(self) -> None: ...


def new_id() -> str:
    return uuid.uuid4().hex


def utcnow() -> datetime:
    return datetime.now(UTC)


_RUNNERS: dict[str, Callable[[Any], Any]] = {"pair": run_pair, "chunk": run_chunk}


@dataclass
class _Embedded:
    record: JobRecord
    future: Future[Any] | None = None
    done: asyncio.Event = field(default_factory=asyncio.Event)
    loop: asyncio.AbstractEventLoop | None = None
    finished_mono: float | None = None


class EmbeddedQueue:
    """Jobs run by a thread pool in this process; records expire ``result_ttl_s`` after."""

    mode = "embedded"

    def __init__(self, settings: Settings) -> None:
        self._settings = settings
        self._pool = ThreadPoolExecutor(settings.embedded_workers, thread_name_prefix="hmcc-job")
        self._jobs: dict[str, _Embedded] = {}
        self._batches: dict[str, tuple[float, dict[str, Any]]] = {}
        self._lock = threading.Lock()
        self._queued = 0
        self._last_purge = 0.0
        self._metrics = MemoryJobMetrics()

    async def submit(self, kind: JobKind, payloads: Sequence[Payload]) -> list[JobRecord]:
        self._purge()
        loop = asyncio.get_running_loop()
        with self._lock:
            if self._queued + len(payloads) > self._settings.max_queue_depth:
                raise QueueFull
            self._queued += len(payloads)
            entries = []
            for _ in payloads:
                entry = _Embedded(JobRecord(new_id(), kind, JobState.queued, utcnow()), loop=loop)
                self._jobs[entry.record.job_id] = entry
                entries.append(entry)
        for entry, payload in zip(entries, payloads, strict=True):
            entry.future = self._pool.submit(self._run, entry, payload)
        return [_copy(e.record) for e in entries]

    def _run(self, entry: _Embedded, payload: Any) -> None:
        record = entry.record
        with self._lock:
            if record.status is not JobState.queued:
                return
            self._queued -= 1
            record.status = JobState.started
            record.started_at = utcnow()
        try:
            outcome = _RUNNERS[record.kind](payload)
            if isinstance(outcome, list):
                record.failed_items = sum(o["status"] == "failed" for o in outcome)
            self._metrics.record(outcome if isinstance(outcome, list) else [outcome])
            status, error = JobState.finished, None
        except Exception:
            log.exception("job crashed", extra={"job_id": record.job_id})
            self._metrics.record_failure("exception")
            outcome = None
            status, error = JobState.failed, {"code": "internal_error", "message": "the job failed"}
        with self._lock:
            record.outcome, record.error = outcome, error
            record.status, record.finished_at = status, utcnow()
            entry.finished_mono = time.monotonic()
        self._wake(entry)

    @staticmethod
    def _wake(entry: _Embedded) -> None:
        if entry.loop is not None and not entry.loop.is_closed():
            entry.loop.call_soon_threadsafe(entry.done.set)

    async def fetch(
        self, job_ids: list[str], with_outcome: bool = True
    ) -> list[JobRecord | None]:
        with self._lock:
            return [_copy(e.record) if (e := self._jobs.get(i)) else None for i in job_ids]

    async def wait(
        self, job_id: str, timeout_s: float, *, pending: bool = False
    ) -> JobRecord | None:
        entry = self._jobs.get(job_id)
        if entry is None:
            return None
        if timeout_s > 0 and entry.record.status not in TERMINAL:
            try:
                await asyncio.wait_for(entry.done.wait(), timeout_s)
            except TimeoutError:
                pass
        with self._lock:
            return _copy(entry.record)

    async def cancel(self, job_id: str) -> JobRecord | None:
        entry = self._jobs.get(job_id)
        if entry is None:
            return None
        with self._lock:
            record = entry.record
            if record.status is not JobState.queued:
                raise NotCancelable(record.status)
            record.status, record.finished_at = JobState.canceled, utcnow()
            entry.finished_mono = time.monotonic()
            self._queued -= 1
        if entry.future is not None:
            entry.future.cancel()
        self._wake(entry)
        return _copy(record)

    async def readiness(self) -> dict[str, Any]:
        return {"ready": True, "backend": self.mode, "workers": self._settings.embedded_workers}

    def depth_sync(self) -> int:
        return self._queued

    async def put_batch(self, batch_id: str, meta: dict[str, Any]) -> None:
        with self._lock:
            self._batches[batch_id] = (time.monotonic(), meta)

    async def get_batch(self, batch_id: str) -> dict[str, Any] | None:
        with self._lock:
            item = self._batches.get(batch_id)
        return None if item is None else item[1]

    def job_metrics(self) -> JobMetricsSnapshot:
        return self._metrics.snapshot()

    def _purge(self) -> None:
        """Forget finished jobs and batches older than the result TTL (at most once a second)."""
        now = time.monotonic()
        if now - self._last_purge < 1.0:
            return
        self._last_purge = now
        ttl = self._settings.result_ttl_s
        with self._lock:
            for job_id in [
                i for i, e in self._jobs.items()
                if e.finished_mono is not None and now - e.finished_mono > ttl
            ]:
                del self._jobs[job_id]
            for batch_id in [
                b for b, (t, meta) in self._batches.items() if now - t > meta["ttl_s"]
            ]:
                del self._batches[batch_id]

    async def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)


def _copy(record: JobRecord) -> JobRecord:
    return JobRecord(**vars(record))
