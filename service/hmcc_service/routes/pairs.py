"""``/v1/pairs``: the pairs worth matching among a flight's images, chosen by footprint
overlap from their rough poses (:func:`hmcc.footprint.flight_pairs`), answered at once.

No queue: the work is geometry on the images' cameras and poses (no keypoints), about a
millisecond an image and tens of microseconds a candidate pair (``docs/service/api.md`` has
the figures). It runs in a worker thread, at most :data:`CONCURRENT_CHOICES` at once, so the
event loop keeps answering; :data:`MAX_CANDIDATES` bounds one request's work.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import anyio
import anyio.to_thread
import orjson
from fastapi import APIRouter, Request, Response

from hmcc import InputError
from hmcc.footprint import FlightPairs
from hmcc_schema import PairsQuery, parse_pairs

from ..bodies import body_schema, parse_body
from ..deps import ApiKey
from ..errors import error_responses, invalid_input
from ..models import PairsView

__all__ = ["CONCURRENT_CHOICES", "MAX_CANDIDATES", "router"]

log = logging.getLogger("hmcc.api")

router = APIRouter(prefix="/v1", tags=["pairs"], dependencies=[ApiKey])

#: Candidate pairs (footprints whose circles meet) one request may make the service clip: a
#: few seconds of one core. A request above it is 422 on ``images``.
MAX_CANDIDATES = 500_000
#: Requests choosing pairs at once (each in a thread); the others wait for one to end.
CONCURRENT_CHOICES = 2

_ERRORS = {code: doc for code, doc in error_responses("route").items() if code not in (404, 429)}


def _choose(query: PairsQuery) -> tuple[FlightPairs, float]:
    t0 = time.perf_counter()
    chosen = query.choose(MAX_CANDIDATES)
    return chosen, (time.perf_counter() - t0) * 1e3


@router.post(
    "/pairs",
    response_model=PairsView,
    responses=_ERRORS,
    operation_id="choose_pairs",
    summary="Choose the pairs worth matching from the images' rough poses",
    openapi_extra=body_schema("PairsRequest"),
)
async def choose_pairs(request: Request) -> Response:
    """Each image's footprint on the ground from its camera and rough pose; the pairs whose
    footprints overlap by more than ``params.min_overlap`` of the smaller one (the paper's
    half), each image capped at its ``params.max_per_image`` largest overlaps and keeping at
    least its ``params.min_partners`` largest. Answered at once (200), no job."""
    query = await parse_body(request, parse_pairs)
    state = request.app.state
    if getattr(state, "pairs_limiter", None) is None:  # made in the server's event loop
        state.pairs_limiter = anyio.CapacityLimiter(CONCURRENT_CHOICES)
    try:
        chosen, ms = await anyio.to_thread.run_sync(_choose, query, limiter=state.pairs_limiter)
    except InputError as e:
        raise invalid_input(e) from None
    ground = (
        {"ground_z": query.ground_z}
        if query.ground_z is not None
        else {"flying_height": float(query.flying_height or 0.0)}
    )
    doc = {
        "images": len(query.images),
        "pairs": [{"image1": a, "image2": b, "overlap": o} for a, b, o in chosen.pairs],
        "params": dataclasses.asdict(query.params),
        "ground": ground,
        "timings_ms": {"total": ms},
    }
    log.info("pairs chosen: %d of %d images", len(chosen.pairs), len(query.images))
    return Response(orjson.dumps(doc), media_type="application/json")
