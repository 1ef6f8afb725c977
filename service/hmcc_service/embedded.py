"""The embedded queue (no ``REDIS_URL``): jobs run in the API's own child processes.

The API process parses requests and routes them; the pairs are verified by a
:class:`~hmcc_worker.pool.ComputePool` of ``HMCC_EMBEDDED_WORKERS`` child processes, on all
cores and without the GIL, and a pair that crashes native code costs that pair, never the API
(it is ``worker_crashed``; the pool replaces the child). One thread per child hands it jobs and
waits; a job's input is dropped once it ran. A child that dies idle is replaced too; if the
pool cannot be rebuilt (its children die at start), ``/readyz`` answers 503 and new jobs are
refused (503) rather than failed.

A batch's arrays go to the children once: its chunks are written to one shared file
(:func:`~hmcc_worker.shared_flight.shared_flight`, in memory where there is room) that each child
maps and reads its chunks' pairs and images from, so a chunk is handed over as a few indices
rather than pickled with its pairs' matches and its images' keypoints (images that many chunks
name were sent with each). The file is removed when the batch's last job ends.

Results are kept in memory for ``HMCC_RESULT_TTL_S`` (a batch's as long as the batch) and at
most ``HMCC_RESULT_MEMORY_MB`` megabytes of ended jobs, counting each job's own bookkeeping
(:data:`KEPT_JOB_BYTES`) besides its results: past that, the oldest ended jobs are forgotten
first (a pair job then reads 404, a batch's pairs ``expired``).
"""

from __future__ import annotations

import asyncio
import logging
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from hmcc.flight import Flight, FlightImage
from hmcc_schema.columns import PairColumns
from hmcc_worker.metrics import JobMetricsSnapshot, MemoryJobMetrics, children_cpu_s
from hmcc_worker.outcomes import StoredOutcomes, verify_flight_stored
from hmcc_worker.pool import CHILD_LOST, ComputePool, ComputePoolDead
from hmcc_worker.protocol import TERMINAL, ErrorCode, JobKind, JobStatus
from hmcc_worker.shared_flight import shared_flight

from . import shutdown
from .queue import (
    JobRecord,
    NotCancelable,
    QueueFull,
    QueueUnavailable,
    ShuttingDown,
    new_id,
    utcnow,
)
from .settings import Settings

__all__ = ["KEPT_JOB_BYTES", "EmbeddedQueue"]

log = logging.getLogger("hmcc.queue")

#: What an ended job holds besides its stored outcomes, as the memory bound counts it: its
#: entry, record, event and future, and its keys (measured with tracemalloc: about 3.3 KB;
#: the process's RSS grew by about 4.3 KB a job kept).
KEPT_JOB_BYTES = 4608


def _held_bytes(outcomes: list[bytes] | None) -> int:
    """The memory an ended job holds: :data:`KEPT_JOB_BYTES` and its stored outcomes (the
    bytes objects and the list, not only their lengths)."""
    if not outcomes:
        return KEPT_JOB_BYTES
    return KEPT_JOB_BYTES + sys.getsizeof(outcomes) + sum(map(sys.getsizeof, outcomes))


_POOL_DEAD = "the compute pool's children cannot be started again; restart the service"


@dataclass(eq=False)
class _SharedBatch:
    """A batch's shared file (removed when ``file`` is closed) and its jobs not ended yet."""

    file: ExitStack
    left: int


def _share(
    flights: Sequence[Flight], images: Mapping[str, FlightImage]
) -> tuple[list[Flight], _SharedBatch]:
    """The chunks ``flights`` of one batch (whose images are ``images``) written to one shared
    file; the chunks as shared flights of its pairs, and the file."""
    first = flights[0]
    # chunks of pairs as columns: the columns themselves (written to the file as they are)
    columns = PairColumns.joined([flight.pairs for flight in flights])
    whole = Flight(
        dict(images),
        columns if columns is not None else [pair for flight in flights for pair in flight.pairs],
        first.method,
        first.options,
        first.plane_z,
        first.ground_z,
        first.match_options,
    )
    file = ExitStack()
    shared = file.enter_context(shared_flight(whole))
    chunks: list[Flight] = []
    start = 0
    for flight in flights:
        chunks.append(shared.subset(range(start, start + len(flight.pairs))))
        start += len(flight.pairs)
    return chunks, _SharedBatch(file, len(flights))


def _int64_matches(flight: Flight) -> Flight:
    """``flight`` with its pairs' matches in the core's dtype, int64 (a batch's are parsed as
    sent, views of the body: :func:`hmcc_schema.parse_batch`'s ``views``)."""
    if all(p.matches.dtype == np.int64 for p in flight.pairs):
        return flight
    pairs = [
        p if p.matches.dtype == np.int64 else replace(p, matches=p.matches.astype(np.int64))
        for p in flight.pairs
    ]
    return replace(flight, pairs=pairs)


