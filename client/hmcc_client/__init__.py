"""hmcc-client: the typed HTTP client of the hmcc-match service, sync and asyncio.

Installs with httpx, msgpack and numpy only (not the service's core: no OpenCV, numba, SciPy
or pydantic). See ``docs/client.md``.
"""

from __future__ import annotations

from .bodies import JSON, MSGPACK, BatchBody, Pair, flight_bodies
from .client import AsyncHmccClient, HmccClient, HmccError
from .models import (
    MAX_WAIT_S,
    TERMINAL,
    Batch,
    BatchItem,
    BatchStatus,
    ChosenPair,
    ErrorBody,
    FittedModel,
    Issue,
    ItemStatus,
    Job,
    JobStatus,
    JobTimings,
    Limits,
    Pairs,
    Stage,
    VerificationResult,
)

__version__ = "0.1.0"

__all__ = [
    "JSON",
    "MAX_WAIT_S",
    "MSGPACK",
    "TERMINAL",
    "AsyncHmccClient",
    "Batch",
    "BatchBody",
    "BatchItem",
    "BatchStatus",
    "ChosenPair",
    "ErrorBody",
    "FittedModel",
    "HmccClient",
    "HmccError",
    "Issue",
    "ItemStatus",
    "Job",
    "JobStatus",
    "JobTimings",
    "Limits",
    "Pair",
    "Pairs",
    "Stage",
    "VerificationResult",
    "flight_bodies",
]
