"""Queue records -> the bytes the API answers (shapes in :mod:`hmcc_service.models`), as JSON
or, when the request's ``Accept`` asks for it (:func:`answer_type`), as MessagePack.

A pair's result or error was encoded once, by the process that verified it, in both forms
(:mod:`hmcc_worker.outcomes`); here it is spliced into the answer as it is (JSON:
``orjson.Fragment``; MessagePack: the answer is written around the stored bytes), never parsed
again. In MessagePack, a result's ``inliers`` (and ``matches``) are ``{"dtype", "shape",
"data"}`` maps of raw little-endian values, as arrays travel in request bodies; every other
field is the JSON answer's.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from datetime import datetime, timedelta
from typing import Any

import msgpack
import orjson

from hmcc_schema.parse import JSON, MSGPACK
from hmcc_worker.outcomes import encode_result, unpack, unpack_msgpack
from hmcc_worker.protocol import ItemStatus, JobStatus

from .queue import JobRecord

__all__ = [
    "ITEM_STATUSES",
    "answer_type",
    "batch_counts",
    "batch_item",
    "batch_item_msgpack",
    "batch_page_msgpack",
    "job_view",
    "job_view_msgpack",
    "result_responses",
]

#: A batch item's statuses: a job's, and ``expired`` for a result no longer kept.
ITEM_STATUSES = tuple(s.value for s in ItemStatus)


def _iso(t: datetime | None) -> str | None:
    return None if t is None else t.isoformat().replace("+00:00", "Z")


def _ms(a: datetime | None, b: datetime | None) -> float | None:
    """Milliseconds from ``a`` to ``b``, to the microsecond the times hold (0.001 ms): rounded,
    since ``timedelta.total_seconds() * 1e3`` reads 12.300000000000001 for 12.3."""
    if a is None or b is None:
        return None
    return max(0.0, round((b - a) / timedelta(microseconds=1)) / 1e3)


def _outcome(
    record: JobRecord | None, stored: bytes | None
) -> tuple[str, orjson.Fragment | None, Any]:
    """``(status, result, error)`` of one pair of a job."""
    if record is None:
        return ItemStatus.expired.value, None, None
    if record.status is JobStatus.finished:
        if stored is None:
            return ItemStatus.expired.value, None, None
        status, body = unpack(stored)
        if status is JobStatus.finished:
            return status.value, orjson.Fragment(body), None
        return status.value, None, orjson.Fragment(body)
    return record.status.value, None, record.error


def _job_head(record: JobRecord, status: str) -> dict[str, Any]:
    """A ``JobView`` but its ``result`` and ``error``."""
    return {
        "job_id": record.job_id,
        "status": status,
        "submitted_at": _iso(record.submitted_at),
        "started_at": _iso(record.started_at),
        "finished_at": _iso(record.finished_at),
        "timings_ms": {
            "queue_wait": _ms(record.submitted_at, record.started_at),
            "run": _ms(record.started_at, record.finished_at),
            "turnaround": _ms(record.submitted_at, record.finished_at),
        },
    }


def job_view(record: JobRecord, stored: bytes | None) -> bytes:
    """A pair job as ``JobView``; ``stored``: its outcome once it finished (the caller answers
    404 for a finished job whose outcome is gone)."""
    status, result, error = _outcome(record, stored)
    return orjson.dumps(_job_head(record, status) | {"result": result, "error": error})


def batch_item(
    index: int, pair_id: str | None, record: JobRecord | None, stored: bytes | None
) -> dict[str, Any]:
    """One pair of a batch as ``BatchItem`` (a dict holding fragments, for orjson)."""
    status, result, error = _outcome(record, stored)
    return {"index": index, "id": pair_id, "status": status, "result": result, "error": error}


# -- MessagePack ------------------------------------------------------------------------------


def answer_type(accept: str | None) -> str:
    """The media type of an answer that carries results: :data:`MSGPACK` when ``accept`` (the
    request's ``Accept``) names it with a quality above 0 and at least that of JSON
    (``application/json``, else ``application/*``, else ``*/*``); else :data:`JSON`, whatever
    else ``accept`` asks for (an Accept the API cannot serve gets JSON, not 406)."""
    if not accept or MSGPACK not in accept.lower():
        return JSON
    quality: dict[str, float] = {}
    for part in accept.lower().split(","):
        kind, *params = (p.strip() for p in part.split(";"))
        q = 1.0
        for param in params:
            name, _, value = param.partition("=")
            if name.strip() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        quality[kind] = max(q, quality.get(kind, 0.0))
    json_q = next((quality[k] for k in (JSON, "application/*", "*/*") if k in quality), 0.0)
    wanted = quality.get(MSGPACK, 0.0)
    return MSGPACK if wanted > 0 and wanted >= json_q else JSON


def _header(n: int, small: int, short: int) -> bytes:
    """A MessagePack map (``small`` 0x80, ``short`` 0xde) or array (0x90, 0xdc) header."""
    if n < 16:
        return bytes((small | n,))
    if n < 2**16:
        return bytes((short,)) + n.to_bytes(2, "big")
    return bytes((short + 1,)) + n.to_bytes(4, "big")


def _map(head: dict[str, Any], packed: list[tuple[str, bytes | memoryview]]) -> bytes:
    """A MessagePack map: ``head``'s entries, then ``packed``'s, their values already packed."""
    parts: list[bytes | memoryview] = [_header(len(head) + len(packed), 0x80, 0xDE)]
    for key, value in head.items():
        parts += (msgpack.packb(key), msgpack.packb(value))
    for key, raw in packed:
        parts += (msgpack.packb(key), raw)
    return b"".join(parts)


_NIL = msgpack.packb(None)
#: A batch item's map header and first key, and its other keys (the order of ``BatchItem``).
_ITEM = _header(5, 0x80, 0xDE) + msgpack.packb("index")
_ID, _STATUS, _RESULT, _ERROR = (msgpack.packb(k) for k in ("id", "status", "result", "error"))
_STATUSES = {s: msgpack.packb(s) for s in ITEM_STATUSES}


def _outcome_msgpack(
    record: JobRecord | None, stored: bytes | None
) -> tuple[str, bytes | memoryview, bytes]:
    """:func:`_outcome` in MessagePack: ``(status, result, error)``, the last two packed."""
    if record is None or (record.status is JobStatus.finished and stored is None):
        return ItemStatus.expired.value, _NIL, _NIL
    if stored is not None and record.status is JobStatus.finished:
        status, packed = unpack_msgpack(stored)
        if packed is not None:
            return status.value, packed, _NIL
        # stored as JSON only (an error; a result from an older worker): converted here
        _, body = unpack(stored)
        if status is JobStatus.finished:
            return status.value, encode_result(orjson.loads(body)), _NIL
        return status.value, _NIL, msgpack.packb(orjson.loads(body))
    return record.status.value, _NIL, _NIL if record.error is None else msgpack.packb(record.error)


def job_view_msgpack(record: JobRecord, stored: bytes | None) -> bytes:
    """:func:`job_view` in MessagePack."""
    status, result, error = _outcome_msgpack(record, stored)
    return _map(_job_head(record, status), [("result", result), ("error", error)])


#: The parts of a packed batch item, joined once for the whole page.
Packed = tuple[bytes | memoryview, ...]


def batch_item_msgpack(
    index: int,
    pair_id: str | None,
    record: JobRecord | None,
    stored: bytes | None,
    pack: Callable[[Any], bytes] = msgpack.packb,
) -> Packed:
    """:func:`batch_item` in MessagePack, as the parts :func:`batch_page_msgpack` joins (the
    stored result among them as it is). ``pack``: a page's own ``msgpack.Packer().pack``
    rather than :func:`msgpack.packb`, which builds a packer each call."""
    status, result, error = _outcome_msgpack(record, stored)
    parts = (_ITEM, pack(index), _ID, pack(pair_id), _STATUS, _STATUSES[status])
    return (*parts, _RESULT, result, _ERROR, error)


def batch_page_msgpack(view: dict[str, Any], items: Sequence[Packed]) -> bytes:
    """A ``BatchView`` in MessagePack: ``view``'s fields but ``results``, then ``results``,
    the items of :func:`batch_item_msgpack`."""
    head = {k: v for k, v in view.items() if k != "results"}
    results = b"".join((_header(len(items), 0x90, 0xDC), *itertools.chain.from_iterable(items)))
    return _map(head, [("results", results)])


def batch_counts(
    chunks: Sequence[dict[str, Any]], records: Sequence[JobRecord | None]
) -> dict[str, int]:
    """Pairs per state, from the chunks' job records (outcomes not needed)."""
    counts = dict.fromkeys(ITEM_STATUSES, 0)
    for chunk, record in zip(chunks, records, strict=True):
        n = chunk["count"]
        if record is None:
            counts[ItemStatus.expired.value] += n
        elif record.status is JobStatus.finished:
            failed = record.failed or 0
            counts["failed"] += failed
            counts["finished"] += n - failed
        elif record.status is JobStatus.failed:
            counts["failed"] += n
        else:
            counts[record.status.value] += n
    return counts


def result_responses(answers: dict[int, str], model: str) -> dict[int | str, Any]:
    """OpenAPI ``responses`` of a route that answers ``model`` in either media type, for each
    status of ``answers`` (status -> what it answers)."""
    ref = {"schema": {"$ref": f"#/components/schemas/{model}"}}
    how = (
        f": JSON, or MessagePack when `Accept` names `{MSGPACK}` (with a quality at least "
        "that of JSON): the same fields, each result's `inliers` (and `matches`) a "
        '`{"dtype", "shape", "data"}` map of raw little-endian values (`<i4`, or `<i8` '
        "past 2^31). Any other `Accept` is answered in JSON."
    )
    return {
        status: {"description": what + how, "content": {JSON: ref, MSGPACK: ref}}
        for status, what in answers.items()
    }
