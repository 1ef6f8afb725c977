"""``/v1/limits``: what one request may hold, read by clients that split a flight into batches
(:meth:`hmcc_client.HmccClient.verify_flight`)."""

from __future__ import annotations

from fastapi import APIRouter

from hmcc import METHODS
from hmcc_schema.models import MAX_BATCH_IMAGES, MAX_KEYPOINTS, MAX_MATCHES

from ..deps import ApiKey, SettingsDep
from ..errors import error_responses
from ..models import MAX_WAIT_S, Limits

router = APIRouter(prefix="/v1", tags=["service"], dependencies=[ApiKey])


@router.get(
    "/limits",
    response_model=Limits,
    responses={401: error_responses("limit")[401]},
    operation_id="get_limits",
    summary="What one request may hold",
)
async def get_limits(settings: SettingsDep) -> Limits:
    return Limits(
        max_body_bytes=settings.max_body_bytes,
        max_batch_pairs=settings.max_batch_pairs,
        max_batch_images=MAX_BATCH_IMAGES,
        max_keypoints=MAX_KEYPOINTS,
        max_matches=MAX_MATCHES,
        batch_chunk_pairs=settings.chunk_limits()[0],
        max_wait_s=MAX_WAIT_S,
        max_queue_depth=settings.max_queue_depth,
        methods=list(METHODS),
    )
