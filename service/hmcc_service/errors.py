"""One error shape for every 4xx/5xx: ``{"error": {"code", "message", "issues"?}}``.

Messages name the field and the reason; nothing internal (paths, stack traces, exception
types) is ever sent: unexpected exceptions are logged and answered with a bare 500.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.routing import Match

from hmcc import InputError
from hmcc_schema import FieldIssue, clip, validation_issues
from hmcc_worker.protocol import ErrorCode

from .models import ErrorResponse
from .queue import NotCancelable, QueueFull, QueueUnavailable, ShuttingDown
from .settings import Settings

__all__ = [
    "MAX_ISSUES",
    "ApiError",
    "error_response",
    "error_responses",
    "install_error_handlers",
    "invalid_input",
    "queue_errors",
]

log = logging.getLogger("hmcc.api")


class ApiError(Exception):
    """An error answer: HTTP ``status``, ``code`` (an :class:`ErrorCode`), ``message``."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        *,
        issues: list[FieldIssue] | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.status, self.code, self.message = status, code, message
        self.issues, self.headers = issues, headers


def error_response(
    status: int,
    code: str,
    message: str,
    issues: list[FieldIssue] | None = None,
    headers: dict[str, str] | None = None,
) -> JSONResponse:
    body: dict[str, Any] = {"code": code, "message": message}
    if issues is not None:
        body["issues"] = [i.model_dump() for i in issues]
    return JSONResponse({"error": body}, status_code=status, headers=headers)


#: Issues listed in one answer at most (a body can hold 10^5 bad numbers).
MAX_ISSUES = 100


def invalid_input(error: ValidationError | InputError) -> ApiError:
    """422 naming each offending field (the first ``MAX_ISSUES``; the message says how many
    more there were)."""
    issues = validation_issues(error)
    message = "; ".join(f"{i.field}: {i.reason}" for i in issues[:5])
    if len(issues) > 5:
        message += f"; and {len(issues) - 5} more"
    return ApiError(422, ErrorCode.invalid_input, message, issues=issues[:MAX_ISSUES])


@asynccontextmanager
async def queue_errors(settings: Settings) -> AsyncIterator[None]:
    """The queue's exceptions as answers: 429/503 with Retry-After, 409."""
    retry = {"Retry-After": str(settings.retry_after_s)}
    try:
        yield
    except QueueFull:
        raise ApiError(
            429,
            ErrorCode.queue_full,
            f"more than {settings.max_queue_depth} jobs are waiting; retry later",
            headers=retry,
        ) from None
    except QueueUnavailable as e:
        raise ApiError(
            503,
            ErrorCode.queue_unavailable,
            str(e) or "the job queue (Redis) is unreachable; retry later",
            headers=retry,
        ) from None
    except ShuttingDown:
        raise ApiError(
            503,
            ErrorCode.shutting_down,
            "the service is shutting down and takes no new jobs; retry later",
            headers=retry,
        ) from None
    except NotCancelable as e:
        raise ApiError(
            409,
            ErrorCode.not_cancelable,
            f"the job is {e.status.value}; only a queued job can be cancelled",
        ) from None


def error_responses(thing: str) -> dict[int | str, dict[str, Any]]:
    """The error answers every /v1 route documents (``thing``: what a 404 did not find)."""

    def doc(description: str) -> dict[str, Any]:
        return {"model": ErrorResponse, "description": description}

    return {
        401: doc("API key missing or wrong"),
        404: doc(f"No such {thing} (or it expired)"),
        408: doc("Body not received in time (HMCC_BODY_TIMEOUT_S, HMCC_BODY_MIN_BYTES_PER_S)"),
        413: doc("Body too large"),
        415: doc("Body is neither JSON nor MessagePack (Content-Type), or is compressed"),
        422: doc("Invalid input: each field and reason"),
        429: doc("Queue full; see Retry-After"),
        503: doc(
            "Queue unreachable, too many bodies being read, or shutting down; see Retry-After"
        ),
    }


_HTTP_CODES = {
    400: ErrorCode.bad_request,
    401: ErrorCode.unauthorized,
    404: ErrorCode.not_found,
    405: ErrorCode.method_not_allowed,
    408: ErrorCode.request_timeout,
    413: ErrorCode.body_too_large,
    414: ErrorCode.uri_too_long,
    415: ErrorCode.unsupported_media_type,
    431: ErrorCode.headers_too_large,
}


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        return error_response(exc.status, exc.code, exc.message, exc.issues, exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _request_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        issues: list[FieldIssue] = []
        for e in exc.errors():
            loc = [p for p in e.get("loc", ()) if p not in ("body",)]
            where = clip(".".join(str(p) for p in loc)) or "body"
            issue = FieldIssue(field=where, reason=clip(str(e.get("msg", "invalid"))))
            if issue not in issues:
                issues.append(issue)
        message = "; ".join(f"{i.field}: {i.reason}" for i in issues[:5])
        return error_response(422, ErrorCode.invalid_input, message, issues)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> Response:
        code = str(_HTTP_CODES.get(exc.status_code, "http_error"))
        message = exc.detail if isinstance(exc.detail, str) else code.replace("_", " ")
        headers = dict(exc.headers) if exc.headers else None
        if exc.status_code == 405:  # every method of the path, not the first route's only
            allow = {"Allow": ", ".join(_allowed(request))}
            if request.method == "OPTIONS":  # what OPTIONS asks is answered, not refused
                return Response(status_code=204, headers=allow)
            headers = {**(headers or {}), **allow}
        return error_response(exc.status_code, code, message, headers=headers)

    @app.exception_handler(ClientDisconnect)
    async def _client_disconnect(request: Request, exc: ClientDisconnect) -> Response:
        """The client went away before its body arrived: its doing, not an error of ours.
        Counted as 499 (nginx's "client closed request"); the answer goes nowhere."""
        log.info(
            "client disconnected before its request body arrived",
            extra={"path": request.url.path},
        )
        return Response(status_code=499)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error", extra={"path": request.url.path})
        return error_response(500, ErrorCode.internal_error, "internal error")


def _allowed(request: Request) -> list[str]:
    """The methods some route of the app accepts for this request's path."""
    scope = {**request.scope, "method": "GET"}
    methods: set[str] = set()
    stack = list(request.app.router.routes)
    while stack:
        route = stack.pop()
        nested = getattr(route, "original_router", None)  # an included router (FastAPI)
        if nested is not None:
            stack.extend(nested.routes)
        elif route.matches(scope)[0] is not Match.NONE:
            methods |= set(getattr(route, "methods", None) or ())
    if methods:
        methods.add("OPTIONS")
    return sorted(methods)
