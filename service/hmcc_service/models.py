"""Response models of the API (the request models are the contract's ``PairRequest`` and
``BatchRequest``, :mod:`hmcc_schema.models`). Routes build their answers as bytes, splicing in
the results the workers encoded; these models document them in the OpenAPI document, and the
API fuzz test checks every response against them."""

from __future__ import annotations

from datetime import datetime
from typing import TYPE_CHECKING, Any, Literal, TypeAlias

from pydantic import BaseModel, Field

from hmcc_worker.protocol import BatchStatus, ItemStatus, JobStatus

__all__ = [
    "MAX_WAIT_S",
    "BatchItem",
    "BatchView",
    "ChosenPair",
    "ErrorBody",
    "ErrorResponse",
    "Health",
    "JobTimings",
    "JobView",
    "Limits",
    "PairsView",
    "Readiness",
    "VerificationResult",
]

#: Upper bound of ``?wait=`` in seconds (longer waits are several long polls).
MAX_WAIT_S = 60.0

# The statuses are the protocol's, as a ``Literal`` of all of an enum's members: the same type
# as the enum for mypy, an inline enum of its strings in the OpenAPI document for pydantic and
# FastAPI (an ``Enum`` field would add a named schema of its own).
if TYPE_CHECKING:
    JobStatusLiteral: TypeAlias = JobStatus
    ItemStatusLiteral: TypeAlias = ItemStatus
    BatchStatusLiteral: TypeAlias = BatchStatus
else:
    JobStatusLiteral = Literal[tuple(JobStatus)]
    ItemStatusLiteral = Literal[tuple(ItemStatus)]
    BatchStatusLiteral = Literal[tuple(BatchStatus)]


class Issue(BaseModel):
    field: str = Field(description="Dotted path into the request body, e.g. `matches[3][1]`.")
    reason: str


class ErrorBody(BaseModel):
    code: str = Field(
        description="A job or pair: `invalid_input` (with `issues`), `worker_crashed` (the pair "
        "killed the process verifying it; not retried), `worker_lost` (its worker vanished "
        "twice), `timeout`, `payload_expired`, `internal_error`. An answer: `invalid_input`, "
        "`not_found`, `not_cancelable`, `queue_full`, `queue_unavailable`, `body_too_large`, "
        "`unsupported_media_type`, `unauthorized`, `bad_request`, `method_not_allowed`, "
        "`uri_too_long`, `headers_too_large`, `server_busy`, `request_timeout`, "
        "`shutting_down`."
    )
    message: str
    issues: list[Issue] | None = None


class ErrorResponse(BaseModel):
    error: ErrorBody


class FittedModel(BaseModel):
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
    """A pair's result, as the core produced it. With ``params.result = "inliers"`` only
    ``method``, ``inliers``, ``model`` and ``timings_ms.total`` are present (and, for a pair
    that asked for matching, ``matches`` and ``matching`` without its ``params``)."""

    method: str
    matches: list[list[int]] | None = Field(
        default=None,
        description="A pair that asked for matching (`match`): the matches found, `[i, j]` "
        "keypoint i of image1 and keypoint j of image2.",
    )
    inliers: list[int] = Field(
        description="Ascending indices into the request's `matches` (or, for a pair that "
        "asked for matching, into the result's)."
    )
    model: FittedModel
    stages: list[Stage] | None = None
    timings_ms: dict[str, float] = Field(
        description="Each stage's wall time and `total`, their sum (ms)."
    )
    statistics: dict[str, Any] | None = None
    params: dict[str, Any] | None = Field(
        default=None, description="The resolved parameters, echoed."
    )
    matching: dict[str, Any] | None = Field(
        default=None,
        description="A pair that asked for matching: the matcher's figures: `mode` "
        "(`guided`, `guided-turned` with `turn_deg`, `brute-force` with `pose_unusable` where "
        "the poses cannot predict (a camera not above the ground), `pose-mismatch` (brute "
        "force after passes that did not fit, with `matching.brute_force_on_mismatch`), "
        "`pose-mismatch-unmatched`, `no-overlap`), `candidates_per_keypoint` (descriptors "
        "compared per keypoint of image1), `matches`, `time_ms`, the passes' radii and "
        "support, and `params` (the matcher's options, echoed).",
    )
    motions: dict[str, Any] | None = Field(
        default=None,
        description="With `params.return_motions`: `z0_m`, `stages` (in order), and per match "
        "`start`/`end` ([x, y] metres on the plane, null where a ray misses it), "
        "`direction_deg`, `length_m` and `decision` (`inlier` or the first stage that did not "
        "keep it).",
    )


