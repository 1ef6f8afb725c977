"""What routes get injected, as ``Annotated`` aliases: the app's queue and settings, ``?wait``,
and the API key's place in the OpenAPI document."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Query, Request, Security
from fastapi.security import APIKeyHeader

from .models import MAX_WAIT_S
from .queue import JobQueue
from .settings import Settings

__all__ = ["ApiKey", "QueueDep", "SettingsDep", "Wait"]


def _queue(request: Request) -> JobQueue:
    queue: JobQueue = request.app.state.queue
    return queue


def _settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


_api_key_header = APIKeyHeader(
    name="X-API-Key",
    auto_error=False,
    description="Required on every /v1 route when the service sets HMCC_API_KEY.",
)


async def _api_key_documented(key: str | None = Security(_api_key_header)) -> None:
    """The key is checked by :class:`hmcc_service.limits.V1Gate` before a byte of the body
    is read; this dependency only puts the scheme in the OpenAPI document."""


QueueDep = Annotated[JobQueue, Depends(_queue)]
SettingsDep = Annotated[Settings, Depends(_settings)]
ApiKey = Depends(_api_key_documented)
Wait = Annotated[
    float,
    Query(
        ge=0.0,
        le=MAX_WAIT_S,
        description="Seconds to wait for the job to end before answering (long poll), at most 60.",
    ),
]
BatchWait = Annotated[
    float,
    Query(
        ge=0.0,
        le=MAX_WAIT_S,
        description=(
            "Seconds to wait, before answering, for one more job of the batch (a chunk of its"
            " pairs) to end, unless the batch has ended (long poll), at most 60."
        ),
    ),
]
