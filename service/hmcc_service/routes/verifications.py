"""``/v1/verifications``: submit one pair, read it (long poll), cancel it."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Depends, Path, Request
from fastapi.responses import JSONResponse

from hmcc.schema import PairRequest

from ..errors import ApiError
from ..models import ErrorResponse, JobView
from ..queue import TERMINAL, JobQueue, JobRecord, QueueUnavailable
from ..views import job_view
from .common import (
    Wait,
    body_schema,
    error_responses,
    get_queue,
    queue_errors,
    read_json,
    require_api_key,
)

log = logging.getLogger("hmcc.api")

router = APIRouter(prefix="/v1", tags=["verifications"], dependencies=[Depends(require_api_key)])

JobId = Path(max_length=100, description="The id returned at submission.")
_ERRORS = error_responses("job")


def _answer(record: JobRecord, submitted: bool = False, waited: bool = False) -> JSONResponse:
    """Reads are 200. A submission is 202, or 200 when it waited and the job ended."""
    status = 200 if not submitted or (waited and record.status in TERMINAL) else 202
    return JSONResponse(
        job_view(record),
        status_code=status,
        headers={"Location": f"/v1/verifications/{record.job_id}"},
    )


async def _find(queue: JobQueue, job_id: str, wait: float) -> JobRecord:
    record = await queue.wait(job_id, wait) if wait > 0 else (await queue.fetch([job_id]))[0]
    if record is None or record.kind != "pair":
        raise ApiError(404, "not_found", f"no verification job {job_id!r} (unknown or expired)")
    return record


@router.post(
    "/verifications",
    status_code=202,
    response_model=JobView,
    responses={200: {"model": JobView, "description": "Finished within ?wait"}, **_ERRORS},
    operation_id="submit_verification",
    summary="Verify the matches of one image pair",
    openapi_extra=body_schema("PairRequest"),
)
async def submit_verification(
    request: Request, wait: float = Wait, queue: JobQueue = Depends(get_queue)
) -> JSONResponse:
    """Queue one pair (the JSON pair format). 202 + ``Location``; with ``?wait=S``, 200 and
    the finished job if it ends within S seconds."""
    pair = await read_json(request, PairRequest)
    async with queue_errors(request.app.state.settings):
        record = (await queue.submit("pair", [pair]))[0]
    log.info("pair queued", extra={"job_id": record.job_id})
    if wait > 0:
        # The job is accepted now: a queue error while waiting must not hide it (a client
        # would submit it again), so the answer is then the 202 of an accepted job.
        try:
            record = await queue.wait(record.job_id, wait, pending=True) or record
        except QueueUnavailable:
            pass
    return _answer(record, submitted=True, waited=wait > 0)


@router.get(
    "/verifications/{job_id}",
    response_model=JobView,
    responses=_ERRORS,
    operation_id="get_verification",
    summary="A verification job: status, result or error",
)
async def get_verification(
    request: Request, job_id: str = JobId, wait: float = Wait,
    queue: JobQueue = Depends(get_queue),
) -> JSONResponse:
    """``?wait=S`` holds the request until the job ends or S seconds pass."""
    async with queue_errors(request.app.state.settings):
        record = await _find(queue, job_id, wait)
    return _answer(record)


@router.delete(
    "/verifications/{job_id}",
    response_model=JobView,
    responses={409: {"model": ErrorResponse, "description": "Not queued any more"}, **_ERRORS},
    operation_id="cancel_verification",
    summary="Cancel a queued verification job",
)
async def cancel_verification(
    request: Request, job_id: str = JobId, queue: JobQueue = Depends(get_queue)
) -> JSONResponse:
    async with queue_errors(request.app.state.settings):
        await _find(queue, job_id, 0.0)
        record = await queue.cancel(job_id)
    if record is None:
        raise ApiError(404, "not_found", f"no verification job {job_id!r} (unknown or expired)")
    return _answer(record)
