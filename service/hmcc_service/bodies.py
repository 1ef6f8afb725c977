"""Request bodies: read (already gated by :class:`~hmcc_service.limits.V1Gate`), parsed into
the core's :class:`~hmcc.flight.Flight` by :mod:`hmcc_schema` in the encoding the content type
names (JSON, or MessagePack with raw array buffers), off the event loop when large."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import anyio.to_thread
from fastapi import Request
from pydantic import ValidationError

from hmcc import InputError
from hmcc_schema.parse import JSON, MSGPACK

from .errors import invalid_input
from .limits import media_type

__all__ = ["INLINE_PARSE_BYTES", "body_schema", "parse_body"]

#: Bodies above this are parsed in a worker thread, so the event loop keeps answering.
INLINE_PARSE_BYTES = 256 * 1024

T = TypeVar("T")


async def parse_body(request: Request, parse: Callable[[bytes, str], T]) -> T:
    """The body, parsed by ``parse(raw, media type)`` (422 naming each problem)."""
    raw = await request.body()
    kind = media_type(request.headers.get("content-type")) or JSON
    try:
        if len(raw) <= INLINE_PARSE_BYTES:
            return parse(raw, kind)
        return await anyio.to_thread.run_sync(parse, raw, kind)
    except (ValidationError, InputError) as e:
        raise invalid_input(e) from None


def body_schema(name: str) -> dict[str, Any]:
    """``openapi_extra`` for a route that parses its body itself but documents it as the
    schema ``name``, in JSON (the contract) or MessagePack."""
    ref = {"$ref": f"#/components/schemas/{name}"}
    msgpack_note = (
        "The same body in MessagePack, where an array of numbers (keypoints, matches) may also "
        'be `{"dtype", "shape", "data"}`: raw little-endian values (`<f4`/`<f8` keypoints; '
        "`<i4`, `<i8`, `<u2`, `<u4` matches), read without parsing. For clients that send "
        "whole flights."
    )
    if name == "BatchRequest":
        msgpack_note += (
            " `pairs` may also be one object of columns, `{image1, image2, id?, counts, "
            "matches}`: the pairs' image ids (and ids, or null) as arrays, each pair's number "
            "of matches as a buffer (`<i4`/`<i8`), every pair's matches one after another as "
            "one (M, 2) buffer; read at once, not pair by pair. A pair with keypoints of its "
            "own or `match: true` has no columns."
        )
    return {
        "requestBody": {
            "required": True,
            "content": {
                JSON: {"schema": ref},
                MSGPACK: {"schema": ref, "description": msgpack_note},
            },
        }
    }
