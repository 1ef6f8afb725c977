"""The job an RQ worker runs, and the callbacks RQ calls around it (the only functions a worker
runs: :data:`JOB_FUNCTIONS`).

:func:`verify_job` reads the job's input (``PAYLOAD_KEY``, and the batch's images it names),
has the worker's :class:`~hmcc_worker.pool.ComputePool` verify it, and stores one outcome
document per pair under ``OUTCOMES_KEY`` for as long as the job's result lives; RQ keeps only a
small summary. A pair that crashed or timed out is an outcome like any other, so a job ends
``finished`` unless it could not run at all:

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

from hmcc.flight import FlightImage

from . import rq_compat
from .metrics import RedisJobMetrics
from .payload import decode_flight, decode_image, image_names
from .pool import ComputePool
from .protocol import IMAGES_KEY, OUTCOMES_KEY, PAYLOAD_KEY, ErrorCode, JobStatus

__all__ = [
    "JOB_FUNCTIONS",
    "PayloadExpired",
    "classify_failure",
    "on_job_failure",
    "on_job_success",
    "set_compute",
    "verify_job",
]

log = logging.getLogger("hmcc.worker")

_compute: ComputePool | None = None
#: Decoded images of recent batches, so the chunks of a batch do not fetch them again.
_images: OrderedDict[tuple[str, str], FlightImage] = OrderedDict()
_IMAGE_CACHE = 512


class PayloadExpired(RuntimeError):
    """A job's input is gone (it waited longer than its TTL)."""


def set_compute(pool: ComputePool) -> None:
    """The pool this process's jobs run on (set by the worker at start)."""
    global _compute
    _compute = pool


def verify_job() -> dict[str, int]:
    """RQ: verify the input stored for this job; returns ``{"pairs", "failed"}``."""
    t0 = time.perf_counter()
    job = rq_compat.current_job()
    connection = job.connection
    raw = connection.get(PAYLOAD_KEY.format(job_id=job.id))
    if not isinstance(raw, bytes):
        raise PayloadExpired(job.id)
    names = image_names(raw)
    images = _fetch_images(connection, job.meta.get("batch"), names) if names else None
    flight = decode_flight(raw, images)
    if _compute is None:
        raise RuntimeError("verify_job runs in an hmcc worker (no compute pool here)")
    outcomes = _compute.run(flight)
    failed = sum(o.status is JobStatus.failed for o in outcomes)
    key = OUTCOMES_KEY.format(job_id=job.id)
    ttl = job.result_ttl if job.result_ttl and job.result_ttl > 0 else 3600
    with connection.pipeline() as pipe:
        pipe.delete(key)
        pipe.rpush(key, *(o.pack() for o in outcomes))
        pipe.expire(key, ttl)
        pipe.execute()
    job.meta["failed"] = failed
    job.save_meta()
    RedisJobMetrics(connection).record(outcomes, time.perf_counter() - t0)
    return {"pairs": len(outcomes), "failed": failed}


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
        for name, blob in zip(missing, blobs, strict=True):
            found[name] = _images[(key, name)] = decode_image(blob)
            while len(_images) > _IMAGE_CACHE:
                _images.popitem(last=False)
    for name in names:
        _images.move_to_end((key, name))
    return found


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


def on_job_failure(job: Any, connection: Any, exc_type: Any, exc_value: Any, tb: Any) -> None:
    """RQ failure callback (also for a job whose worker died): the reason and the time, for
    the API (RQ records no end for a job its registry cleanup fails), and the count, for the
    metrics."""
    job.meta["error"] = classify_failure(exc_type)
    job.meta["ended"] = datetime.now(UTC).isoformat()
    job.save_meta()
    RedisJobMetrics(connection).record_failure(getattr(exc_type, "__name__", "unknown"))


#: The only callables a worker runs, by the dotted name RQ stores (:mod:`.protocol`).
JOB_FUNCTIONS = {
    f"{__name__}.verify_job": verify_job,
    f"{__name__}.on_job_failure": on_job_failure,
    f"{__name__}.on_job_success": on_job_success,
}
