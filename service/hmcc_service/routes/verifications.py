"""``/v1/verifications``: submit one pair, read it (long poll), cancel it."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Path, Request, Response

from hmcc_schema import parse_pair
from hmcc_schema.parse import MSGPACK
from hmcc_worker.protocol import TERMINAL, ErrorCode, JobKind, JobStatus

from ..bodies import body_schema, parse_body
from ..deps import ApiKey, QueueDep, SettingsDep, Wait
from ..errors import ApiError, error_responses, queue_errors
from ..models import ErrorResponse, JobView
from ..queue import JobQueue, JobRecord, QueueUnavailable
from ..views import answer_type, job_view, job_view_msgpack, result_responses

log = logging.getLogger("hmcc.api")

router = APIRouter(prefix="/v1", tags=["verifications"], dependencies=[ApiKey])

JobId = Path(max_length=100, description="The id returned at submission.")
_ERRORS = error_responses("job")


async def _answer(
    request: Request,
    queue: JobQueue,
    record: JobRecord,
    submitted: bool = False,
    waited: bool = False,
) -> Response:
    """Reads are 200. A submission is 202, or 200 when it waited and the job ended. JSON, or
    MessagePack when the request's ``Accept`` asks for it (:func:`~..views.answer_type`)."""
    stored = None
    if record.status is JobStatus.finished:
        found = (await queue.outcomes([(record.job_id, 0, 1)]))[0]
        if not found:
            raise _not_found(record.job_id)
        stored = found[0]
    status = 200 if not submitted or (waited and record.status in TERMINAL) else 202
    kind = answer_type(request.headers.get("accept"))
    view = job_view_msgpack if kind == MSGPACK else job_view
    return Response(
        view(record, stored),
        status_code=status,
        media_type=kind,
        headers={"Location": f"/v1/verifications/{record.job_id}", "Vary": "Accept"},
    )


def _not_found(job_id: str) -> ApiError:
    return ApiError(
        404, ErrorCode.not_found, f"no verification job {job_id!r} (unknown or expired)"
    )


async def _find(queue: JobQueue, job_id: str, wait: float) -> JobRecord:
    record = await queue.wait(job_id, wait) if wait > 0 else (await queue.fetch([job_id]))[0]
    if record is None or record.kind is not JobKind.pair:
        raise _not_found(job_id)
    return record


@router.post(
    "/verifications",
    status_code=202,
    response_model=JobView,
    responses={
        **result_responses({200: "Finished within ?wait", 202: "Accepted"}, "JobView"),
        **_ERRORS,
    },
    operation_id="submit_verification",
    summary="Verify the matches of one image pair",
    openapi_extra=body_schema("PairRequest"),
)
async def submit_verification(
    request: Request, queue: QueueDep, settings: SettingsDep, wait: Wait = 0.0
) -> Response:
    """Queue one pair (the JSON pair format). 202 + ``Location``; with ``?wait=S``, 200 and
    the finished job if it ends within S seconds."""
    flight = await parse_body(request, parse_pair)
    async with queue_errors(settings):
        record = (await queue.submit(JobKind.pair, [flight]))[0]
    log.info("pair queued", extra={"job_id": record.job_id})
    if wait > 0:
        # The job is accepted now: a queue error while waiting must not hide it (a client
        # would submit it again), so the answer is then the 202 of an accepted job.
        try:
            record = await queue.wait(record.job_id, wait, pending=True) or record
        except QueueUnavailable:
            pass
    async with queue_errors(settings):
        return await _answer(request, queue, record, submitted=True, waited=wait > 0)


@router.get(
    "/verifications/{job_id}",
    response_model=JobView,
    responses={**result_responses({200: "The job"}, "JobView"), **_ERRORS},
    operation_id="get_verification",
    summary="A verification job: status, result or error",
)
async def get_verification(
    request: Request,
    queue: QueueDep,
    settings: SettingsDep,
    job_id: str = JobId,
    wait: Wait = 0.0,
) -> Response:
    """``?wait=S`` holds the request until the job ends or S seconds pass."""
    async with queue_errors(settings):
        record = await _find(queue, job_id, wait)
        return await _answer(request, queue, record)


@router.delete(
    "/verifications/{job_id}",
    response_model=JobView,
    responses={
        **result_responses({200: "The canceled job"}, "JobView"),
        409: {"model": ErrorResponse, "description": "Not queued any more"},
        **_ERRORS,
    },
    operation_id="cancel_verification",
    summary="Cancel a queued verification job",
)
async def cancel_verification(
    request: Request, queue: QueueDep, settings: SettingsDep, job_id: str = JobId
) -> Response:
    async with queue_errors(settings):
        await _find(queue, job_id, 0.0)
        record = await queue.cancel(job_id)
        if record is None:
            raise _not_found(job_id)
        return await _answer(request, queue, record)
