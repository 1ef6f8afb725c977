"""How ``hmcc serve`` runs uvicorn: our HTTP protocol (:mod:`hmcc_service.http_protocol`) and a
shutdown that neither loses accepted work nor waits on stalled clients.

On the first SIGTERM (or SIGINT) :class:`Server` calls :func:`hmcc_service.shutdown.begin` at
once: from then on no job is accepted (503 ``shutting_down`` + Retry-After) and ``/readyz``
answers 503, so nothing gets a 202 the process will not run. The server keeps listening and
answering reads until the jobs it accepted before have ended (a client can still read its
result), at most ``HMCC_SHUTDOWN_DRAIN_S``; with none running that is the next tick (0.1 s).
Uploads that stall meanwhile are answered 503 at once (:mod:`hmcc_service.limits`). Then
uvicorn's own shutdown: the listener closes, idle connections close, and requests still open
(a long poll) get ``HMCC_SHUTDOWN_TIMEOUT_S`` to end before they are cancelled. A
second signal ends the drain at once. ``--workers`` > 1 (RQ only, jobs live in Redis) runs
uvicorn's own supervisor, with the same shutdown timeout and no drain.
"""

from __future__ import annotations

import logging
import time
from types import FrameType
from typing import Any

import uvicorn

from . import shutdown
from .http_protocol import MAX_HEAD_BYTES, HttpProtocol
from .settings import Settings

__all__ = ["Server", "serve"]

log = logging.getLogger("hmcc.api")

#: uvicorn's exit status when the server did not start.
_STARTUP_FAILURE = 3


class Server(uvicorn.Server):
    """uvicorn's server with the drain of the module docstring."""

    def __init__(self, config: uvicorn.Config, drain_s: float) -> None:
        super().__init__(config)
        self.drain_s = drain_s
        self._drain_until: float | None = None

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        if self._drain_until is None and not self.should_exit:
            shutdown.begin()
            self._drain_until = time.monotonic() + self.drain_s
            return
        super().handle_exit(sig, frame)

    async def on_tick(self, counter: int) -> bool:
        if self._drain_until is not None and not self.should_exit:
            left = shutdown.pending()
            if left == 0:
                self.should_exit = True
            elif time.monotonic() >= self._drain_until:
                log.warning("shutting down with %d accepted job(s) not ended", left)
                self.should_exit = True
        return await super().on_tick(counter)


def serve(settings: Settings, workers: int = 1) -> int:
    """Run the API as ``hmcc serve`` does, until it is signalled; the exit status."""
    options: dict[str, Any] = {
        "factory": True,
        "host": settings.host,
        "port": settings.port,
        "workers": workers,
        "log_config": None,
        "access_log": False,
        "http": HttpProtocol,
        "h11_max_incomplete_event_size": MAX_HEAD_BYTES,
        "timeout_graceful_shutdown": settings.shutdown_timeout_s,
    }
    app = "hmcc_service.app:app_from_env"
    if workers > 1:
        uvicorn.run(app, **options)
        return 0
    server = Server(uvicorn.Config(app, **options), settings.shutdown_drain_s)
    server.run()
    return 0 if server.started else _STARTUP_FAILURE
