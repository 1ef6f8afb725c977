"""What every /v1 route shares: the queue, the API key check, error mapping, ?wait=."""

from __future__ import annotations

import hmac
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any, TypeVar

import anyio.to_thread
from fastapi import Query, Request, Security
from fastapi.security import APIKeyHeader
from pydantic import BaseModel, ValidationError

from ..errors import ApiError, invalid_input
from ..models import MAX_WAIT_S, ErrorResponse
from ..queue import JobQueue, NotCancelable, QueueFull, QueueUnavailable
from ..settings import Settings

__all__ = [
    "MAX_WAIT_S", "Wait", "body_schema", "error_responses", "get_queue", "queue_errors",
    "read_json", "require_api_key",
]


Wait = Query(
    0.0,
    ge=0.0,
    le=MAX_WAIT_S,
    description="Seconds to wait for the job to end before answering (long poll), at most 60.",
)

_api_key = APIKeyHeader(
    name="X-API-Key",
    auto_error=False,
    description="Required on every /v1 route when the service sets HMCC_API_KEY.",
)


async def require_api_key(request: Request, key: str | None = Security(_api_key)) -> None:
    settings: Settings = request.app.state.settings
    if settings.api_key is None:
        return
    expected = settings.api_key.get_secret_value().encode()
    if key is None or not hmac.compare_digest(key.encode(), expected):
        raise ApiError(401, "unauthorized", "missing or wrong X-API-Key header",
                       headers={"WWW-Authenticate": "X-API-Key"})


def get_queue(request: Request) -> JobQueue:
    queue: JobQueue = request.app.state.queue
    return queue


@asynccontextmanager
async def queue_errors(settings: Settings) -> AsyncIterator[None]:
    """Map queue exceptions to 4xx/503 with Retry-After."""
    retry = {"Retry-After": str(settings.retry_after_s)}
    try:
        yield
    except QueueFull:
        raise ApiError(
            429, "queue_full",
            f"more than {settings.max_queue_depth} jobs are waiting; retry later",
            headers=retry,
        ) from None
    except QueueUnavailable:
        raise ApiError(
            503, "queue_unavailable",
            "the job queue (Redis) is unreachable; retry later", headers=retry,
        ) from None
    except NotCancelable as e:
        raise ApiError(
            409, "not_cancelable",
            f"the job is {e.status.value}; only a queued job can be cancelled",
        ) from None


#: Bodies above this are validated in a worker thread, so the event loop keeps answering.
INLINE_PARSE_BYTES = 256 * 1024

M = TypeVar("M", bound=BaseModel)


async def read_json(request: Request, model: type[M]) -> M:
    """The body, validated as ``model`` in one pass over the raw bytes (415 unless JSON)."""
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if content_type != "application/json" and not content_type.endswith("+json"):
        raise ApiError(415, "unsupported_media_type",
                       "send the body as JSON (Content-Type: application/json)")
    raw = await request.body()
    try:
        if len(raw) <= INLINE_PARSE_BYTES:
            return model.model_validate_json(raw)
        return await anyio.to_thread.run_sync(model.model_validate_json, raw)
    except ValidationError as e:
        raise invalid_input(e) from None


def error_responses(thing: str) -> dict[int | str, dict[str, Any]]:
    """The error answers every /v1 route documents (``thing``: what a 404 did not find)."""
    def doc(description: str) -> dict[str, Any]:
        return {"model": ErrorResponse, "description": description}

    return {
        401: doc("API key missing or wrong"),
        404: doc(f"No such {thing} (or it expired)"),
        413: doc("Body too large"),
        415: doc("Body is not JSON (Content-Type)"),
        422: doc("Invalid input: each field and reason"),
        429: doc("Queue full; see Retry-After"),
        503: doc("Queue unreachable; see Retry-After"),
    }


def body_schema(name: str) -> dict[str, Any]:
    """``openapi_extra`` for a route that parses its JSON body itself (one pydantic pass over
    the raw bytes, and the same bytes go to the queue) but documents it as ``name``."""
    return {
        "requestBody": {
            "required": True,
            "content": {"application/json": {"schema": {"$ref": f"#/components/schemas/{name}"}}},
        }
    }
