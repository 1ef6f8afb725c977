"""The RQ backend of :mod:`hmcc_service.queue`: jobs on Redis, run by ``hmcc worker``.

Jobs carry JSON text (RQ's JSONSerializer), name only the functions the worker allow-lists,
and are enqueued with a timeout, result/failure TTLs, one retry, and a failure callback that
counts failures. Waiting (``?wait=``) blocks on the job's RQ result stream (``XREAD``), so a
finished job is answered within a Redis round trip, without polling.

Every Redis error becomes :class:`QueueUnavailable` (-> 503); the clients reconnect on the
next call, so the service recovers by itself when Redis returns.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import Any

import anyio.to_thread
import redis.asyncio
from redis import Redis
from redis.asyncio.retry import Retry as AsyncRetry
from redis.backoff import ExponentialBackoff
from redis.exceptions import RedisError
from redis.retry import Retry as RedisRetry
from rq import Callback, Queue, Retry, Worker
from rq.job import JobStatus
from rq.registry import StartedJobRegistry
from rq.results import Result
from rq.serializers import JSONSerializer
from rq.timeouts import TimerDeathPenalty
from rq.utils import str_to_date

from hmcc_worker.jobs import payload_key
from hmcc_worker.metrics import JobMetricsSnapshot, RedisJobMetrics
from hmcc_worker.payload import encode
from hmcc_worker.rq_worker import AllowlistedJob

from .queue import (
    TERMINAL,
    JobKind,
    JobRecord,
    JobState,
    NotCancelable,
    Payload,
    QueueFull,
    QueueUnavailable,
    new_id,
)
from .settings import Settings

__all__ = ["RQQueue"]

_FUNCTIONS = {
    "pair": "hmcc_worker.jobs.verify_pair_job",
    "chunk": "hmcc_worker.jobs.verify_chunk_job",
}
_ON_FAILURE = "hmcc_worker.jobs.on_job_failure"
_ON_SUCCESS = "hmcc_worker.jobs.on_job_success"
_STATES = {
    JobStatus.CREATED: JobState.queued,
    JobStatus.QUEUED: JobState.queued,
    JobStatus.DEFERRED: JobState.queued,
    JobStatus.SCHEDULED: JobState.queued,
    JobStatus.STARTED: JobState.started,
    JobStatus.FINISHED: JobState.finished,
    JobStatus.FAILED: JobState.failed,
    JobStatus.STOPPED: JobState.failed,
    JobStatus.CANCELED: JobState.canceled,
}
_BATCH_KEY = "hmcc:batch:{}"


class RQQueue:
    mode = "rq"

    def __init__(self, settings: Settings) -> None:
        assert settings.redis_url
        self._settings = settings
        # Fail fast when Redis is away (a refused connection is instant on the same host),
        # absorb a blip with two quick retries.
        retry = RedisRetry(ExponentialBackoff(cap=0.05, base=0.01), 2)
        self._redis = Redis.from_url(
            settings.redis_url, socket_connect_timeout=1, socket_timeout=5, retry=retry
        )
        self._aredis = redis.asyncio.Redis.from_url(
            settings.redis_url,
            socket_connect_timeout=1,
            socket_timeout=5,
            retry=AsyncRetry(ExponentialBackoff(cap=0.05, base=0.01), 2),
        )
        self._queue = Queue(
            settings.queue_name,
            connection=self._redis,
            serializer=JSONSerializer,
            job_class=AllowlistedJob,
        )
        self._last_cleanup = 0.0

    # -- jobs ---------------------------------------------------------------------------------

    async def submit(self, kind: JobKind, payloads: Sequence[Payload]) -> list[JobRecord]:
        return await anyio.to_thread.run_sync(self._submit, kind, payloads)

    def _submit(self, kind: JobKind, payloads: Sequence[Payload]) -> list[JobRecord]:
        s = self._settings
        try:
            if self._queue.count + len(payloads) > s.max_queue_depth:
                raise QueueFull
            blobs = [encode(p) for p in payloads]  # off the event loop
            ids = [new_id() for _ in blobs]
            datas = [
                Queue.prepare_data(
                    _FUNCTIONS[kind],
                    timeout=s.job_timeout_s,
                    result_ttl=s.result_ttl_s,
                    failure_ttl=s.failure_ttl_s,
                    retry=Retry(max=1),
                    on_success=Callback(_ON_SUCCESS),
                    on_failure=Callback(_ON_FAILURE),
                    job_id=job_id,
                    description=f"{kind} job",
                    meta={"kind": kind},
                )
                for job_id in ids
            ]
            # One transaction: the inputs, then the jobs that read them.
            with self._redis.pipeline() as pipe:
                for job_id, blob in zip(ids, blobs, strict=True):
                    pipe.set(payload_key(job_id), blob, ex=s.failure_ttl_s)
                jobs = self._queue.enqueue_many(datas, pipeline=pipe)
                pipe.execute()
        except RedisError as e:
            raise QueueUnavailable from e
        return [JobRecord(job.id, kind, JobState.queued, job.created_at) for job in jobs]

    async def fetch(
        self, job_ids: list[str], with_outcome: bool = True
    ) -> list[JobRecord | None]:
        """Status fields of the job hashes (never the input), then the latest result of each
        ended job: one pipelined round trip each, on the async client (no thread hop)."""
        try:
            records = await self._fetch_once(job_ids, with_outcome)
            if any(r is not None and r.status is JobState.started for r in records):
                if await anyio.to_thread.run_sync(self._cleanup_started):
                    records = await self._fetch_once(job_ids, with_outcome)
        except RedisError as e:
            raise QueueUnavailable from e
        return records

    async def _fetch_once(
        self, job_ids: list[str], with_outcome: bool
    ) -> list[JobRecord | None]:
        async with self._aredis.pipeline(transaction=False) as pipe:
            for job_id in job_ids:
                pipe.hmget(AllowlistedJob.key_for(job_id), _FIELDS)
            rows = await pipe.execute()
        records: list[JobRecord | None] = [
            None if row[0] is None else _record(job_id, row)
            for job_id, row in zip(job_ids, rows, strict=True)
        ]
        ended = [r for r in records if r is not None and r.status in (
            JobState.finished, JobState.failed)]
        if not ended:
            return records
        async with self._aredis.pipeline(transaction=False) as pipe:
            for r in ended:
                pipe.xrevrange(Result.get_key(r.job_id), "+", "-", count=1)
            raws = await pipe.execute()
        for record, raw in zip(ended, raws, strict=True):
            self._attach_result(record, raw[0] if raw else None, with_outcome)
        return records

    def _attach_result(
        self, record: JobRecord, entry: tuple[bytes, dict[bytes, bytes]] | None,
        with_outcome: bool,
    ) -> None:
        """Set the outcome (finished) or the error (failed) from the latest result entry."""
        result = None
        if entry is not None:
            result_id, payload = entry
            if record.status is JobState.failed or with_outcome:
                result = Result.restore(
                    record.job_id, result_id.decode(), payload, self._redis, JSONSerializer
                )
            elif int(payload.get(b"type", 0)) == Result.Type.SUCCESSFUL.value:
                return  # finished, outcome not asked for
        if record.status is JobState.finished:
            if result is not None and result.type == Result.Type.SUCCESSFUL:
                record.outcome = result.return_value
            else:
                record.status = JobState.failed
                record.error = {"code": "result_missing", "message": "the result has expired"}
        else:
            record.error = self._failure(result)

    def _failure(self, result: Result | None) -> dict[str, str]:
        text = (result.exc_string or "") if result is not None else ""
        if "AbandonedJobError" in text:
            return {
                "code": "worker_lost",
                "message": "the worker running this job stopped; it was retried once and "
                "the retry did not finish either",
            }
        if "PayloadExpired" in text:
            return {
                "code": "payload_expired",
                "message": "the job's input expired before a worker took it (HMCC_FAILURE_TTL_S)",
            }
        if "JobTimeoutException" in text:
            return {
                "code": "timeout",
                "message": f"the job ran longer than {self._settings.job_timeout_s} s "
                "(HMCC_JOB_TIMEOUT_S)",
            }
        return {"code": "internal_error", "message": "the job failed (retried once)"}

    def _cleanup_started(self) -> bool:
        """Retry or fail jobs whose worker died (at most once a second). True if it ran."""
        now = time.monotonic()
        if now - self._last_cleanup < 1.0:
            return False
        self._last_cleanup = now
        # TimerDeathPenalty: this runs in a thread, where SIGALRM (RQ's default) cannot.
        StartedJobRegistry(queue=self._queue, death_penalty_class=TimerDeathPenalty).cleanup()
        return True

    async def wait(
        self, job_id: str, timeout_s: float, *, pending: bool = False
    ) -> JobRecord | None:
        """``pending``: the caller knows the job exists and has not ended (just submitted),
        so the first look is the blocking read, not a fetch."""
        deadline = time.monotonic() + timeout_s
        stream = Result.get_key(job_id)
        last_id: Any = "0-0"
        look = not pending
        while True:
            if look:
                record = (await self.fetch([job_id]))[0]
                remaining = deadline - time.monotonic()
                if record is None or record.status in TERMINAL or remaining <= 0:
                    return record
            remaining = max(0.0, deadline - time.monotonic())
            # Wake on the next result entry; re-check at least every second so that a job
            # whose worker died is noticed (and retried) while we wait.
            block_ms = max(1, int(min(remaining, 1.0) * 1000))
            try:
                reply: Any = await self._aredis.xread(
                    {stream: last_id}, count=1, block=block_ms
                )
                if reply:
                    entry = reply[0][1][-1]
                    last_id = entry[0]
                    record = await self._ended(job_id, entry)
                    if record is not None:
                        return record
            except RedisError as e:
                raise QueueUnavailable from e
            look = True

    async def _ended(
        self, job_id: str, entry: tuple[bytes, dict[bytes, bytes]]
    ) -> JobRecord | None:
        """The job, if the result entry just read ended it (the entry is the result: no
        second read); None when it did not (a retry was recorded)."""
        row: Any = await self._aredis.hmget(AllowlistedJob.key_for(job_id), _FIELDS)
        if row[0] is None:
            return None
        record = _record(job_id, row)
        if record.status not in (JobState.finished, JobState.failed):
            return None
        self._attach_result(record, entry, with_outcome=True)
        return record

    async def cancel(self, job_id: str) -> JobRecord | None:
        if not await anyio.to_thread.run_sync(self._cancel, job_id):
            return None
        return (await self.fetch([job_id]))[0]

    def _cancel(self, job_id: str) -> bool:
        try:
            jobs = AllowlistedJob.fetch_many(
                [job_id], connection=self._redis, serializer=JSONSerializer
            )
            job = jobs[0]
            if job is None:
                return False
            status = _STATES.get(job.get_status(refresh=True), JobState.queued)
            if status is not JobState.queued:
                raise NotCancelable(status)
            job.cancel()
        except RedisError as e:
            raise QueueUnavailable from e
        return True

    # -- health and metrics -------------------------------------------------------------------

    async def readiness(self) -> dict[str, Any]:
        return await anyio.to_thread.run_sync(self._readiness)

    def _readiness(self) -> dict[str, Any]:
        try:
            self._redis.ping()
            workers = len(Worker.all(queue=self._queue))
            depth = self._queue.count
        except RedisError:
            return {"ready": False, "backend": self.mode, "redis": "unreachable", "workers": 0}
        return {
            "ready": workers > 0,
            "backend": self.mode,
            "redis": "ok",
            "workers": workers,
            "queued": depth,
        }

    def depth_sync(self) -> int:
        try:
            return int(self._queue.count)
        except RedisError as e:
            raise QueueUnavailable from e

    def job_metrics(self) -> JobMetricsSnapshot:
        try:
            return RedisJobMetrics(self._redis).snapshot()
        except RedisError as e:
            raise QueueUnavailable from e

    # -- batches ------------------------------------------------------------------------------

    async def put_batch(self, batch_id: str, meta: dict[str, Any]) -> None:
        try:
            await self._aredis.set(_BATCH_KEY.format(batch_id), json.dumps(meta), ex=meta["ttl_s"])
        except RedisError as e:
            raise QueueUnavailable from e

    async def get_batch(self, batch_id: str) -> dict[str, Any] | None:
        try:
            raw = await self._aredis.get(_BATCH_KEY.format(batch_id))
        except RedisError as e:
            raise QueueUnavailable from e
        return None if raw is None else json.loads(raw)

    async def close(self) -> None:
        await self._aredis.aclose()
        self._redis.close()


_FIELDS = ["status", "created_at", "started_at", "ended_at", "meta"]


def _status(raw: bytes | None) -> JobStatus | None:
    try:
        return JobStatus(raw.decode()) if raw else None
    except ValueError:  # a status this RQ does not know: treat the job as waiting
        return None


def _record(job_id: str, row: list[bytes | None]) -> JobRecord:
    status_raw, created, started, ended, meta_raw = row
    rq_status = _status(status_raw)
    status = JobState.queued if rq_status is None else _STATES.get(rq_status, JobState.queued)
    meta = json.loads(meta_raw) if meta_raw else {}
    return JobRecord(
        job_id,
        "chunk" if meta.get("kind") == "chunk" else "pair",
        status,
        str_to_date(created) if created else datetime.now(UTC),
        str_to_date(started) if started and status is not JobState.queued else None,
        str_to_date(ended) if ended and status in TERMINAL else None,
        failed_items=meta.get("failed_items"),
    )
