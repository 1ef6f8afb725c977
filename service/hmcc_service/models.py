"""Response models of the API (the request models are the core's ``PairRequest`` and
``BatchRequest``). Routes build plain dicts for speed; these models document them in the
OpenAPI document, and the API fuzz test checks every response against them."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, Field

__all__ = [
    "BatchItem",
    "BatchView",
    "ErrorBody",
    "ErrorResponse",
    "Health",
    "JobView",
    "MAX_WAIT_S",
    "Readiness",
    "VerificationResult",
]

#: Upper bound of ``?wait=`` in seconds (longer waits are several long polls).
MAX_WAIT_S = 60.0

JobStatus = Literal["queued", "started", "finished", "failed", "canceled"]


class Issue(BaseModel):
    field: str = Field(description="Dotted path into the request body, e.g. `matches[3][1]`.")
    reason: str


class ErrorBody(BaseModel):
    code: str = Field(
        description="`invalid_input`, `not_found`, `not_cancelable`, `queue_full`, "
        "`queue_unavailable`, `body_too_large`, `unauthorized`, `worker_lost`, `timeout`, "
        "`internal_error`, ..."
    )
    message: str
    issues: list[Issue] | None = None


class ErrorResponse(BaseModel):
    error: ErrorBody


class Model(BaseModel):
    type: str | None = Field(
        description="`fundamental`, `essential`, `homography`, or null (method `hmcc`)."
    )
    matrix: list[list[float]] | None = Field(description="3x3, row-major, pixels.")


class Stage(BaseModel):
    name: str
    input: int
    kept: int
    time_ms: float
    stats: dict[str, Any]


class VerificationResult(BaseModel):
    method: str
    inliers: list[int] = Field(description="Ascending indices into the request's `matches`.")
    model: Model
    stages: list[Stage]
    timings_ms: dict[str, float] = Field(
        description="Each stage's time; `compute` (sum of stages), `job` (the job's own time, "
        "with parsing), `queue_wait` (submitted -> started), `total` (submitted -> finished)."
    )
    statistics: dict[str, Any]
    params: dict[str, Any] = Field(description="The resolved parameters, echoed.")


class JobView(BaseModel):
    job_id: str
    status: JobStatus
    submitted_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    result: VerificationResult | None = None
    error: ErrorBody | None = None


class BatchItem(BaseModel):
    index: int = Field(description="Position of the pair in the request's `pairs`.")
    id: str | None = Field(description="The pair's `id` from the request, if given.")
    status: JobStatus
    result: VerificationResult | None = None
    error: ErrorBody | None = None


class BatchView(BaseModel):
    batch_id: str
    status: Literal["queued", "running", "finished"] = Field(
        description="`finished` once every pair is finished, failed or canceled."
    )
    submitted_at: datetime
    total: int
    queued: int
    started: int
    finished: int
    failed: int
    canceled: int
    jobs: int = Field(description="Queue jobs the batch was split into.")
    offset: int
    limit: int
    next_offset: int | None = Field(description="Offset of the next page; null on the last.")
    results: list[BatchItem]


class Health(BaseModel):
    status: Literal["ok"]
    version: str


class Readiness(BaseModel):
    ready: bool
    backend: Literal["embedded", "rq"]
    redis: str | None = None
    workers: int
    queued: int | None = None
