"""The RQ worker: warm, fork-free, and unable to run anything but our jobs.

* ``SimpleWorker`` runs jobs in its own process: numpy, SciPy and OpenCV are imported and
  warmed once at start, not per job (RQ's default worker forks a work horse per job).
* Job data is JSON (RQ's ``JSONSerializer``); nothing is unpickled.
* :class:`AllowlistedJob` refuses any function or callback outside
  :data:`hmcc_worker.jobs.JOB_FUNCTIONS` and ignores webhooks, so a Redis client cannot make a
  worker import or call something else.
* A job's "started" entry expires ``timeout + grace`` seconds after it starts (RQ's default
  adds 60 s). When a worker dies mid-job, the registry cleanup (run by every worker every
  few seconds and by the API when it reads a started job) retries the job once, then fails it.

Run N workers by starting ``hmcc worker`` N times (processes, containers or machines), all
with the same ``REDIS_URL``.
"""

from __future__ import annotations

import logging
import os
import socket
from typing import Any

from redis import Redis
from rq import Queue, SimpleWorker
from rq.job import Job
from rq.serializers import JSONSerializer

from .jobs import JOB_FUNCTIONS, warm_up

__all__ = ["AllowlistedJob", "HmccWorker", "UnsafeJobError", "make_worker", "warm_up"]

log = logging.getLogger("hmcc.worker")


class UnsafeJobError(RuntimeError):
    """A job in Redis names a callable this worker does not run."""


class AllowlistedJob(Job):
    @property
    def func(self) -> Any:
        name = self.func_name
        if self.instance is not None or name not in JOB_FUNCTIONS:
            raise UnsafeJobError(f"refusing to run {name!r}: not an hmcc job function")
        return JOB_FUNCTIONS[name]

    def _allowed(self, name: str | None) -> Any:
        if not name:
            return None
        if name not in JOB_FUNCTIONS:
            log.warning("ignoring callback %r: not an hmcc job function", name)
            return None
        return JOB_FUNCTIONS[name]

    @property
    def success_callback(self) -> Any:
        return self._allowed(self._success_callback_name)

    @property
    def failure_callback(self) -> Any:
        return self._allowed(self._failure_callback_name)

    @property
    def stopped_callback(self) -> Any:
        return self._allowed(self._stopped_callback_name)

    def restore(self, raw_data: Any) -> Any:
        out = super().restore(raw_data)
        self.webhooks = []
        return out

    def send_webhooks(self, *args: Any, **kwargs: Any) -> None:
        return None


class HmccWorker(SimpleWorker):
    """SimpleWorker whose started-job entries expire ``timeout + grace_s`` after the start."""

    grace_s = 10

    def get_heartbeat_ttl(self, job: Job, working_time: float = 0.0) -> int:
        timeout = job.timeout if job.timeout and job.timeout > 0 else self.worker_ttl
        return max(1, int(timeout - working_time)) + self.grace_s


def make_worker(
    redis_url: str,
    queue_name: str,
    *,
    job_timeout_s: int,
    grace_s: int,
    result_ttl_s: int,
    name: str | None = None,
) -> HmccWorker:
    # No socket timeout: the worker blocks in BLPOP for up to worker_ttl by design.
    connection = Redis.from_url(redis_url, socket_connect_timeout=2, socket_keepalive=True)
    queue = Queue(
        queue_name, connection=connection, serializer=JSONSerializer, job_class=AllowlistedJob
    )
    HmccWorker.grace_s = grace_s
    return HmccWorker(
        [queue],
        connection=connection,
        serializer=JSONSerializer,
        job_class=AllowlistedJob,
        name=name or f"hmcc-{socket.gethostname()}-{os.getpid()}",
        worker_ttl=max(job_timeout_s + grace_s, 30),
        maintenance_interval=max(1, min(grace_s, 10)),
        default_result_ttl=result_ttl_s,
    )
