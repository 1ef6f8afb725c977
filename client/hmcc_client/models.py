"""The API's answers as frozen dataclasses, read from their JSON (or from the same document
in MessagePack, where a result's ``inliers`` and ``matches`` are raw array buffers).

The server describes the same JSON with pydantic models (``hmcc_service.models``, in the
OpenAPI document); the client reads it with the standard library and numpy so that it
installs without pydantic (``tests/hmcc_client/test_models.py`` checks that the fields agree).
Unknown keys are ignored, so a newer server's additions do not break an older client. Times
are timezone-aware ``datetime``; durations are milliseconds; a result's ``inliers`` and
``matches`` are int64 numpy arrays, whichever way they came.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from datetime import datetime
from typing import Any, Literal, Self, cast

import numpy as np

__all__ = [
    "MAX_WAIT_S",
    "TERMINAL",
    "Batch",
    "BatchItem",
    "BatchStatus",
    "ChosenPair",
    "ErrorBody",
    "FittedModel",
    "Issue",
    "ItemStatus",
    "Job",
    "JobStatus",
    "JobTimings",
    "Limits",
    "Pairs",
    "Stage",
    "VerificationResult",
]

#: Upper bound of ``?wait=`` in seconds (longer waits are several long polls).
MAX_WAIT_S = 60.0

JobStatus = Literal["queued", "started", "finished", "failed", "canceled"]
#: A batch item's status: its job's, or ``expired`` once its result is no longer kept.
ItemStatus = Literal["queued", "started", "finished", "failed", "canceled", "expired"]
BatchStatus = Literal["queued", "running", "finished"]
#: The statuses of a job that has ended.
TERMINAL: frozenset[str] = frozenset({"finished", "failed", "canceled"})

Doc = dict[str, Any]


def _time(value: str | None) -> datetime | None:
    return None if value is None else datetime.fromisoformat(value)


@dataclass(frozen=True, slots=True)
class Issue:
    """What is wrong with one field: ``field``, a dotted path into the request body (e.g.
    ``pairs[3].matches[7][1]``), and ``reason``."""

    field: str
    reason: str

    @classmethod
    def from_json(cls, doc: Doc) -> Self:
        return cls(doc["field"], doc["reason"])


@dataclass(frozen=True, slots=True)
class ErrorBody:
    """Why a job or a pair failed (``code``: ``invalid_input``, ``worker_crashed``,
    ``timeout``, ...), with the field ``issues`` of ``invalid_input``."""

    code: str
    message: str
    issues: list[Issue] | None = None

    @classmethod
    def from_json(cls, doc: Doc) -> Self:
        issues = doc.get("issues")
        return cls(
            doc["code"],
            doc["message"],
            None if issues is None else [Issue.from_json(i) for i in issues],
        )

    def to_dict(self) -> Doc:
        """The JSON object, as the server wrote it (``issues`` only when there are some)."""
        doc: Doc = {"code": self.code, "message": self.message}
        if self.issues is not None:
            doc["issues"] = [{"field": i.field, "reason": i.reason} for i in self.issues]
        return doc


@dataclass(frozen=True, slots=True)
class FittedModel:
    """``type``: ``fundamental``, ``essential``, ``homography``, or None (method ``hmcc``);
    ``matrix``: 3x3, row-major, pixels."""

    type: str | None
    matrix: list[list[float]] | None


@dataclass(frozen=True, slots=True)
class Stage:
    """One stage of a method: matches in, matches kept, its wall time, its own figures."""

    name: str
    input: int
    kept: int
    time_ms: float
    stats: dict[str, Any]


def _indices(value: Any, width: int | None = None) -> np.ndarray:
    """An array of indices as an int64 ndarray: a JSON list, or a ``{"dtype", "shape",
    "data"}`` map of raw little-endian values (MessagePack answers); ``width`` columns."""
    if isinstance(value, dict):
        array = np.frombuffer(value["data"], dtype=value["dtype"]).astype(np.int64)
        if len(value["shape"]) != 1:  # reshape costs more than the copy for a page's arrays
            array = array.reshape(value["shape"])
    else:
        array = np.asarray(value, dtype=np.int64)
    return array if width is None else array.reshape(-1, width)


@dataclass(frozen=True, slots=True, eq=False)
class VerificationResult:
    """A pair's result, as the core produced it. ``inliers``: ascending indices into the
    request's ``matches`` or, for a pair that asked for matching, into ``matches`` (the
    ``[i, j]`` keypoint indices the service found, with ``matching``: the matcher's figures:
    ``mode``, ``candidates_per_keypoint``, ``matches``, ``time_ms``, ...); ``timings_ms``:
    each stage's wall time and ``total``, their sum. ``inliers`` is a 1-D int64 numpy array,
    ``matches`` an (M, 2) one, whether the answer was JSON or MessagePack.
    With ``params.result = "inliers"`` only ``method``, ``inliers``, ``model`` and
    ``timings_ms.total`` are present. :meth:`to_dict` gives the JSON object itself."""

    method: str
    inliers: np.ndarray
    model: FittedModel
    timings_ms: dict[str, float]
    stages: list[Stage] | None = None
    statistics: dict[str, Any] | None = None
    params: dict[str, Any] | None = None
    motions: dict[str, Any] | None = None
    matches: np.ndarray | None = None
    matching: dict[str, Any] | None = None
    _doc: Doc = field(default_factory=dict, repr=False)

    @classmethod
    def from_json(cls, doc: Doc) -> Self:
        model = doc["model"]
        stages = doc.get("stages")
        matches = doc.get("matches")
        return cls(
            method=doc["method"],
            inliers=_indices(doc["inliers"]),
            model=FittedModel(model.get("type"), model.get("matrix")),
            timings_ms=doc["timings_ms"],
            stages=None if stages is None else [Stage(**s) for s in stages],
            statistics=doc.get("statistics"),
            params=doc.get("params"),
            motions=doc.get("motions"),
            matches=None if matches is None else _indices(matches, 2),
            matching=doc.get("matching"),
            _doc=doc,
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, VerificationResult):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    __hash__ = None  # type: ignore[assignment]

    def to_dict(self) -> Doc:
        """The result's JSON object as the server sent it (keys it left out stay out), its
        arrays as lists whichever way they came."""
        doc = dict(self._doc)
        for key in ("inliers", "matches"):
            if isinstance(doc.get(key), dict):
                doc[key] = getattr(self, key).tolist()
        return doc


@dataclass(frozen=True, slots=True)
class JobTimings:
    """The service's own times of a job (ms): submitted -> started (``queue_wait``), started
    -> finished (``run``), submitted -> finished (``turnaround``)."""

    queue_wait: float | None = None
    run: float | None = None
    turnaround: float | None = None


@dataclass(frozen=True, slots=True)
class Job:
    """A verification job; ``done`` once finished, failed or canceled. A job that ran and
    failed has ``status == "failed"`` and ``error``."""

    job_id: str
    status: JobStatus
    submitted_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    timings_ms: JobTimings = field(default_factory=JobTimings)
    result: VerificationResult | None = None
    error: ErrorBody | None = None

    @property
    def done(self) -> bool:
        return self.status in TERMINAL

    @classmethod
    def from_json(cls, doc: Doc) -> Self:
        return cls(
            job_id=doc["job_id"],
            status=doc["status"],
            submitted_at=cast(datetime, _time(doc["submitted_at"])),
            started_at=_time(doc.get("started_at")),
            finished_at=_time(doc.get("finished_at")),
            timings_ms=JobTimings(**doc.get("timings_ms", {})),
            result=_result(doc.get("result")),
            error=_error(doc.get("error")),
        )


@dataclass(frozen=True, slots=True)
class BatchItem:
    """One pair of a batch: ``index``, its position in the request's ``pairs`` (in the
    flight's, from :meth:`HmccClient.verify_flight`), its ``id`` if given, and its result or
    error once it has ended."""

    index: int
    id: str | None
    status: ItemStatus
    result: VerificationResult | None = None
    error: ErrorBody | None = None

    @classmethod
    def from_json(cls, doc: Doc) -> Self:
        return cls(
            doc["index"],
            doc.get("id"),
            doc["status"],
            _result(doc.get("result")),
            _error(doc.get("error")),
        )


@dataclass(frozen=True, slots=True)
class Batch:
    """A batch's progress (counts of its pairs by status, and ``jobs``, the queue jobs it was
    split into) and one page of results (``offset``, ``limit``, ``next_offset``: None on the
    last); ``done`` once every pair is finished, failed or canceled."""

    batch_id: str
    status: BatchStatus
    submitted_at: datetime
    total: int
    queued: int
    started: int
    finished: int
    failed: int
    canceled: int
    expired: int
    jobs: int
    offset: int
    limit: int
    next_offset: int | None
    results: list[BatchItem]

    @property
    def done(self) -> bool:
        return self.status == "finished"

    @classmethod
    def from_json(cls, doc: Doc) -> Self:
        counts = {
            f.name: doc[f.name]
            for f in fields(cls)
            if f.name not in ("submitted_at", "next_offset", "results")
        }
        return cls(
            **counts,
            submitted_at=cast(datetime, _time(doc["submitted_at"])),
            next_offset=doc.get("next_offset"),
            results=[BatchItem.from_json(item) for item in doc["results"]],
        )


@dataclass(frozen=True, slots=True)
class ChosenPair:
    """A pair worth matching: two image ids of the request (``image1`` the earlier in its
    order) and their footprints' ``overlap`` (intersection over the smaller, in (0, 1])."""

    image1: str
    image2: str
    overlap: float


