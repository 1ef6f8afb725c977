"""The RQ worker: warm, fork-free, and unable to run anything but our jobs.

* ``SimpleWorker`` runs jobs in its own process: numpy, SciPy and OpenCV are imported and
  warmed once at start, not per job (RQ's default worker forks a work horse per job).
* Job data is JSON (RQ's ``JSONSerializer``); nothing is unpickled.
* :class:`AllowlistedJob` refuses any function or callback outside
  :data:`hmcc_worker.jobs.JOB_FUNCTIONS` and ignores webhooks, so a Redis client cannot make a
  worker import or call something else.
* While a job runs, a heartbeat thread renews its "started" entry every ``beat_s`` seconds for
  ``beat_s + grace_s`` (RQ's SimpleWorker sets it once, for the job timeout + 60 s). So when
  a worker dies mid-job, its job is noticed within ``beat_s + grace_s`` seconds by the registry
  cleanup (run by every worker every few seconds and by the API when it reads a started job),
  which retries the job once and then fails it with a reason. The heartbeat stops renewing at
  the job timeout + grace, so a job stuck in native code cannot stay "started" forever.

Run N workers by starting ``hmcc worker`` N times (processes, containers or machines), all
with the same ``REDIS_URL``.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any

from redis import Redis
from rq import Queue, SimpleWorker
from rq.executions import Execution
from rq.job import Job
from rq.serializers import JSONSerializer
from rq.worker import WorkerStatus

from .jobs import JOB_FUNCTIONS, warm_up

__all__ = [
    "AllowlistedJob", "HmccWorker", "UnsafeJobError", "make_worker", "run_worker", "warm_up"
]

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
    """SimpleWorker with a per-job heartbeat thread (see the module docstring)."""

    beat_s = 2
    grace_s = 10

    def get_heartbeat_ttl(self, job: Job, working_time: float = 0.0) -> int:
        timeout = job.timeout if job.timeout and job.timeout > 0 else self.worker_ttl
        if working_time > timeout + self.grace_s:
            return 1  # past its deadline: stop vouching for it
        return self.beat_s + self.grace_s

    def execute_job(self, job: Job, queue: Queue) -> None:
        execution = self.prepare_execution(job)
        stop = threading.Event()
        beat = threading.Thread(
            target=self._beat, args=(job, execution, stop), name="hmcc-heartbeat", daemon=True
        )
        beat.start()
        try:
            self.perform_job(job, queue, execution)
        finally:
            stop.set()
            beat.join()
        self.set_state(WorkerStatus.IDLE)

    def heartbeat(self, timeout: int | None = None, pipeline: Any = None) -> None:
        """Also re-register when the registration is gone: a Redis that restarted empty
        forgets its workers, and ``/readyz`` would report none while this one works on."""
        if pipeline is None and not self.connection.exists(self.key):
            self.log.warning("worker %s: registration lost (Redis restarted?); re-registering",
                             self.name)
            self.register_birth()
        super().heartbeat(timeout, pipeline)

    def _beat(self, job: Job, execution: Execution, stop: threading.Event) -> None:
        while not stop.wait(self.beat_s):
            try:
                self.maintain_heartbeats(job, execution)
            except Exception:  # a missed beat is retried; the job goes on
                log.warning("heartbeat failed", exc_info=True)


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
    HmccWorker.beat_s = max(1, min(5, grace_s))
    return HmccWorker(
        [queue],
        connection=connection,
        serializer=JSONSerializer,
        job_class=AllowlistedJob,
        # A random suffix: a restarted container has the same host name and pid 1, and RQ
        # refuses a name whose registration has not expired yet.
        name=name or f"hmcc-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}",
        # 20 s: idle workers block 5 s in BLPOP between heartbeats (RQ waits ttl - 15).
        worker_ttl=20,
        maintenance_interval=max(1, min(grace_s, 10)),
        default_result_ttl=result_ttl_s,
    )


def run_worker(make: Callable[[], HmccWorker], *, burst: bool, logging_level: str) -> None:
    """Work until asked to stop (SIGINT/SIGTERM) or, with ``burst``, until the queue is empty.

    RQ's worker quits on a Redis error outside its dequeue loop (a heartbeat, the registry
    maintenance); a worker that quits while Redis is away would leave the service with none
    when Redis returns. So a worker that ends without being asked to is replaced by a new
    one (new name) after a second."""
    while True:
        worker = make()
        try:
            worker.work(burst=burst, logging_level=logging_level, with_scheduler=False)
        except Exception:
            log.warning("worker %s ended with an error", worker.name, exc_info=True)
        if burst or worker._stop_requested:
            return
        log.warning("worker %s ended unexpectedly (Redis away?); starting anew in 1 s",
                    worker.name)
        time.sleep(1.0)