class JobTimings(BaseModel):
    """The service's own times of a job (ms): waiting, running, both."""

    queue_wait: float | None = Field(default=None, description="Submitted -> started.")
    run: float | None = Field(
        default=None, description="Started -> finished: the job's pairs, its input and output."
    )
    turnaround: float | None = Field(default=None, description="Submitted -> finished.")


class JobView(BaseModel):
    job_id: str
    status: JobStatusLiteral
    submitted_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    timings_ms: JobTimings = Field(default_factory=JobTimings)
    result: VerificationResult | None = None
    error: ErrorBody | None = None


class BatchItem(BaseModel):
    index: int = Field(description="Position of the pair in the request's `pairs`.")
    id: str | None = Field(description="The pair's `id` from the request, if given.")
    status: ItemStatusLiteral
    result: VerificationResult | None = None
    error: ErrorBody | None = None


class BatchView(BaseModel):
    batch_id: str
    status: BatchStatusLiteral = Field(
        description="`finished` once every pair is finished, failed or canceled."
    )
    submitted_at: datetime
    total: int
    queued: int
    started: int
    finished: int
    failed: int
    canceled: int
    expired: int = Field(description="Pairs whose result is no longer kept.")
    jobs: int = Field(description="Queue jobs the batch was split into.")
    offset: int
    limit: int
    next_offset: int | None = Field(description="Offset of the next page; null on the last.")
    results: list[BatchItem]


class ChosenPair(BaseModel):
    image1: str = Field(description="An image id of the request (the earlier in its order).")
    image2: str = Field(description="An image id of the request (the later in its order).")
    overlap: float = Field(
        description="The footprints' intersection over the smaller footprint, in (0, 1]."
    )


class PairsView(BaseModel):
    """The pairs worth matching among a flight's images, chosen by footprint overlap."""

    images: int = Field(description="Images in the request.")
    pairs: list[ChosenPair] = Field(
        description="Sorted by the images' order in the request, image1 then image2."
    )
    params: dict[str, Any] = Field(description="The resolved options, echoed.")
    ground: dict[str, float] = Field(description="`ground_z` or `flying_height`, as given.")
    timings_ms: dict[str, float] = Field(description="`total`: parsing excluded.")


class Limits(BaseModel):
    """What one request may hold, so clients can split their work without guessing."""

    max_body_bytes: int = Field(description="Request bodies above this get 413.")
    max_batch_pairs: int = Field(description="Pairs per batch at most.")
    max_batch_images: int = Field(description="Images per batch (and per pairs request) at most.")
    max_keypoints: int = Field(description="Keypoints per image at most.")
    max_matches: int = Field(description="Matches per pair at most.")
    batch_chunk_pairs: int = Field(description="Pairs per queue job of a batch at most.")
    max_wait_s: float = Field(description="The longest `?wait=` (seconds).")
    max_queue_depth: int = Field(description="Queued jobs above which submissions get 429.")
    methods: list[str] = Field(description="Every method's name; the first is the default.")


class Health(BaseModel):
    status: Literal["ok"]
    version: str


class Readiness(BaseModel):
    ready: bool
    backend: Literal["embedded", "rq"]
    redis: str | None = None
    workers: int
    queued: int | None = None
