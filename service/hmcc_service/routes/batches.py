"""``/v1/batches``: many pairs of one flight, images sent once, split into queue jobs."""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import logging
import time
from collections.abc import Callable, Sequence
from datetime import UTC, datetime
from typing import Any

import msgpack
import orjson
from fastapi import APIRouter, Path, Query, Request, Response

from hmcc.flight import Flight, FlightPair
from hmcc_schema.columns import PairColumns, parse_batch_body
from hmcc_schema.parse import MSGPACK
from hmcc_worker.protocol import TERMINAL, BatchStatus, ErrorCode, JobKind

from ..bodies import body_schema, parse_body
from ..deps import ApiKey, BatchWait, QueueDep, SettingsDep
from ..errors import ApiError, error_responses, queue_errors
from ..models import BatchView
from ..queue import JobQueue, JobRecord, new_id
from ..views import (
    answer_type,
    batch_counts,
    batch_item,
    batch_item_msgpack,
    batch_page_msgpack,
    result_responses,
)

log = logging.getLogger("hmcc.api")

router = APIRouter(prefix="/v1", tags=["batches"], dependencies=[ApiKey])

_ERRORS = error_responses("batch")


#: A batch is shared among at least this many jobs, and at least as many as the service runs
#: at once (its workers), while its jobs keep at least :data:`MIN_CHUNK_PAIRS` pairs: a small
#: batch still runs on every worker, a large one in jobs as large as that allows (up to
#: ``HMCC_BATCH_CHUNK_PAIRS``), so that a job's own cost (about 10 ms of the API's, Redis's and
#: its worker's CPU with RQ) stays small against its pairs'.
MIN_JOBS = 8
MIN_CHUNK_PAIRS = 16
#: The largest ``offset`` of a page: above the pairs of any batch a body can carry (a pair
#: takes tens of bytes), and far within every JSON number the answer echoes it in.
MAX_OFFSET = 1_000_000_000


