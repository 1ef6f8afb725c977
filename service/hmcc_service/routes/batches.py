"""``/v1/batches``: many pairs of one flight, images sent once, split into queue jobs."""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from typing import Any

from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.responses import JSONResponse

from hmcc.errors import InputError
from hmcc.schema import BatchPair, BatchRequest, FieldIssue

from ..errors import ApiError, invalid_input
from ..models import BatchView
from ..queue import JobQueue, new_id
from ..settings import Settings
from ..views import batch_counts, batch_item
from .common import (
    body_schema,
    error_responses,
    get_queue,
    queue_errors,
    read_json,
    require_api_key,
)

log = logging.getLogger("hmcc.api")

router = APIRouter(prefix="/v1", tags=["batches"], dependencies=[Depends(require_api_key)])

_ERRORS = error_responses("batch")


def split(pairs: list[BatchPair], max_pairs: int, max_matches: int) -> list[list[BatchPair]]:
    """Consecutive chunks of at most ``max_pairs`` pairs and ``max_matches`` matches (a pair
    with more matches than that is a chunk of its own)."""
    chunks: list[list[BatchPair]] = []
    current: list[BatchPair] = []
    matches = 0
    for pair in pairs:
        n = len(pair.matches)
        if current and (len(current) == max_pairs or matches + n > max_matches):
            chunks.append(current)
            current, matches = [], 0
        current.append(pair)
        matches += n
    if current:
        chunks.append(current)
    return chunks


def _chunk(batch: BatchRequest, pairs: list[BatchPair]) -> BatchRequest:
    """A chunk is a batch of its own: its pairs and only the images they name."""
    ids = {p.image1 for p in pairs} | {p.image2 for p in pairs}
    chunk = BatchRequest.model_construct(
        images={i: batch.images[i] for i in ids},
        pairs=pairs,
        plane=batch.plane,
        method=batch.method,
        params=batch.params,
    )
    return chunk


def _view(
    meta: dict[str, Any], counts: dict[str, int], offset: int, limit: int,
    items: list[dict[str, Any]],
) -> dict[str, Any]:
    total = meta["total"]
    pending = counts["queued"] + counts["started"]
    if pending == 0:
        status = "finished"
    elif counts["queued"] == total:
        status = "queued"
    else:
        status = "running"
    end = offset + len(items)
    return {
        "batch_id": meta["batch_id"],
        "status": status,
        "submitted_at": meta["submitted_at"],
        "total": total,
        **counts,
        "jobs": len(meta["chunks"]),
        "offset": offset,
        "limit": limit,
        "next_offset": end if end < total and items else None,
        "results": items,
    }


@router.post(
    "/batches",
    status_code=202,
    response_model=BatchView,
    responses=_ERRORS,
    operation_id="submit_batch",
    summary="Verify many pairs of one flight",
    openapi_extra=body_schema("BatchRequest"),
)
async def submit_batch(request: Request, queue: JobQueue = Depends(get_queue)) -> JSONResponse:
    """Images once (id -> camera and pose), then pairs by image id. The pairs are split into
    jobs of at most ``HMCC_BATCH_CHUNK_PAIRS`` pairs / ``HMCC_BATCH_CHUNK_MATCHES`` matches."""
    settings: Settings = request.app.state.settings
    batch = await read_json(request, BatchRequest)
    try:
        batch.check_images()
    except InputError as e:
        raise invalid_input(e) from None
    if len(batch.pairs) > settings.max_batch_pairs:
        reason = f"{len(batch.pairs)} pairs; at most {settings.max_batch_pairs} per batch"
        raise ApiError(422, "invalid_input", f"pairs: {reason}",
                       issues=[FieldIssue(field="pairs", reason=reason)])
    chunks = split(batch.pairs, settings.batch_chunk_pairs, settings.batch_chunk_matches)
    payloads = [_chunk(batch, c) for c in chunks]
    batch_id = new_id()
    async with queue_errors(settings):
        records = await queue.submit("chunk", payloads)
        starts = [0]
        for c in chunks[:-1]:
            starts.append(starts[-1] + len(c))
        meta = {
            "batch_id": batch_id,
            "submitted_at": datetime.now(UTC).isoformat().replace("+00:00", "Z"),
            "total": len(batch.pairs),
            "ids": [p.id for p in batch.pairs],
            "chunks": [
                {"job_id": r.job_id, "start": s, "count": len(c)}
                for r, s, c in zip(records, starts, chunks, strict=True)
            ],
            "ttl_s": min(settings.result_ttl_s + len(chunks) * settings.job_timeout_s, 30 * 86400),
        }
        await queue.put_batch(batch_id, meta)
    log.info("batch queued: %d pairs in %d jobs", len(batch.pairs), len(chunks),
             extra={"job_id": batch_id})
    counts = dict.fromkeys(("queued", "started", "finished", "failed", "canceled"), 0)
    counts["queued"] = len(batch.pairs)
    return JSONResponse(
        _view(meta, counts, 0, 0, []),
        status_code=202,
        headers={"Location": f"/v1/batches/{batch_id}"},
    )


@router.get(
    "/batches/{batch_id}",
    response_model=BatchView,
    responses=_ERRORS,
    operation_id="get_batch",
    summary="A batch's progress and one page of its results",
)
async def get_batch(
    request: Request,
    batch_id: str = Path(max_length=100),
    offset: int = Query(0, ge=0, description="First pair index of the page."),
    limit: int = Query(100, ge=0, le=1000, description="Pairs per page (0: progress only)."),
    queue: JobQueue = Depends(get_queue),
) -> JSONResponse:
    async with queue_errors(request.app.state.settings):
        meta = await queue.get_batch(batch_id)
        if meta is None:
            raise ApiError(404, "not_found", f"no batch {batch_id!r} (unknown or expired)")
        chunks = meta["chunks"]
        records = await queue.fetch([c["job_id"] for c in chunks], with_outcome=False)
        counts = batch_counts(chunks, records)
        end = min(offset + limit, meta["total"])
        page = [
            k for k, c in enumerate(chunks) if c["start"] < end and c["start"] + c["count"] > offset
        ]
        full = await queue.fetch([chunks[k]["job_id"] for k in page]) if page else []
    by_chunk = dict(zip(page, full, strict=True))
    items = []
    for k in page:
        c = chunks[k]
        for position in range(c["count"]):
            index = c["start"] + position
            if offset <= index < end:
                items.append(batch_item(index, meta["ids"][index], by_chunk[k], position))
    return JSONResponse(_view(meta, counts, offset, limit, items))
