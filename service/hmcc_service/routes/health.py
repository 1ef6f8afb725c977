"""``/healthz`` (the process answers), ``/readyz`` (the queue can take and run jobs),
``/metrics`` (Prometheus text format). Not behind the API key: probes and scrapers."""

from __future__ import annotations

import anyio.to_thread
from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from hmcc import __version__

from .. import shutdown
from ..deps import QueueDep
from ..models import Health, Readiness

router = APIRouter(tags=["operations"])


@router.get("/healthz", response_model=Health, operation_id="healthz", summary="Process is up")
async def healthz() -> dict[str, str]:
    return {"status": "ok", "version": __version__}


@router.get(
    "/readyz",
    response_model=Readiness,
    responses={
        503: {
            "model": Readiness,
            "description": "Redis unreachable, no worker, or the service is shutting down",
        }
    },
    operation_id="readyz",
    summary="Queue backend reachable and workers present",
)
async def readyz(queue: QueueDep) -> JSONResponse:
    state = await queue.readiness()
    if shutdown.began():
        state["ready"] = False
    return JSONResponse(state, status_code=200 if state["ready"] else 503)


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format"}},
    operation_id="metrics",
    summary="Prometheus metrics",
)
async def metrics(request: Request) -> Response:
    registry = request.app.state.metrics.registry
    body = await anyio.to_thread.run_sync(generate_latest, registry)
    return Response(body, media_type=CONTENT_TYPE_LATEST)