@dataclass(frozen=True, slots=True)
class Pairs:
    """The pairs worth matching among a flight's images (``POST /v1/pairs``): ``images``
    sent, the ``pairs`` in the images' order, the resolved ``params`` and ``ground``
    (``ground_z`` or ``flying_height``, as given) echoed, ``timings_ms["total"]``."""

    images: int
    pairs: list[ChosenPair]
    params: dict[str, Any]
    ground: dict[str, float]
    timings_ms: dict[str, float]

    @classmethod
    def from_json(cls, doc: Doc) -> Self:
        return cls(
            doc["images"],
            [ChosenPair(p["image1"], p["image2"], p["overlap"]) for p in doc["pairs"]],
            doc["params"],
            doc["ground"],
            doc["timings_ms"],
        )


@dataclass(frozen=True, slots=True)
class Limits:
    """What one request may hold (``GET /v1/limits``), so a client splits its work without
    guessing."""

    max_body_bytes: int
    max_batch_pairs: int
    max_batch_images: int
    max_keypoints: int
    max_matches: int
    batch_chunk_pairs: int
    max_wait_s: float
    max_queue_depth: int
    #: every method's name; the first is the default
    methods: list[str]

    @classmethod
    def from_json(cls, doc: Doc) -> Self:
        return cls(**{f.name: doc[f.name] for f in fields(cls)})


def _result(doc: Doc | None) -> VerificationResult | None:
    return None if doc is None else VerificationResult.from_json(doc)


def _error(doc: Doc | None) -> ErrorBody | None:
    return None if doc is None else ErrorBody.from_json(doc)
