"""The job an RQ worker runs, and the callbacks RQ calls around it (the only functions a worker
runs: :data:`JOB_FUNCTIONS`).

:func:`verify_job` reads the job's input (``PAYLOAD_KEY``, and the batch's images it names),
has the worker's :class:`~hmcc_worker.pool.ComputePool` verify it, and stores one outcome
document per pair under ``OUTCOMES_KEY`` for as long as the job's result lives, with the pairs'
metrics; RQ keeps only a small summary. A pair that crashed or timed out is an outcome like any
other, so a job ends ``finished`` unless it could not run at all:

* its input expired before a worker took it (:class:`PayloadExpired` -> ``payload_expired``);
* its input is not a payload of ours (``ValueError`` -> ``internal_error``);
* its worker died (RQ's registry cleanup: retried once, then ``worker_lost``).

:func:`on_job_failure` classifies those by exception type into the job's ``meta["error"]``,
which the API reads.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from datetime import UTC, datetime
from typing import Any

from redis import Redis

from hmcc.flight import Flight, FlightImage

from . import rq_compat
from .metrics import RedisJobMetrics
from .outcomes import PairOutcome, verify_flight
from .payload import decode_flight, decode_image, image_names
from .pool import CHILD_LOST, ComputePool, describe
from .protocol import IMAGES_KEY, OUTCOMES_KEY, PAYLOAD_KEY, ErrorCode, JobStatus

__all__ = [
    "JOB_FUNCTIONS",
    "PayloadExpired",
    "classify_failure",
    "on_job_failure",
    "on_job_success",
    "set_compute",
    "verify_job",
    "verify_stored",
]

log = logging.getLogger("hmcc.worker")

_compute: ComputePool | None = None
_redis_url: str | None = None
#: Decoded images of recent batches, so the chunks of a batch do not fetch them again (in the
#: compute child, which reads its jobs' input itself; in the worker when it re-runs a chunk).
_images: OrderedDict[tuple[str, str], FlightImage] = OrderedDict()
_IMAGE_CACHE = 512
#: ... and at most this many bytes of their arrays (16 000 SIFT descriptors are 2 MB an image).
_IMAGE_CACHE_BYTES = 512 * 1024 * 1024
_image_bytes = 0
#: The compute child's own connection, by URL.
_connections: dict[str, Redis] = {}


class PayloadExpired(RuntimeError):
    """A job's input is gone (it waited longer than its TTL)."""


def set_compute(pool: ComputePool, redis_url: str) -> None:
    """The pool this process's jobs run on, and the Redis its children read their input from
    (set by the worker at start)."""
    global _compute, _redis_url
    _compute, _redis_url = pool, redis_url


def verify_job() -> dict[str, int]:
    """RQ: verify the input stored for this job; returns ``{"pairs", "failed"}``.

    The compute child reads the input, verifies it, stores the outcomes and counts the pairs'
    metrics itself, and hands back two counts: neither the arrays nor the outcomes pass
    through this process (no decode here, no pickling of a chunk and its images to the child;
    the child keeps the batch's decoded images across its chunks), which is left RQ's own work
    and the job's time. If the child dies or runs out of time, this process reads the input
    and has its pairs run one by one, so only the pair that killed the child fails."""
    t0 = time.perf_counter()
    job = rq_compat.current_job()
    if _compute is None or _redis_url is None:
        raise RuntimeError("verify_job runs in an hmcc worker (no compute pool here)")
    ttl = job.result_ttl if job.result_ttl and job.result_ttl > 0 else 3600
    batch = job.meta.get("batch")
    try:
        pairs, failed = _compute.call(verify_stored, _redis_url, job.id, batch, ttl)
    except CHILD_LOST as e:
        log.warning("job %s: its compute child %s", job.id, describe(e))
        outcomes = _compute.after_loss(_load(job.connection, job.id, batch), e)
        _store(job.connection, job.id, outcomes, ttl)
        pairs, failed = _counts(outcomes)
    job.meta["failed"] = failed
    job.save_meta()
    RedisJobMetrics(job.connection).record((), time.perf_counter() - t0)
    return {"pairs": pairs, "failed": failed}


def verify_stored(redis_url: str, job_id: str, batch_id: str | None, ttl: int) -> tuple[int, int]:
    """In the compute child: read job ``job_id``'s input, verify it, store its outcomes and
    count its pairs' metrics (in one transaction); returns ``(pairs, failed pairs)``, all the
    worker needs of them. (A child killed by the timeout between that transaction and its
    answer has its pairs re-run by the worker, which stores and counts them again.)"""
    connection = _connections.get(redis_url)
    if connection is None:
        connection = _connections[redis_url] = Redis.from_url(
            redis_url, socket_connect_timeout=2, socket_keepalive=True
        )
    outcomes = verify_flight(_load(connection, job_id, batch_id))
    _store(connection, job_id, outcomes, ttl)
    return _counts(outcomes)


