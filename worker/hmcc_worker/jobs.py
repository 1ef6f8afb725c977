"""The functions a queue runs: a pair, or a chunk of a batch's pairs.

Arguments and results are JSON (strings in, JSON-ready dicts out), so RQ's JSON serializer
carries them and nothing is pickled. Every outcome is a dict::

    {"status": "finished", "result": {...verification, timings_ms.compute...}}
    {"status": "failed", "error": {"code": "invalid_input", "message": ..., "issues": [...]}}

Input problems the API could not see (they need the numbers: cameras 1000 km apart, too few
matches for the model) are outcomes, not exceptions: retrying them cannot help. An exception
escaping a job is a bug or a resource fault; RQ retries it once and then records it failed.

``verify_pair_job`` / ``verify_chunk_job`` are the RQ entry points: the same work, plus the
per-stage durations recorded in Redis for ``/metrics``.
"""

from __future__ import annotations

import time
from typing import Any

from pydantic import ValidationError

from hmcc.errors import InputError
from hmcc.schema import BatchRequest, PairRequest, validation_issues, verify_request

from .metrics import RedisJobMetrics

__all__ = [
    "JOB_FUNCTIONS",
    "on_job_failure",
    "run_chunk",
    "run_pair",
    "verify_chunk_job",
    "verify_pair_job",
    "warm_up",
]


def run_pair(pair_json: str) -> dict[str, Any]:
    """Verify one pair given as JSON text (the public pair format)."""
    t0 = time.perf_counter()
    try:
        request = PairRequest.model_validate_json(pair_json)
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


def run_chunk(chunk_json: str) -> list[dict[str, Any]]:
    """Verify the pairs of a batch chunk (a :class:`BatchRequest` as JSON text); one outcome
    per pair, in order. The chunk was validated by the API: a chunk that does not parse is
    not ours, and raises."""
    requests = BatchRequest.model_validate_json(chunk_json).pair_requests()
    outcomes = []
    for request in requests:
        outcomes.append(_verify(request, time.perf_counter()))
    return outcomes


def _metrics() -> RedisJobMetrics | None:
    from rq import get_current_job

    job = get_current_job()
    return None if job is None else RedisJobMetrics(job.connection)


def _note_failed_items(outcomes: list[dict[str, Any]]) -> None:
    """Chunk jobs: record how many pairs failed in the job's meta, so progress can be
    counted without loading every result."""
    from rq import get_current_job

    job = get_current_job()
    if job is not None:
        job.meta["failed_items"] = sum(o["status"] == "failed" for o in outcomes)
        job.save_meta()


def verify_pair_job(pair_json: str) -> dict[str, Any]:
    outcome = run_pair(pair_json)
    if (metrics := _metrics()) is not None:
        metrics.record([outcome])
    return outcome


def verify_chunk_job(chunk_json: str) -> list[dict[str, Any]]:
    outcomes = run_chunk(chunk_json)
    _note_failed_items(outcomes)
    if (metrics := _metrics()) is not None:
        metrics.record(outcomes)
    return outcomes


def on_job_failure(job: Any, connection: Any, exc_type: Any, exc_value: Any, tb: Any) -> None:
    """RQ failure callback (also called for a job whose worker died): count the failure."""
    reason = getattr(exc_type, "__name__", "unknown")
    RedisJobMetrics(connection).record_failure(reason)


#: The only callables a worker runs, by the dotted name stored in Redis.
JOB_FUNCTIONS = {
    f"{__name__}.verify_pair_job": verify_pair_job,
    f"{__name__}.verify_chunk_job": verify_chunk_job,
    f"{__name__}.on_job_failure": on_job_failure,
}
