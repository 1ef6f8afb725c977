"""The RQ backend of :mod:`hmcc_service.queue`: jobs on Redis, run by ``hmcc worker``.

* **Input**: each job's flight as a binary payload (``PAYLOAD_KEY``, :mod:`hmcc_worker.payload`);
  a batch stores its images once (``IMAGES_KEY``, one hash field each) and its chunks only name
  them. The RQ job itself carries no input (RQ compresses and rewrites job data).
* **Enqueueing** checks the queue depth and enqueues in one optimistic transaction (``WATCH``
  on the queue list), so concurrent submitters cannot overshoot ``HMCC_MAX_QUEUE_DEPTH``.
  Jobs name only the functions workers allow-list, with one retry (for a lost worker) and
  callbacks that free the input and classify failures.
* **Outcomes**: the worker stores one document per pair (``OUTCOMES_KEY``); the API reads the
  page it answers and splices the bytes. Waiting (``?wait=``) blocks on the jobs' RQ result
  streams (``XREAD``), so an ended job is answered within a round trip, without polling.

Every Redis error becomes :class:`QueueUnavailable` (-> 503); the clients reconnect on the
next call, so the service recovers by itself when Redis returns.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from datetime import UTC, datetime
from typing import Any

import anyio.to_thread
import orjson
import redis.asyncio
from redis import Redis
from redis._parsers import Encoder
from redis.asyncio.retry import Retry as AsyncRetry
from redis.backoff import ExponentialBackoff
from redis.connection import PythonRespSerializer
from redis.exceptions import RedisError, WatchError
from redis.retry import Retry as RedisRetry
from rq import Callback, Queue, Retry, Worker
from rq.job import JobStatus as RQStatus
from rq.serializers import JSONSerializer

from hmcc.flight import Flight, FlightImage
from hmcc_schema.columns import PairColumns
from hmcc_worker import rq_compat
from hmcc_worker.metrics import JobMetricsSnapshot, RedisJobMetrics
from hmcc_worker.payload import encode_flight, encode_image
from hmcc_worker.protocol import (
    BATCH_KEY,
    IMAGES_KEY,
    JOB_FUNCTION,
    ON_FAILURE,
    ON_SUCCESS,
    OUTCOMES_KEY,
    PAYLOAD_KEY,
    TERMINAL,
    WORKER_CHILDREN_FIELD,
    WORKER_FRESH_S,
    ErrorCode,
    JobKind,
    JobStatus,
)

from .queue import JobRecord, NotCancelable, QueueFull, QueueUnavailable, new_id
from .settings import Settings

__all__ = ["RQQueue"]

_STATES = {
    RQStatus.CREATED: JobStatus.queued,
    RQStatus.QUEUED: JobStatus.queued,
    RQStatus.DEFERRED: JobStatus.queued,
    RQStatus.SCHEDULED: JobStatus.queued,
    RQStatus.STARTED: JobStatus.started,
    RQStatus.FINISHED: JobStatus.finished,
    RQStatus.FAILED: JobStatus.failed,
    RQStatus.STOPPED: JobStatus.failed,
    RQStatus.CANCELED: JobStatus.canceled,
}
#: Attempts of the enqueue transaction before giving up (each retry follows another client's
#: change of the queue; thousands of changes a second would be needed to exhaust them).
_ENQUEUE_ATTEMPTS = 100
#: Values above this many bytes are sent as they are, not copied into the command's buffer.
_BUFFER_CUTOFF = 6000


class RQQueue:
    mode = "rq"

    def __init__(self, settings: Settings) -> None:
        assert settings.redis_url
        self._settings = settings
        # Fail fast when Redis is away (a refused connection is instant on the same host),
        # absorb a blip with two quick retries.
        retry = RedisRetry(ExponentialBackoff(cap=0.05, base=0.01), 2)
        # Replies are parsed by hiredis; commands are packed in Python, which sends a large
        # value (a job's input) as it is: hiredis's packer copies it, at about 2.5 ms a MB.
        encoder = Encoder(encoding="utf-8", encoding_errors="strict", decode_responses=False)
        self._redis = Redis.from_url(
            settings.redis_url,
            socket_connect_timeout=1,
            socket_timeout=5,
            retry=retry,
            command_packer=PythonRespSerializer(_BUFFER_CUTOFF, encoder.encode),
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
            job_class=rq_compat.AllowlistedJob,
        )
        self._last_cleanup = 0.0

    # -- jobs ---------------------------------------------------------------------------------

    async def submit(
        self,
        kind: JobKind,
        flights: Sequence[Flight],
        *,
        batch_id: str | None = None,
        images: Mapping[str, FlightImage] | None = None,
        ttl_s: int | None = None,
    ) -> list[JobRecord]:
        return await anyio.to_thread.run_sync(
            lambda: self._submit(kind, flights, batch_id, images, ttl_s)
        )

    def _submit(
        self,
        kind: JobKind,
        flights: Sequence[Flight],
        batch_id: str | None,
        images: Mapping[str, FlightImage] | None,
        ttl_s: int | None,
    ) -> list[JobRecord]:
        s = self._settings
        ttl = ttl_s or s.result_ttl_s
        input_ttl = max(s.failure_ttl_s, ttl)
        chunked = batch_id is not None and images is not None
        ids = [new_id() for _ in flights]
        datas = [
            Queue.prepare_data(
                JOB_FUNCTION,
                # The compute pool bounds each pair by job_timeout_s; RQ's own bound is the
                # backstop for the whole job (a chunk re-run pair by pair after a crash).
                timeout=s.job_timeout_s * (len(flight.pairs) + 1),
                result_ttl=ttl,
                failure_ttl=max(s.failure_ttl_s, ttl),
                retry=Retry(max=1),
                on_success=Callback(ON_SUCCESS),
                on_failure=Callback(ON_FAILURE),
                job_id=job_id,
                description=f"{kind.value} job",
                meta={"kind": kind.value, "pairs": len(flight.pairs), "batch": batch_id},
            )
            for job_id, flight in zip(ids, flights, strict=True)
        ]
        blobs = [encode_flight(_as_sent(f), images=not chunked) for f in flights]  # off the loop
        try:
            # The inputs first (they are useless without their jobs, and expire), then the
            # depth check and the jobs in one transaction: retrying it re-sends little.
            with self._redis.pipeline(transaction=False) as pipe:
                for job_id, blob in zip(ids, blobs, strict=True):
                    pipe.set(PAYLOAD_KEY.format(job_id=job_id), blob, ex=input_ttl)
                if chunked:
                    assert batch_id is not None and images is not None
                    key = IMAGES_KEY.format(batch_id=batch_id)
                    pipe.hset(key, mapping={n: encode_image(im) for n, im in images.items()})
                    pipe.expire(key, input_ttl)
                pipe.execute()
            jobs = self._enqueue_within_depth(datas)
        except QueueFull:
            self._forget_inputs(ids, batch_id if chunked else None)
            raise
        except RedisError as e:
            raise QueueUnavailable from e
        return [
            JobRecord(job.id, kind, JobStatus.queued, job.created_at, pairs=len(f.pairs))
            for job, f in zip(jobs, flights, strict=True)
        ]

    def _enqueue_within_depth(self, datas: list[Any]) -> list[Any]:
        """Enqueue unless the queue would hold more than ``max_queue_depth`` jobs, atomically:
        the depth is read under ``WATCH`` and a concurrent change makes the transaction fail
        and start again."""
        with self._redis.pipeline() as pipe:
            for _ in range(_ENQUEUE_ATTEMPTS):
                try:
                    pipe.watch(self._queue.key)
                    depth = int(pipe.llen(self._queue.key))
                    if depth + len(datas) > self._settings.max_queue_depth:
                        pipe.unwatch()
                        raise QueueFull
                    pipe.multi()
                    jobs = self._queue.enqueue_many(datas, pipeline=pipe)
                    pipe.execute()
                    return jobs
                except WatchError:
                    continue
        raise QueueUnavailable("the queue changed too often to enqueue")

    def _forget_inputs(self, ids: list[str], batch_id: str | None) -> None:
        keys = [PAYLOAD_KEY.format(job_id=i) for i in ids]
        if batch_id is not None:
            keys.append(IMAGES_KEY.format(batch_id=batch_id))
        self._redis.delete(*keys)

    async def fetch(self, job_ids: Sequence[str]) -> list[JobRecord | None]:
        """Status fields of the job hashes (one pipelined round trip); a started job whose
        worker died is retried or failed here first (the registry cleanup)."""
        try:
            records = await self._fetch_once(job_ids)
            if any(r is not None and r.status is JobStatus.started for r in records):
                if await anyio.to_thread.run_sync(self._cleanup_started):
                    records = await self._fetch_once(job_ids)
        except RedisError as e:
            raise QueueUnavailable from e
        return records

    async def _fetch_once(self, job_ids: Sequence[str]) -> list[JobRecord | None]:
        async with self._aredis.pipeline(transaction=False) as pipe:
            for job_id in job_ids:
                pipe.hmget(rq_compat.job_key(job_id), rq_compat.JOB_RECORD_FIELDS)
            rows = await pipe.execute()
        return [
            None if row[0] is None else _record(job_id, row)
            for job_id, row in zip(job_ids, rows, strict=True)
        ]

    async def outcomes(self, ranges: Sequence[tuple[str, int, int]]) -> list[list[bytes] | None]:
        try:
            async with self._aredis.pipeline(transaction=False) as pipe:
                for job_id, start, stop in ranges:
                    pipe.exists(OUTCOMES_KEY.format(job_id=job_id))
                    pipe.lrange(OUTCOMES_KEY.format(job_id=job_id), start, stop - 1)
                replies = await pipe.execute()
        except RedisError as e:
            raise QueueUnavailable from e
        return [
            list(items) if exists else None
            for exists, items in zip(replies[::2], replies[1::2], strict=True)
        ]

    def _cleanup_started(self) -> bool:
        """Retry or fail jobs whose worker died (at most once a second). True if it ran."""
        now = time.monotonic()
        if now - self._last_cleanup < 1.0:
            return False
        self._last_cleanup = now
        rq_compat.cleanup_abandoned(self._queue)
        return True

    async def wait(
        self, job_id: str, timeout_s: float, *, pending: bool = False
    ) -> JobRecord | None:
        """``pending``: the caller knows the job exists and has not ended (just submitted),
        so the first look is the blocking read, not a fetch."""
        deadline = time.monotonic() + timeout_s
        stream = rq_compat.results_stream_key(job_id)
        position: Any = "0-0"  # a result entry written before we block is read at once
        look = not pending
        while True:
            if look:
                record = (await self.fetch([job_id]))[0]
                if record is None or record.status in TERMINAL or time.monotonic() >= deadline:
                    return record
            entries = await self._block({stream: position}, deadline - time.monotonic())
            if entries:
                position = entries[0][1][-1][0]  # read on from there (a retried attempt)
            look = True

    async def wait_any(self, job_ids: Sequence[str], timeout_s: float) -> None:
        if job_ids and timeout_s > 0:
            await self._block({rq_compat.results_stream_key(i): "$" for i in job_ids}, timeout_s)

    async def _block(self, streams: dict[Any, Any], seconds: float) -> Any:
        """Until a result entry arrives on one of ``streams`` (name -> position), or for
        ``seconds`` (at most one: a caller re-checks, so a job whose worker died is noticed and
        retried while it waits). Returns what XREAD read."""
        block_ms = max(1, int(min(max(seconds, 0.0), 1.0) * 1000))
        try:
            return await self._aredis.xread(streams, count=1, block=block_ms)
        except RedisError as e:
            raise QueueUnavailable from e

    async def cancel(self, job_id: str) -> JobRecord | None:
        if not await anyio.to_thread.run_sync(self._cancel, job_id):
            return None
        return (await self.fetch([job_id]))[0]

    def _cancel(self, job_id: str) -> bool:
        try:
            job = rq_compat.AllowlistedJob.fetch_many(
                [job_id], connection=self._redis, serializer=JSONSerializer
            )[0]
            if job is None:
                return False
            status = _STATES.get(job.get_status(refresh=True), JobStatus.queued)
            if status is not JobStatus.queued:
                raise NotCancelable(status)
            job.cancel()
            job.meta["ended"] = datetime.now(UTC).isoformat()
            job.save_meta()
            self._redis.delete(PAYLOAD_KEY.format(job_id=job_id))
        except RedisError as e:
            raise QueueUnavailable from e
        return True

    # -- health and metrics -------------------------------------------------------------------

    async def readiness(self) -> dict[str, Any]:
        return await anyio.to_thread.run_sync(self._readiness)

    def _readiness(self) -> dict[str, Any]:
        """Ready when Redis answers and a worker with a live compute child beat recently."""
        try:
            self._redis.ping()
            alive = self._alive_workers()
            depth = self._queue.count
        except RedisError:
            return {"ready": False, "backend": "rq", "redis": "unreachable", "workers": 0}
        return {
            "ready": alive > 0,
            "backend": "rq",
            "redis": "ok",
            "workers": alive,
            "queued": depth,
        }

    async def workers(self) -> int:
        try:
            return await anyio.to_thread.run_sync(self._alive_workers)
        except RedisError as e:
            raise QueueUnavailable from e

    def _alive_workers(self) -> int:
        """The workers with a live compute child that beat recently (a SIGKILLed worker's
        registration lingers until it expires; its heartbeat stops at once; a worker reports
        its live children with each heartbeat)."""
        workers = Worker.all(queue=self._queue)
        with self._redis.pipeline(transaction=False) as pipe:
            for w in workers:
                pipe.hget(w.key, WORKER_CHILDREN_FIELD)
            children = pipe.execute()
        now = datetime.now(UTC)
        return sum(
            1
            for w, n in zip(workers, children, strict=True)
            if w.last_heartbeat is not None
            and (now - w.last_heartbeat).total_seconds() <= WORKER_FRESH_S
            and (n is None or int(n) != 0)  # None: a worker that does not report them
        )

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

    def compute_cpu_s(self) -> float | None:
        return None  # the workers' children compute, on their own machines

    # -- batches ------------------------------------------------------------------------------

    async def put_batch(self, batch_id: str, meta: dict[str, Any]) -> None:
        try:
            await self._aredis.set(
                BATCH_KEY.format(batch_id=batch_id), orjson.dumps(meta), ex=meta["ttl_s"]
            )
        except RedisError as e:
            raise QueueUnavailable from e

    async def get_batch(self, batch_id: str) -> dict[str, Any] | None:
        try:
            raw = await self._aredis.get(BATCH_KEY.format(batch_id=batch_id))
        except RedisError as e:
            raise QueueUnavailable from e
        return None if raw is None else dict(orjson.loads(raw))

    async def batch_ended(self, batch_id: str) -> None:
        # no job of the batch reads its images any more (an ended job is not retried)
        try:
            await self._aredis.delete(IMAGES_KEY.format(batch_id=batch_id))
        except RedisError as e:
            raise QueueUnavailable from e

    async def close(self) -> None:
        await self._aredis.aclose()
        self._redis.close()


def _as_sent(flight: Flight) -> Flight:
    """A flight whose pairs are columns with its pairs as rows, each pair's matches as sent (a
    view of the column: the payload converts them once, not each pair to int64 first)."""
    if isinstance(flight.pairs, PairColumns):
        return replace(flight, pairs=flight.pairs.as_sent())
    return flight


def _status(raw: bytes | None) -> RQStatus | None:
    try:
        return RQStatus(raw.decode()) if raw else None
    except ValueError:  # a status this RQ does not know: treat the job as waiting
        return None


def _record(job_id: str, row: list[bytes | None]) -> JobRecord:
    status_raw, created, started, ended, meta_raw = row
    rq_status = _status(status_raw)
    status = JobStatus.queued if rq_status is None else _STATES.get(rq_status, JobStatus.queued)
    meta = orjson.loads(meta_raw) if meta_raw else {}
    ended_at = rq_compat.record_time(ended)
    if ended_at is None and meta.get("ended"):
        ended_at = datetime.fromisoformat(meta["ended"])
    error = None
    if status is JobStatus.failed:
        error = meta.get("error") or {
            "code": ErrorCode.internal_error.value,
            "message": "the job failed",
        }
    return JobRecord(
        job_id,
        JobKind(meta.get("kind", "pair")),
        status,
        rq_compat.record_time(created) or datetime.now(UTC),
        rq_compat.record_time(started) if status is not JobStatus.queued else None,
        ended_at if status in TERMINAL else None,
        pairs=int(meta.get("pairs", 1)),
        failed=meta.get("failed"),
        error=error,
    )
