"""The API process's shutdown as the app sees it: whether it began, and the work it waits for.

:class:`hmcc_service.server.Server` calls :func:`begin` on the first SIGTERM (or SIGINT), at
once, from the signal handler; from then on the embedded queue refuses new jobs (503
``shutting_down``) and ``/readyz`` answers 503, while the server keeps answering reads until
:func:`pending` is 0 (the jobs accepted before have ended) or ``HMCC_SHUTDOWN_DRAIN_S`` has
passed. One process serves one app, so the state is the process's.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

__all__ = ["begin", "began", "pending", "track", "untrack"]

_began = threading.Event()
_trackers: list[Callable[[], int]] = []


def begin() -> None:
    """Shutdown began: take no new work from now on."""
    _began.set()


def began() -> bool:
    return _began.is_set()


def track(count: Callable[[], int]) -> None:
    """Make ``count`` (jobs accepted and not ended) part of what shutdown waits for."""
    _trackers.append(count)


def untrack(count: Callable[[], int]) -> None:
    if count in _trackers:
        _trackers.remove(count)


def pending() -> int:
    """Jobs accepted by this process and not ended, across what is tracked."""
    return sum(count() for count in list(_trackers))
