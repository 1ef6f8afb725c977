"""Request bodies: read (already gated by :class:`~hmcc_service.limits.V1Gate`), parsed into
the core's :class:`~hmcc.flight.Flight` by :mod:`hmcc_schema`, off the event loop when large."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import anyio.to_thread
from fastapi import Request
from pydantic import ValidationError

from hmcc import InputError

from .errors import invalid_input

__all__ = ["INLINE_PARSE_BYTES", "body_schema", "parse_body"]

#: Bodies above this are parsed in a worker thread, so the event loop keeps answering.
INLINE_PARSE_BYTES = 256 * 1024

T = TypeVar("T")


async def parse_body(request: Request, parse: Callable[[bytes], T]) -> T:
    """The body, parsed by ``parse`` (422 naming each problem)."""
    raw = await request.body()
    try:
        if len(raw) <= INLINE_PARSE_BYTES:
            return parse(raw)
        return await anyio.to_thread.run_sync(parse, raw)
    except (ValidationError, InputError) as e:
        raise invalid_input(e) from None


def body_schema(name: str) -> dict[str, Any]:
    """``openapi_extra`` for a route that parses its JSON body itself but documents it as the
    schema ``name``."""
    return {
        "requestBody": {
            "required": True,
            "content": {"application/json": {"schema": {"$ref": f"#/components/schemas/{name}"}}},
        }
    }
