"""What a request must pass before its body is read, and the deadlines and memory its body is
read under, as pure ASGI middleware.

* :class:`V1Gate` (``/v1`` routes): the API key (401) and, for a POST, the content type and
  content encoding (415) before a byte of the body is read. Then the body is read under:

  - **deadlines**: all of it within ``HMCC_BODY_TIMEOUT_S`` of the request's head, and, after
    ``HMCC_BODY_GRACE_S``, at ``HMCC_BODY_MIN_BYTES_PER_S`` at least (by ``grace + n / rate``
    seconds, more than ``n`` bytes). A body that misses them is answered 408
    ``request_timeout`` and its connection closed, which frees what it held.
  - **the body budget**: at most ``HMCC_BODY_BUDGET_BYTES`` of bodies are held at once, across
    requests, from their arrival until the request is answered (parsed and queued). A request
    holds the bytes of its body that have *arrived*, taken from the budget chunk by chunk, not
    the length its head declares: a declared length costs nothing until the bytes come, so
    idle or stalled connections hold (almost) nothing and cannot starve the others, and the
    memory bound is a bound on bytes really held. Bytes that do not fit wait for room, up to
    ``HMCC_BODY_WAIT_S`` (not counted against the deadlines), then 503 ``server_busy`` +
    Retry-After, which frees what the request held, so bodies competing for the last of the
    budget cannot all wait on each other for long: the first to give up lets the others end.

  Once the API began shutting down (SIGTERM, :mod:`hmcc_service.shutdown`), a request that
  waits :data:`SHUTDOWN_POLL_S` for more of its body is answered 503 ``shutting_down`` +
  Retry-After (a body that keeps coming is read to its end): a stalled upload must not hold
  the process, and the embedded queue would refuse its job anyway.

  A shared up-front reservation of the declared length is what let two clients declaring
  64 MB and sending one byte hold the whole budget; reserving as bytes arrive is the simplest
  design that makes the budget cost a client what it really sends.
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

from . import shutdown
from .errors import ApiError
from .settings import Settings

__all__ = ["SHUTDOWN_POLL_S", "BodySizeLimit", "V1Gate", "media_type"]

#: Seconds between two looks, by a request waiting for more of its body, at whether the API
#: began shutting down.
SHUTDOWN_POLL_S = 0.5


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
        self._waiting = 0

    async def acquire(self, n: int, timeout_s: float) -> bool:
        n = min(n, self.total)
        if self._waiting == 0 and self.available >= n:  # no await: atomic on the event loop
            self.available -= n
            return True
        self._waiting += 1
        try:
            async with self._changed:
                try:
                    async with asyncio.timeout(timeout_s):
                        await self._changed.wait_for(lambda: self.available >= n)
                except TimeoutError:
                    return False
                self.available -= n
                return True
        finally:
            self._waiting -= 1

    async def release(self, n: int) -> None:
        if n <= 0:
            return
        async with self._changed:
            self.available += min(n, self.total)
            self._changed.notify_all()


class _BodyReader:
    """The ``receive`` of one request, reading its body under the deadlines and taking each
    chunk's bytes from the budget (see the module docstring); ``held`` is what it took."""

    def __init__(self, receive: Receive, budget: _ByteBudget, settings: Settings) -> None:
        self._receive = receive
        self._budget = budget
        self._settings = settings
        self._loop = asyncio.get_running_loop()
        self._start = self._loop.time()
        self._ended = False
        self.received = 0
        self.held = 0

    def _deadline(self) -> float:
        s = self._settings
        allowed = min(s.body_timeout_s, s.body_grace_s + self.received / s.body_min_bytes_per_s)
        return self._start + allowed

    async def __call__(self) -> Message:
        if self._ended:  # the body is read: what comes now is the disconnect, whenever it does
            return await self._receive()
        message = await self._next()
        if message["type"] != "http.request":
            return message
        size = len(message.get("body", b""))
        waited = self._loop.time()
        if not await self._budget.acquire(size, self._settings.body_wait_s):
            raise ApiError(
                503,
                ErrorCode.server_busy,
                "too many request bodies are being read at once; retry later",
                headers={"Retry-After": str(self._settings.retry_after_s), "Connection": "close"},
            )
        self._start += self._loop.time() - waited  # the budget's wait is not the client's
        self.held += min(size, self._budget.total)
        self.received += size
        self._ended = not message.get("more_body", False)
        return message

    async def _next(self) -> Message:
        """The next message, by the deadline; looking every :data:`SHUTDOWN_POLL_S` whether
        the API began shutting down, when a body still to come is refused at once."""
        while True:
            deadline = self._deadline()
            try:
                async with asyncio.timeout_at(min(deadline, self._loop.time() + SHUTDOWN_POLL_S)):
                    return await self._receive()
            except TimeoutError:
                if self._loop.time() >= deadline:
                    raise self._timed_out() from None
                if shutdown.began():
                    raise ApiError(
                        503,
                        ErrorCode.shutting_down,
                        "the service is shutting down; send the request again later",
                        headers={
                            "Retry-After": str(self._settings.retry_after_s),
                            "Connection": "close",
                        },
                    ) from None

    def _timed_out(self) -> ApiError:
        s = self._settings
        return ApiError(
            408,
            ErrorCode.request_timeout,
            f"the request body did not arrive in time: {self.received} bytes arrived; a body"
            f" must arrive within {s.body_timeout_s:g} s (HMCC_BODY_TIMEOUT_S), at"
            f" {s.body_min_bytes_per_s} bytes/s at least after the first {s.body_grace_s:g} s"
            " (HMCC_BODY_MIN_BYTES_PER_S, HMCC_BODY_GRACE_S)",
            headers={"Connection": "close"},
        )


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
        encoding = (_header(scope, b"content-encoding") or "identity").strip().lower()
        if encoding != "identity":
            await send_error(
                send,
                415,
                ErrorCode.unsupported_media_type,
                f"Content-Encoding {encoding!r} is not supported: send the body uncompressed",
            )
            return
        if self._budget is None:
            total = max(self.settings.body_budget_bytes, self.settings.max_body_bytes)
            self._budget = _ByteBudget(total)
        body = _BodyReader(receive, self._budget, self.settings)
        try:
            await self.app(scope, body, send)
        finally:
            await self._budget.release(body.held)


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
