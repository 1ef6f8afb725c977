"""The FastAPI application: ``create_app(settings)``.

Request path: [CORS, only when configured] -> HttpMetrics -> BodySizeLimit (413) -> V1Gate
(401, 415; then the body under deadlines, 408, and the body budget, 503) -> routes -> queue
(embedded child processes, or RQ). The queue is built here, not in the lifespan, so the app
also works under ``httpx.ASGITransport`` (which runs no lifespan; the embedded pool then starts
with the first job); the lifespan starts the embedded pool warm, makes its jobs what a shutdown
waits for (:mod:`hmcc_service.shutdown`), and closes the queue.
"""

from __future__ import annotations

import gc
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import anyio.to_thread
from fastapi import FastAPI, Request
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles
from pydantic.json_schema import models_json_schema

from hmcc import __version__
from hmcc_schema import BatchRequest, PairRequest, PairsRequest
from hmcc_worker.logs import configure_logging

from . import shutdown
from .embedded import EmbeddedQueue
from .errors import install_error_handlers
from .limits import BodySizeLimit, V1Gate
from .metrics import HttpMetrics, Metrics
from .queue import JobQueue
from .routes import batches, health, limits, pairs, verifications
from .settings import Settings, get_settings

__all__ = ["create_app"]

log = logging.getLogger("hmcc.api")

DESCRIPTION = """Geometric verification of UAV feature matches with rough POS (HMCC-RANSAC).

POST a pair (keypoints, candidate matches, each image's camera and rough pose) and read back
the inlier indices, the fitted model, per-stage timings and statistics. Jobs run on a queue:
in-process by default, RQ workers on Redis when the service has `REDIS_URL`.
"""


def make_queue(settings: Settings) -> JobQueue:
    if settings.redis_url:
        from .rq_queue import RQQueue

        return RQQueue(settings)
    return EmbeddedQueue(settings)


def create_app(settings: Settings | None = None, *, freeze: bool = False) -> FastAPI:
    """The API. ``freeze``: what the process holds once started is left out of the garbage
    collector's work from then on (:func:`gc.freeze`; for the process that serves the app,
    ``hmcc serve``, not one that makes many apps)."""
    settings = settings or get_settings()
    queue = make_queue(settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if isinstance(queue, EmbeddedQueue):
            await anyio.to_thread.run_sync(queue.start)
            shutdown.track(queue.pending)
        if freeze:
            # The modules, models and routes (some 10^5 objects that live as long as the
            # process) were walked again by each full collection that a batch's body set off:
            # 0.27 of the API's 1.55 CPU s on the 18 283-pair benchmark flight.
            gc.collect()
            gc.freeze()
            # A batch's parse makes some 10^5 objects that live until its jobs end (a pair's
            # dict, arrays and FlightPair): with the default first threshold (700), each body
            # set off hundreds of young and several full collections, which walked the batches
            # still held: 0.19-0.27 s of the API's 1.1 CPU s on the benchmark flight against
            # 0.12-0.17 s with 20 000 (three interleaved runs each; the young collections grow
            # as the full ones go).
            gc.set_threshold(20_000, 20, 10)
        log.info("hmcc-match %s serving with the %s queue", __version__, queue.mode)
        try:
            yield
        finally:
            if isinstance(queue, EmbeddedQueue):
                shutdown.untrack(queue.pending)
            await queue.close()

    app = FastAPI(
        title="hmcc-match",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,  # served from the package's own files: see _serve_docs
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.queue = queue
    app.state.metrics = Metrics(queue)
    install_error_handlers(app)
    app.include_router(verifications.router)
    app.include_router(batches.router)
    app.include_router(pairs.router)
    app.include_router(limits.router)
    app.include_router(health.router)
    _serve_docs(app)
    # Outermost last: CORS wraps everything, so a 401/413 is readable cross-origin too.
    app.add_middleware(V1Gate, settings=settings)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(HttpMetrics, metrics=app.state.metrics)
    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=["Content-Type", "X-API-Key"],
        )
    app.openapi = lambda: _openapi(app, settings)  # type: ignore[method-assign]
    return app


#: Where ``/docs`` and ``/redoc`` load their scripts, styles and icon from: the files of
#: Swagger UI and ReDoc that the fastapi-offline package ships, so the pages work offline.
DOCS_ASSETS = "/docs/assets"


def _serve_docs(app: FastAPI) -> None:
    """``/docs`` (Swagger UI) and ``/redoc`` (ReDoc) from this service's own files, not a CDN:
    FastAPI's pages, their assets mounted at :data:`DOCS_ASSETS` (no Google fonts either)."""
    app.mount(
        DOCS_ASSETS, StaticFiles(packages=[("fastapi_offline", "static")]), name="docs-assets"
    )
    openapi_url = app.openapi_url or "/openapi.json"

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "").rstrip("/")
        return get_swagger_ui_html(
            openapi_url=root + openapi_url,
            title=f"{app.title} - Swagger UI",
            swagger_js_url=f"{root}{DOCS_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{root}{DOCS_ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{root}{DOCS_ASSETS}/favicon.png",
            swagger_ui_parameters=app.swagger_ui_parameters,
        )

    @app.get("/redoc", include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "").rstrip("/")
        return get_redoc_html(
            openapi_url=root + openapi_url,
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{root}{DOCS_ASSETS}/redoc.standalone.js",
            redoc_favicon_url=f"{root}{DOCS_ASSETS}/favicon.png",
            with_google_fonts=False,
        )


def _openapi(app: FastAPI, settings: Settings) -> dict[str, Any]:
    """FastAPI's document plus the request body schemas the routes parse themselves (the
    batch's pair limit is the service's setting)."""
    if app.openapi_schema:
        return app.openapi_schema
    from fastapi.openapi.utils import get_openapi

    doc = get_openapi(
        title=app.title, version=app.version, description=app.description, routes=app.routes
    )
    _, defs = models_json_schema(
        [(PairRequest, "validation"), (BatchRequest, "validation"), (PairsRequest, "validation")],
        ref_template="#/components/schemas/{model}",
    )
    schemas = doc.setdefault("components", {}).setdefault("schemas", {})
    for name, schema in defs.get("$defs", {}).items():
        schemas.setdefault(name, schema)
    schemas["BatchRequest"]["properties"]["pairs"]["maxItems"] = settings.max_batch_pairs
    app.openapi_schema = doc
    return doc


def app_from_env() -> FastAPI:
    """The uvicorn factory of ``hmcc serve`` (``uvicorn --factory``): settings from the
    environment, JSON logs."""
    settings = get_settings()
    configure_logging(settings.log_level)
    return create_app(settings, freeze=True)