def split(
    pairs: Sequence[FlightPair],
    max_pairs: int,
    max_matches: int,
    weights: Sequence[int] | None = None,
    min_jobs: int = MIN_JOBS,
) -> list[range]:
    """Consecutive chunks of at most ``max_pairs`` pairs and ``max_matches`` matches (a pair
    with more matches than that is a chunk of its own), as ranges of pair indices; smaller
    chunks (down to :data:`MIN_CHUNK_PAIRS`) when that gives fewer than ``min_jobs``.
    ``weights``: each pair's count instead of its matches (:func:`pair_weights`)."""
    max_pairs = min(max_pairs, max(MIN_CHUNK_PAIRS, -(-len(pairs) // max(1, min_jobs))))
    chunks: list[range] = []
    start = matches = 0
    # each pair's weight (a pair of columns is not built to be counted)
    counts = (len(p.matches) for p in pairs) if weights is None else weights
    for i, n in enumerate(counts):
        if i > start and (i - start == max_pairs or matches + n > max_matches):
            chunks.append(range(start, i))
            start, matches = i, 0
        matches += n
    chunks.append(range(start, len(pairs)))
    return chunks


def pair_weights(flight: Flight) -> list[int]:
    """What each pair counts toward a chunk's matches: its matches, or, for a pair that asks
    for matching, its first image's keypoints (each compared with its candidates: matching a
    pair costs more than verifying its matches)."""
    if isinstance(flight.pairs, PairColumns):  # no pair of columns asks for matching
        return flight.pairs.counts().tolist()
    weights = []
    for p in flight.pairs:
        keypoints = flight.images[p.image1].keypoints
        weights.append(len(keypoints) if p.match and keypoints is not None else len(p.matches))
    return weights


def subset(flight: Flight, chunk: range) -> Flight:
    """The flight of pairs ``chunk`` and the images they name (pairs as columns stay
    columns: :meth:`~hmcc_schema.columns.PairColumns.take`)."""
    if not isinstance(flight.pairs, PairColumns):
        return flight.subset(chunk)
    pairs = flight.pairs.take(chunk)
    images = {name: flight.images[name] for name in pairs.image_names()}
    return dataclasses.replace(flight, images=images, pairs=pairs)


def _view(
    meta: dict[str, Any],
    counts: dict[str, int],
    offset: int,
    limit: int,
    items: Sequence[Any],
) -> dict[str, Any]:
    total = meta["total"]
    if counts["queued"] + counts["started"] == 0:
        status = BatchStatus.finished.value
    elif counts["queued"] == total:
        status = BatchStatus.queued.value
    else:
        status = BatchStatus.running.value
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


def _json(
    doc: dict[str, Any], status: int = 200, headers: dict[str, str] | None = None
) -> Response:
    return Response(
        orjson.dumps(doc), status_code=status, media_type="application/json", headers=headers
    )


@router.post(
    "/batches",
    status_code=202,
    response_model=BatchView,
    responses=_ERRORS,
    operation_id="submit_batch",
    summary="Verify many pairs of one flight",
    openapi_extra=body_schema("BatchRequest"),
)
async def submit_batch(request: Request, queue: QueueDep, settings: SettingsDep) -> Response:
    """Images once (id -> camera, pose and optionally keypoints), then pairs by image id. The
    pairs are split into jobs of at most ``HMCC_BATCH_CHUNK_PAIRS`` pairs /
    ``HMCC_BATCH_CHUNK_MATCHES`` matches, and into at least 8 jobs, and at least one a worker,
    while each keeps 16 pairs or more; each job reads the batch's images it needs. A pair may
    ask for matching (``match: true``) instead of bringing matches: its images'
    ``descriptors`` are matched guided by the rough poses (options in ``matching``) and the
    result holds the matches; such a pair counts its first image's keypoints toward
    ``HMCC_BATCH_CHUNK_MATCHES``. In MessagePack, the pairs may come as columns (``pairs``:
    ``{image1, image2, id?, counts, matches}``), read at once."""
    flight = await parse_body(
        request, lambda raw, kind: parse_batch_body(raw, settings.max_batch_pairs, kind)
    )
    async with queue_errors(settings):
        chunks = split(
            flight.pairs,
            *settings.chunk_limits(),
            pair_weights(flight),
            max(MIN_JOBS, await queue.workers()),
        )
        # Results live as long as the batch: a finished pair never turns into a missing one.
        ttl = min(settings.result_ttl_s + len(chunks) * settings.job_timeout_s, 30 * 86400)
        batch_id = new_id()
        parts: list[Flight] = [subset(flight, c) for c in chunks]
        records = await queue.submit(
            JobKind.chunk, parts, batch_id=batch_id, images=flight.images, ttl_s=ttl
        )
        meta: dict[str, Any] = {
            "batch_id": batch_id,
            "submitted_at": datetime.now(UTC).isoformat().replace("+00:00", "Z"),
            "total": len(flight.pairs),
            "ids": (
                flight.pairs.pair_ids()
                if isinstance(flight.pairs, PairColumns)
                else [p.id for p in flight.pairs]
            ),
            "chunks": [
                {"job_id": r.job_id, "start": c.start, "count": len(c)}
                for r, c in zip(records, chunks, strict=True)
            ],
            "ttl_s": ttl,
        }
        await queue.put_batch(batch_id, meta)
    log.info(
        "batch queued: %d pairs in %d jobs",
        len(flight.pairs),
        len(chunks),
        extra={"job_id": batch_id},
    )
    counts = batch_counts(meta["chunks"], records)
    return _json(_view(meta, counts, 0, 0, []), 202, {"Location": f"/v1/batches/{batch_id}"})


@router.get(
    "/batches/{batch_id}",
    response_model=BatchView,
    responses={**result_responses({200: "The batch's progress and page"}, "BatchView"), **_ERRORS},
    operation_id="get_batch",
    summary="A batch's progress and one page of its results",
)
async def get_batch(
    request: Request,
    queue: QueueDep,
    settings: SettingsDep,
    batch_id: str = Path(max_length=100),
    offset: int = Query(
        0,
        ge=0,
        le=MAX_OFFSET,
        description=f"First pair index of the page, at most {MAX_OFFSET} (past the last "
        "pair: an empty page).",
    ),
    limit: int = Query(100, ge=0, le=1000, description="Pairs per page (0: progress only)."),
    wait: BatchWait = 0.0,
    ended: bool = Query(
        False,
        description="End the page before its first pair still queued or started: only the "
        "pairs that ended from `offset` on, in order (a client reading results as they end "
        "is not sent those it would ask for again).",
    ),
) -> Response:
    """``?wait=S`` holds the request until a pair of the batch ends (or the batch is
    finished), at most S seconds: progress without polling; with ``?ended=true`` the page
    stops before its first pair still queued or started. JSON, or MessagePack with each
    result's ``inliers`` (and ``matches``) as raw arrays when ``Accept`` asks for
    ``application/vnd.hmcc+msgpack``."""
    kind = answer_type(request.headers.get("accept"))
    item: Callable[..., Any] = batch_item
    if kind == MSGPACK:  # one packer for the page's items (not shared between requests)
        item = functools.partial(batch_item_msgpack, pack=msgpack.Packer().pack)
    async with queue_errors(settings):
        meta = await queue.get_batch(batch_id)
        if meta is None:
            raise ApiError(404, ErrorCode.not_found, f"no batch {batch_id!r} (unknown or expired)")
        chunks = meta["chunks"]
        ids = [c["job_id"] for c in chunks]
        records = await _progress(queue, ids, wait)
        counts = batch_counts(chunks, records)
        count = min(limit, _first_waiting(chunks, records, offset) - offset) if ended else limit
        items = await _page(queue, meta, records, offset, count, item)
        if counts["queued"] + counts["started"] == 0:
            await queue.batch_ended(batch_id)
    view = _view(meta, counts, offset, limit, items)
    vary = {"Vary": "Accept"}
    if kind == MSGPACK:
        return Response(batch_page_msgpack(view, items), media_type=MSGPACK, headers=vary)
    return _json(view, headers=vary)


async def _progress(queue: JobQueue, ids: list[str], wait: float) -> list[JobRecord | None]:
    """The chunks' records, after at most ``wait`` seconds for one of them to end."""
    records = await queue.fetch(ids)
    deadline = time.monotonic() + wait
    pending = _pending(ids, records)
    while pending and (left := deadline - time.monotonic()) > 0:
        await queue.wait_any(pending, min(left, 1.0))
        records = await queue.fetch(ids)
        if len(now := _pending(ids, records)) < len(pending):
            break
        pending = now
        await asyncio.sleep(0)
    return records


def _first_waiting(
    chunks: list[dict[str, Any]], records: list[JobRecord | None], offset: int
) -> int:
    """The index of the first pair from ``offset`` on whose chunk is still queued or started
    (past the last pair: none is)."""
    for c, r in zip(chunks, records, strict=True):
        if c["start"] + c["count"] > offset and r is not None and r.status not in TERMINAL:
            return max(offset, c["start"])
    return MAX_OFFSET + 1


def _pending(ids: list[str], records: list[JobRecord | None]) -> list[str]:
    return [
        i for i, r in zip(ids, records, strict=True) if r is not None and r.status not in TERMINAL
    ]


async def _page(
    queue: JobQueue,
    meta: dict[str, Any],
    records: list[JobRecord | None],
    offset: int,
    limit: int,
    item: Callable[[int, str | None, JobRecord | None, bytes | None], Any],
) -> list[Any]:
    """Items ``offset .. offset + limit - 1``, each made by ``item(index, id, record, stored
    outcome)``: each chunk of the page contributes the slice of its stored outcomes that falls
    in it (one round trip for all)."""
    end = min(offset + limit, meta["total"])
    page = [
        k
        for k, c in enumerate(meta["chunks"])
        if c["start"] < end and c["start"] + c["count"] > offset
    ]
    ranges = []
    for k in page:
        c = meta["chunks"][k]
        first = max(offset, c["start"]) - c["start"]
        last = min(end, c["start"] + c["count"]) - c["start"]
        ranges.append((c["job_id"], first, last))
    finished = [
        i
        for i, k in enumerate(page)
        if (r := records[k]) is not None and r.status.value == "finished"
    ]
    stored = await queue.outcomes([ranges[i] for i in finished]) if finished else []
    by_page = dict(zip(finished, stored, strict=True))
    items = []
    for i, k in enumerate(page):
        c, (_, first, last) = meta["chunks"][k], ranges[i]
        outcomes = by_page.get(i)
        for position in range(first, last):
            index = c["start"] + position
            one = (
                None
                if outcomes is None or position - first >= len(outcomes)
                else (outcomes[position - first])
            )
            items.append(item(index, meta["ids"][index], records[k], one))
    return items
