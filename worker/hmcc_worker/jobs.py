"""The functions a queue runs: a pair, or a chunk of a batch's pairs.

Arguments and results are JSON (strings in, JSON-ready dicts out), so RQ's JSON serializer
carries them and nothing is pickled. Every outcome is a dict::

    {"status": "finished", "result": {...verification, timings_ms.compute...}}
    {"status": "failed", "error": {"code": "invalid_input", "message": ..., "issues": [...]}}

Input problems the API could not see (they need the numbers: cameras 1000 km apart, too few
matches for the model) are outcomes, not exceptions: retrying them cannot help. An exception
escaping a job is a bug or a resource fault; RQ retries it once and then records it failed.

``verify_pair_job`` / ``verify_chunk_job`` are the RQ entry points: the same work on the
input stored under ``payload_key(job id)``, plus the per-stage durations recorded in Redis for
``/metrics``.
"""

from __future__ import annotations

import time
from typing import Any, TypeVar

from pydantic import ValidationError

from hmcc.errors import InputError
from hmcc.schema import BatchRequest, PairRequest, validation_issues, verify_request

from .metrics import RedisJobMetrics
from .payload import decode

M = TypeVar("M", PairRequest, BatchRequest)

__all__ = [
    "JOB_FUNCTIONS",
    "PayloadExpired",
    "on_job_failure",
    "on_job_success",
    "payload_key",
    "run_chunk",
    "run_pair",
    "verify_chunk_job",
    "verify_pair_job",
    "warm_up",
]


def run_pair(pair: str | bytes | PairRequest) -> dict[str, Any]:
    """Verify one pair given as JSON text (the public pair format), as the API's binary
    payload (:mod:`hmcc_worker.payload`), or already parsed."""
    t0 = time.perf_counter()
    if isinstance(pair, bytes):
        pair = _decoded(pair, PairRequest)
    if isinstance(pair, PairRequest):
        return _verify(pair, t0)
    try:
        request = PairRequest.model_validate_json(pair)
    except ValidationError as e:
        return _invalid(e)
    return _verify(request, t0)


def _verify(request: PairRequest, t0: float) -> dict[str, Any]:
    try:
        verification = verify_request(request)
    except InputError as e:
        return _invalid(e)
    result = verification.to_dict()
    timings = result["timings_ms"]
    timings["compute"] = timings.pop("total")
    timings["job"] = (time.perf_counter() - t0) * 1e3
    return {"status": "finished", "result": result}


def _invalid(e: ValidationError | InputError) -> dict[str, Any]:
    issues = validation_issues(e)
    return {
        "status": "failed",
        "error": {
            "code": "invalid_input",
            "message": "; ".join(f"{i.field}: {i.reason}" for i in issues),
            "issues": [i.model_dump() for i in issues],
        },
    }


def warm_up() -> None:
    """Import and exercise the core once, so the first real job pays no start-up cost."""
    from hmcc.simulate import SimulationOptions, simulate_pair

    pair = simulate_pair(SimulationOptions(n_inliers=60, outlier_ratio=0.3), seed=0)
    verify_request(PairRequest.model_validate(pair))


def run_chunk(chunk: str | bytes | BatchRequest) -> list[dict[str, Any]]:
    """Verify the pairs of a batch chunk (a :class:`BatchRequest`: JSON text, binary payload
    or parsed); one outcome per pair, in order. The chunk was validated by the API: a chunk
    that does not parse is not ours, and raises."""
    if isinstance(chunk, bytes):
        chunk = _decoded(chunk, BatchRequest)
    elif isinstance(chunk, str):
        chunk = BatchRequest.model_validate_json(chunk)
    requests = chunk.pair_requests()
    outcomes = []
    for request in requests:
        outcomes.append(_verify(request, time.perf_counter()))
    return outcomes


#: Where the API puts a job's input: ``hmcc:payload:<job id>``. The job data itself holds no
#: input (RQ zlib-compresses job data and rewrites it when a job ends: milliseconds per pair),
#: and a job can only read the payload of its own id.
PAYLOAD_PREFIX = "hmcc:payload:"


def payload_key(job_id: str) -> str:
    return PAYLOAD_PREFIX + job_id


def _current_job() -> Any:
    from rq import get_current_job

    job = get_current_job()
    if job is None:
        raise RuntimeError("an RQ job function called outside an RQ worker")
    return job


def _decoded(data: bytes, kind: type[M]) -> M:
    request = decode(data)
    if not isinstance(request, kind):
        raise ValueError(f"expected a {kind.__name__} payload")
    return request


def _payload(job: Any) -> bytes | None:
    raw: bytes | None = job.connection.get(payload_key(job.id))
    return raw


_EXPIRED = {
    "status": "failed",
    "error": {
        "code": "payload_expired",
        "message": "the job's input expired before a worker took it (HMCC_FAILURE_TTL_S)",
    },
}


def verify_pair_job() -> dict[str, Any]:
    """RQ: verify the pair stored at ``payload_key(job id)``."""
    job = _current_job()
    raw = _payload(job)
    outcome = dict(_EXPIRED) if raw is None else run_pair(raw)
    RedisJobMetrics(job.connection).record([outcome])
    return outcome


class PayloadExpired(RuntimeError):
    """A chunk job's input is gone (it waited longer than its TTL)."""


def verify_chunk_job() -> list[dict[str, Any]]:
    """RQ: verify the batch chunk stored at ``payload_key(job id)``; also records in the
    job's meta how many pairs failed, so progress is counted without loading results."""
    job = _current_job()
    raw = _payload(job)
    if raw is None:
        raise PayloadExpired(job.id)
    outcomes = run_chunk(raw)
    job.meta["failed_items"] = sum(o["status"] == "failed" for o in outcomes)
    job.save_meta()
    RedisJobMetrics(job.connection).record(outcomes)
    return outcomes


def on_job_success(job: Any, connection: Any, result: Any) -> None:
    """RQ success callback: the input is no longer needed."""
    connection.delete(payload_key(job.id))


def on_job_failure(job: Any, connection: Any, exc_type: Any, exc_value: Any, tb: Any) -> None:
    """RQ failure callback (also called for a job whose worker died): count the failure."""
    reason = getattr(exc_type, "__name__", "unknown")
    RedisJobMetrics(connection).record_failure(reason)


#: The only callables a worker runs, by the dotted name stored in Redis.
JOB_FUNCTIONS = {
    f"{__name__}.verify_pair_job": verify_pair_job,
    f"{__name__}.verify_chunk_job": verify_chunk_job,
    f"{__name__}.on_job_failure": on_job_failure,
    f"{__name__}.on_job_success": on_job_success,
}