@dataclass
class _Entry:
    record: JobRecord
    flight: Flight | None
    ttl_s: float
    loop: asyncio.AbstractEventLoop
    done: asyncio.Event = field(default_factory=asyncio.Event)
    future: Future[None] | None = None
    outcomes: list[bytes] | None = None
    size: int = 0
    finished_mono: float | None = None
    #: The shared file of the batch this job is a chunk of, if any.
    batch: _SharedBatch | None = None


class EmbeddedQueue:
    """Jobs run by a pool of child processes; records expire ``result_ttl_s`` after they end."""

    mode = "embedded"

    def __init__(self, settings: Settings) -> None:
        self._settings = settings
        self._compute = ComputePool(settings.embedded_workers, timeout_s=settings.job_timeout_s)
        self._threads = ThreadPoolExecutor(settings.embedded_workers, thread_name_prefix="hmcc-job")
        self._jobs: dict[str, _Entry] = {}
        #: Finished jobs holding outcomes, oldest first (for the memory bound).
        self._kept: OrderedDict[str, int] = OrderedDict()
        self._kept_bytes = 0
        self._batches: dict[str, tuple[float, dict[str, Any]]] = {}
        #: The shared files of batches with jobs not ended.
        self._shared: set[_SharedBatch] = set()
        self._lock = threading.Lock()
        self._queued = 0
        self._last_purge = 0.0
        self._metrics = MemoryJobMetrics()

    def start(self) -> None:
        """Start the children now (they warm up: about a second each), not with the first job."""
        self._compute.start()

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
        self._purge()
        if self._compute.dead:
            raise QueueUnavailable(_POOL_DEAD)
        loop = asyncio.get_running_loop()
        ttl = float(ttl_s or self._settings.result_ttl_s)
        batch: _SharedBatch | None = None
        if kind is JobKind.chunk and batch_id is not None and images is not None and flights:
            try:
                flights, batch = await asyncio.to_thread(_share, flights, images)
            except OSError as e:  # no room for the file: the chunks are pickled as they are
                log.warning("a batch's shared file could not be written (%s)", e)
        if batch is None:
            flights = [_int64_matches(f) for f in flights]
        try:
            if shutdown.began():  # no await from here to the jobs' submission: none slips past
                raise ShuttingDown
            with self._lock:
                if self._queued + len(flights) > self._settings.max_queue_depth:
                    raise QueueFull
                self._queued += len(flights)
                entries = []
                for flight in flights:
                    record = JobRecord(
                        new_id(), kind, JobStatus.queued, utcnow(), pairs=len(flight.pairs)
                    )
                    entry = _Entry(record, flight, ttl, loop, batch=batch)
                    self._jobs[record.job_id] = entry
                    entries.append(entry)
                if batch is not None:
                    self._shared.add(batch)
        except BaseException:
            if batch is not None:
                batch.file.close()
            raise
        for entry in entries:
            entry.future = self._threads.submit(self._run, entry)
        return [replace(e.record) for e in entries]

    def _run(self, entry: _Entry) -> None:
        record = entry.record
        with self._lock:
            if record.status is not JobStatus.queued or entry.flight is None:
                return
            self._queued -= 1
            record.status, record.started_at = JobStatus.started, utcnow()
            flight, entry.flight = entry.flight, None
        t0 = time.perf_counter()
        stored = StoredOutcomes([], 0, {})
        error = None
        try:
            stored = self._verify(flight)
        except ComputePoolDead:
            log.error("job failed: %s", _POOL_DEAD, extra={"job_id": record.job_id})
            self._metrics.record_failure("ComputePoolDead")
            error = {"code": ErrorCode.internal_error.value, "message": _POOL_DEAD}
        except Exception:
            log.exception("job crashed", extra={"job_id": record.job_id})
            self._metrics.record_failure("exception")
            error = {"code": ErrorCode.internal_error.value, "message": "the job failed"}
        self._release(entry)
        self._metrics.add(stored.increments, time.perf_counter() - t0)
        with self._lock:
            entry.outcomes = stored.packed if error is None else None
            entry.size = _held_bytes(stored.packed)
            record.failed = stored.failed
            record.error = error
            record.status = JobStatus.finished if error is None else JobStatus.failed
            record.finished_at = utcnow()
            entry.finished_mono = time.monotonic()
            self._keep(record.job_id, entry.size)
        self._wake(entry)

    def _verify(self, flight: Flight) -> StoredOutcomes:
        """The job's outcomes, stored by the child that verified them; if the child dies or
        runs out of time, its pairs are run one by one (only the pair that killed it fails)."""
        try:
            return self._compute.call(verify_flight_stored, flight)
        except CHILD_LOST as e:
            return StoredOutcomes.of(self._compute.after_loss(flight, e))

    def _release(self, entry: _Entry) -> None:
        """The job no longer needs its batch's shared file: remove it after the batch's last."""
        batch = entry.batch
        if batch is None:
            return
        with self._lock:
            entry.batch = None
            batch.left -= 1
            last = batch.left == 0
            if last:
                self._shared.discard(batch)
        if last:
            batch.file.close()

    def _keep(self, job_id: str, size: int) -> None:
        """Account an ended job's memory (``size``: :func:`_held_bytes`); forget the oldest
        beyond the memory bound."""
        self._kept[job_id] = size
        self._kept_bytes += size
        limit = self._settings.result_memory_mb * 1024 * 1024
        while self._kept_bytes > limit and len(self._kept) > 1:
            old, old_size = self._kept.popitem(last=False)
            self._kept_bytes -= old_size
            self._jobs.pop(old, None)

    @staticmethod
    def _wake(entry: _Entry) -> None:
        if not entry.loop.is_closed():
            entry.loop.call_soon_threadsafe(entry.done.set)

    async def fetch(self, job_ids: Sequence[str]) -> list[JobRecord | None]:
        with self._lock:
            return [replace(e.record) if (e := self._jobs.get(i)) else None for i in job_ids]

    async def outcomes(self, ranges: Sequence[tuple[str, int, int]]) -> list[list[bytes] | None]:
        with self._lock:
            found = [self._jobs.get(job_id) for job_id, _, _ in ranges]
            return [
                None if e is None or e.outcomes is None else e.outcomes[start:stop]
                for e, (_, start, stop) in zip(found, ranges, strict=True)
            ]

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
            return replace(entry.record)

    async def wait_any(self, job_ids: Sequence[str], timeout_s: float) -> None:
        events = [e.done for i in job_ids if (e := self._jobs.get(i)) is not None]
        if not events or any(ev.is_set() for ev in events) or timeout_s <= 0:
            return
        waiters = [asyncio.ensure_future(ev.wait()) for ev in events]
        try:
            await asyncio.wait(waiters, timeout=timeout_s, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waiters:
                w.cancel()

    async def cancel(self, job_id: str) -> JobRecord | None:
        entry = self._jobs.get(job_id)
        if entry is None:
            return None
        with self._lock:
            record = entry.record
            if record.status is not JobStatus.queued:
                raise NotCancelable(record.status)
            record.status, record.finished_at = JobStatus.canceled, utcnow()
            entry.flight, entry.finished_mono = None, time.monotonic()
            self._queued -= 1
            entry.size = _held_bytes(None)
            self._keep(job_id, entry.size)
        if entry.future is not None:
            entry.future.cancel()
        self._release(entry)
        self._wake(entry)
        return replace(record)

    async def readiness(self) -> dict[str, Any]:
        """Ready while the pool has a live child, or has not started yet (without the app's
        lifespan it starts with the first job); ``workers``: its live children."""
        live = 0 if self._compute.dead else len(self._compute.live_children())
        ready = not self._compute.dead and (live > 0 or not self._compute.started)
        state: dict[str, Any] = {"ready": ready, "backend": self.mode, "workers": live}
        if self._compute.dead:
            state["error"] = _POOL_DEAD
        return state

    async def workers(self) -> int:
        return self._settings.embedded_workers

    def depth_sync(self) -> int:
        return self._queued

    def pending(self) -> int:
        """Jobs accepted and not ended (what a shutdown waits for)."""
        with self._lock:
            return sum(e.record.status not in TERMINAL for e in self._jobs.values())

    async def batch_ended(self, batch_id: str) -> None:
        return None  # each job holds its own images, dropped when it ends

    async def put_batch(self, batch_id: str, meta: dict[str, Any]) -> None:
        with self._lock:
            self._batches[batch_id] = (time.monotonic(), meta)

    async def get_batch(self, batch_id: str) -> dict[str, Any] | None:
        with self._lock:
            item = self._batches.get(batch_id)
        return None if item is None else item[1]

    def job_metrics(self) -> JobMetricsSnapshot:
        return self._metrics.snapshot()

    def compute_cpu_s(self) -> float | None:
        return children_cpu_s(self._compute.live_children())

    def _purge(self) -> None:
        """Forget ended jobs and batches past their TTL (at most once a second)."""
        now = time.monotonic()
        if now - self._last_purge < 1.0:
            return
        self._last_purge = now
        with self._lock:
            for job_id in [
                i
                for i, e in self._jobs.items()
                if e.finished_mono is not None and now - e.finished_mono > e.ttl_s
            ]:
                del self._jobs[job_id]
                self._kept_bytes -= self._kept.pop(job_id, 0)
            for batch_id in [
                b for b, (t, meta) in self._batches.items() if now - t > meta["ttl_s"]
            ]:
                del self._batches[batch_id]

    async def close(self) -> None:
        self._threads.shutdown(wait=False, cancel_futures=True)
        await asyncio.to_thread(self._compute.close, False)
        with self._lock:
            shared, self._shared = self._shared, set()
        for batch in shared:
            batch.file.close()
