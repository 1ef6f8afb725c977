"""What a request must pass before its body is read, as pure ASGI middleware.

* :class:`V1Gate` (``/v1`` routes): the API key (401) and, for a POST, the content type (415);
  then a share of the body budget: at most ``HMCC_BODY_BUDGET_BYTES`` of bodies are read and
  parsed at once, across requests (a request waits up to ``HMCC_BODY_WAIT_S`` for its share,
  then gets 503 + Retry-After). No byte of a body is read before all of that, so neither an
  unauthenticated client nor a crowd of them can grow the API's memory.
* :class:`BodySizeLimit`: a declared ``Content-Length`` above ``HMCC_MAX_BODY_BYTES`` is 413 at
  once; a body without one (chunked) is counted as it streams in and refused with 413 as soon
  as it goes over (nothing is buffered here).
"""

from __future__ import annotations

import asyncio
import hmac
import json

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from hmcc_schema.parse import JSON, MSGPACK
from hmcc_worker.protocol import ErrorCode

from .settings import Settings

__all__ = ["BodySizeLimit", "V1Gate", "media_type"]


def media_type(content_type: str | None) -> str | None:
    """The body's media type the API reads (:data:`~hmcc_schema.parse.JSON` or
    :data:`~hmcc_schema.parse.MSGPACK`), or None for one it does not."""
    kind = (content_type or "").split(";")[0].strip().lower()
    if kind == JSON or kind.endswith("+json"):
        return JSON
    return MSGPACK if kind == MSGPACK else None


async def send_error(
    send: Send, status: int, code: str, message: str, headers: dict[str, str] | None = None
) -> None:
    """An error answer in the API's envelope, sent from middleware."""
    body = json.dumps({"error": {"code": code, "message": message}}).encode()
    extra = [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                *extra,
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


def _header(scope: Scope, name: bytes) -> str | None:
    for key, value in scope["headers"]:
        if key == name:
            return str(value.decode("latin-1"))
    return None


def _declared_length(scope: Scope) -> int | None:
    """The Content-Length, -1 when it is not a number, None without one."""
    value = _header(scope, b"content-length")
    if value is None:
        return None
    try:
        return int(value)
    except ValueError:
        return -1


class _ByteBudget:
    """A semaphore counted in bytes."""

    def __init__(self, total: int) -> None:
        self.total = total
        self.available = total
        self._changed = asyncio.Condition()

    async def acquire(self, n: int, timeout_s: float) -> bool:
        n = min(n, self.total)
        async with self._changed:
            try:
                await asyncio.wait_for(
                    self._changed.wait_for(lambda: self.available >= n), timeout_s
                )
            except TimeoutError:
                return False
            self.available -= n
            return True

    async def release(self, n: int) -> None:
        async with self._changed:
            self.available += min(n, self.total)
            self._changed.notify_all()


class V1Gate:
    """API key, content type and body budget of ``/v1`` requests (see the module docstring)."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.settings = settings
        self._key = None if settings.api_key is None else settings.api_key.get_secret_value()
        self._budget: _ByteBudget | None = None  # made on first use, in the server's loop

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "") if scope["type"] == "http" else ""
        if not (path == "/v1" or path.startswith("/v1/")):
            await self.app(scope, receive, send)
            return
        if self._key is not None:
            given = _header(scope, b"x-api-key")
            if given is None or not hmac.compare_digest(given.encode(), self._key.encode()):
                await send_error(
                    send,
                    401,
                    ErrorCode.unauthorized,
                    "missing or wrong X-API-Key header",
                    {"WWW-Authenticate": "X-API-Key"},
                )
                return
        if scope["method"] != "POST":
            await self.app(scope, receive, send)
            return
        if media_type(_header(scope, b"content-type")) is None:
            await send_error(
                send,
                415,
                ErrorCode.unsupported_media_type,
                f"send the body as JSON (Content-Type: {JSON}) or MessagePack ({MSGPACK})",
            )
            return
        declared = _declared_length(scope)
        limit = self.settings.max_body_bytes
        need = declared if declared is not None and 0 <= declared <= limit else limit
        if self._budget is None:
            self._budget = _ByteBudget(max(self.settings.body_budget_bytes, limit))
        if not await self._budget.acquire(need, self.settings.body_wait_s):
            await send_error(
                send,
                503,
                ErrorCode.server_busy,
                "too many request bodies are being read at once; retry later",
                {"Retry-After": str(self.settings.retry_after_s)},
            )
            return
        try:
            await self.app(scope, receive, send)
        finally:
            await self._budget.release(need)


class BodySizeLimit:
    """413 for bodies above ``max_bytes`` (see the module docstring)."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = _declared_length(scope)
        if declared is not None and declared < 0:
            await send_error(send, 400, ErrorCode.bad_request, "Content-Length is not a number")
            return
        if declared is not None and declared > self.max_bytes:
            await send_error(send, 413, ErrorCode.body_too_large, self._message())
            return
        received = 0

        async def counted() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise HTTPException(413, self._message())
            return message

        await self.app(scope, counted, send)

    def _message(self) -> str:
        return f"request body is larger than {self.max_bytes} bytes (HMCC_MAX_BODY_BYTES)"