def _counts(outcomes: list[PairOutcome]) -> tuple[int, int]:
    return len(outcomes), sum(o.status is JobStatus.failed for o in outcomes)


def _load(connection: Any, job_id: str, batch_id: str | None) -> Flight:
    raw = connection.get(PAYLOAD_KEY.format(job_id=job_id))
    if not isinstance(raw, bytes):
        raise PayloadExpired(job_id)
    names = image_names(raw)
    images = _fetch_images(connection, batch_id, names) if names else None
    return decode_flight(raw, images)


def _store(connection: Any, job_id: str, outcomes: list[PairOutcome], ttl: int) -> None:
    """The outcomes, for ``ttl`` seconds, and the pairs' metrics, at once."""
    key = OUTCOMES_KEY.format(job_id=job_id)
    with connection.pipeline() as pipe:
        pipe.delete(key)
        pipe.rpush(key, *(o.pack() for o in outcomes))
        pipe.expire(key, ttl)
        RedisJobMetrics(connection).record(outcomes, pipeline=pipe)
        pipe.execute()


def _fetch_images(
    connection: Any, batch_id: str | None, names: list[str]
) -> dict[str, FlightImage]:
    """The named images of a batch, from the cache or (the rest, in one round trip) Redis."""
    if batch_id is None:
        raise ValueError("a chunk without its batch")
    key = IMAGES_KEY.format(batch_id=batch_id)
    found = {n: _images[(key, n)] for n in names if (key, n) in _images}
    missing = [n for n in names if n not in found]
    if missing:
        blobs = connection.hmget(key, missing)
        if any(b is None for b in blobs):
            raise PayloadExpired(batch_id)
        global _image_bytes
        for name, blob in zip(missing, blobs, strict=True):
            found[name] = _images[(key, name)] = decode_image(blob)
            _image_bytes += _nbytes(found[name])
            while len(_images) > 1 and (
                len(_images) > _IMAGE_CACHE or _image_bytes > _IMAGE_CACHE_BYTES
            ):
                _image_bytes -= _nbytes(_images.popitem(last=False)[1])
    for name in names:
        if (key, name) in _images:  # a chunk's images beyond the bound: its first went
            _images.move_to_end((key, name))
    return found


def _nbytes(image: FlightImage) -> int:
    return sum(a.nbytes for a in (image.keypoints, image.descriptors) if a is not None)


def classify_failure(exc_type: type[BaseException] | None) -> dict[str, str]:
    """The ``{"code", "message"}`` of a job that could not run, by its exception type."""
    if exc_type is None:
        exc_type = Exception
    if issubclass(exc_type, PayloadExpired):
        return {
            "code": ErrorCode.payload_expired,
            "message": "the job's input expired before a worker took it (HMCC_FAILURE_TTL_S)",
        }
    if issubclass(exc_type, rq_compat.AbandonedJobError):
        return {
            "code": ErrorCode.worker_lost,
            "message": "the worker running this job stopped; it was retried once and the "
            "retry did not finish either",
        }
    if issubclass(exc_type, rq_compat.JobTimeoutException):
        return {"code": ErrorCode.timeout, "message": "the job ran past its time limit"}
    return {"code": ErrorCode.internal_error, "message": "the job failed (retried once)"}


def on_job_success(job: Any, connection: Any, result: Any) -> None:
    """RQ success callback: the input is no longer needed."""
    connection.delete(PAYLOAD_KEY.format(job_id=job.id))


#: Marks a failed attempt as counted (``job id``, attempt's start), so that it counts once.
FAILURE_SEEN_KEY = "hmcc:failure-seen:{job_id}:{started}"
FAILURE_SEEN_TTL_S = 24 * 3600


def on_job_failure(job: Any, connection: Any, exc_type: Any, exc_value: Any, tb: Any) -> None:
    """RQ failure callback (also for a job whose worker died): the reason and the time, for
    the API (RQ records no end for a job its registry cleanup fails), and the count, for the
    metrics. A dead worker's job is found by the registry cleanup of the API and of every
    worker, which can run at once: the attempt is counted by the first caller only."""
    job.meta["error"] = classify_failure(exc_type)
    job.meta["ended"] = datetime.now(UTC).isoformat()
    job.save_meta()
    started = getattr(job, "started_at", None)
    key = FAILURE_SEEN_KEY.format(job_id=job.id, started=started.isoformat() if started else "")
    if connection.set(key, 1, nx=True, ex=FAILURE_SEEN_TTL_S):
        RedisJobMetrics(connection).record_failure(getattr(exc_type, "__name__", "unknown"))


#: The only callables a worker runs, by the dotted name RQ stores (:mod:`.protocol`).
JOB_FUNCTIONS = {
    f"{__name__}.verify_job": verify_job,
    f"{__name__}.on_job_failure": on_job_failure,
    f"{__name__}.on_job_success": on_job_success,
}
