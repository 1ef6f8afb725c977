"""One error shape for every 4xx/5xx: ``{"error": {"code", "message", "issues"?}}``.

Messages name the field and the reason; nothing internal (paths, stack traces, exception
types) is ever sent: unexpected exceptions are logged and answered with a bare 500.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from hmcc.errors import InputError
from hmcc.schema import FieldIssue, validation_issues

__all__ = ["ApiError", "error_response", "install_error_handlers", "invalid_input"]

log = logging.getLogger("hmcc.api")


class ApiError(Exception):
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
    return ApiError(422, "invalid_input", message, issues=issues[:MAX_ISSUES])


_HTTP_CODES = {
    400: "bad_request",
    401: "unauthorized",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    413: "body_too_large",
    415: "unsupported_media_type",
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
            where = ".".join(str(p) for p in loc) or "body"
            issue = FieldIssue(field=where, reason=str(e.get("msg", "invalid")))
            if issue not in issues:
                issues.append(issue)
        message = "; ".join(f"{i.field}: {i.reason}" for i in issues[:5])
        return error_response(422, "invalid_input", message, issues)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = _HTTP_CODES.get(exc.status_code, "http_error")
        message = exc.detail if isinstance(exc.detail, str) else code.replace("_", " ")
        headers = dict(exc.headers) if exc.headers else None
        return error_response(exc.status_code, code, message, headers=headers)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error", extra={"path": request.url.path})
        return error_response(500, "internal_error", "internal error")
