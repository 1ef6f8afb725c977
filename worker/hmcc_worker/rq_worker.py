"""The RQ worker: warm, crash-proof, and unable to run anything but our jobs.

* ``SimpleWorker`` takes jobs in its own process, and hands them to one warm compute child
  (:class:`~hmcc_worker.pool.ComputePool`), which reads their input from Redis, verifies it
  and stores the outcomes: a pair that crashes native code kills the child, not the worker,
  and is reported ``worker_crashed`` instead of being retried onto the next worker (RQ's
  default worker forks a work horse per job; this one pays no fork).
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

* The worker's compute pool heals itself (:class:`~hmcc_worker.pool.ComputePool`); each
  heartbeat reports its live children, which ``/readyz`` reads. If the pool cannot be
  rebuilt, the worker takes no more jobs: it deregisters and :func:`run_worker` raises
  :class:`~hmcc_worker.pool.ComputePoolDead`, so that ``hmcc worker`` exits non-zero and its
  supervisor restarts it. (A job in hand then fails its attempt and is retried once, on
  another worker.)
* A worker named with ``--name`` takes over a registration of its name that its own process
  wrote (a worker made anew after Redis restarted on its data) or whose heartbeat is older
  than ``WORKER_FRESH_S`` (a worker gone); RQ alone refuses the name until the registration
  expires, about a minute later.
* Redis going away does not end the process: the worker is made anew with a back-off (at most
  5 s apart, one log line per change of state) for as long as it takes.
* SIGTERM/SIGINT: an idle worker stops at once, a busy one after its job; a second signal
  stops it at once (cold).

Run N workers by starting ``hmcc worker`` N times (processes, containers or machines), all
with the same ``REDIS_URL``.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
import uuid
from collections.abc import Callable
from types import FrameType
from typing import Any

from redis import Redis
from redis.exceptions import RedisError
from rq import Queue, SimpleWorker
from rq.executions import Execution
from rq.job import Job
from rq.serializers import JSONSerializer
from rq.worker import WorkerStatus

from .jobs import set_compute
from .pool import ComputePool, ComputePoolDead
from .protocol import WORKER_CHILDREN_FIELD, WORKER_FRESH_S, WORKER_OWNER_FIELD
from .rq_compat import AllowlistedJob, registration_is_stale

__all__ = ["HmccWorker", "make_worker", "run_worker"]

log = logging.getLogger("hmcc.worker")

#: This process, as the owner of the worker registrations it writes.
_OWNER = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex}"


class HmccWorker(SimpleWorker):
    """SimpleWorker with a per-job heartbeat thread and a stop flag of its own (see the module
    docstring)."""

    beat_s = 2
    grace_s = 10
    #: Set by SIGTERM/SIGINT (RQ only remembers a stop asked while busy).
    stopping = False
    #: The pool the jobs run on (set by :func:`run_worker`): its live children are reported.
    compute: ComputePool | None = None

    def request_stop(self, signum: int, frame: FrameType | None) -> None:
        self.stopping = True
        super().request_stop(signum, frame)

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
        """Also report the compute pool's live children, and re-register when the
        registration is gone (a Redis that restarted empty forgets its workers, and
        ``/readyz`` would report none while this one works on). One round trip (RQ's own
        heartbeat alone takes three; the worker beats every 2 s when idle, a few times a job)."""
        if pipeline is not None:
            super().heartbeat(timeout, pipeline)
            pipeline.hset(self.key, WORKER_CHILDREN_FIELD, self._children())
            return
        with self.connection.pipeline(transaction=False) as pipe:
            pipe.exists(self.key)
            super().heartbeat(timeout, pipe)
            pipe.hset(self.key, WORKER_CHILDREN_FIELD, self._children())
            registered = pipe.execute()[0]
        if not registered:
            self.log.warning(
                "worker %s: registration lost (Redis restarted?); re-registering", self.name
            )
            self.connection.delete(self.key)  # what this beat wrote of it: not a registration
            self.register_birth()
            self.heartbeat(timeout)

    def _children(self) -> int:
        return -1 if self.compute is None else len(self.compute.live_children())

    def serialize(self) -> dict[str, Any]:
        return {
            **super().serialize(),
            WORKER_OWNER_FIELD: _OWNER,
            WORKER_CHILDREN_FIELD: self._children(),
        }

    def register_birth(self) -> None:
        """Take over a stale registration of this worker's name (see the module docstring)
        rather than fail until it expires."""
        if registration_is_stale(
            self.connection,
            self.key,
            owner=_OWNER,
            owner_field=WORKER_OWNER_FIELD,
            fresh_s=WORKER_FRESH_S,
        ):
            self.log.warning("worker %s: taking over a stale registration of its name", self.name)
            self.connection.delete(self.key)
        super().register_birth()

    def dequeue_job_and_maintain_ttl(
        self, timeout: int | None, max_idle_time: int | None = None
    ) -> tuple[Job, Queue] | None:
        """No job for a dead compute pool: the worker ends (RQ's loop quits on the error)."""
        if self.compute is not None and self.compute.dead:
            raise ComputePoolDead("the compute pool cannot be rebuilt; taking no more jobs")
        return super().dequeue_job_and_maintain_ttl(timeout, max_idle_time)

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
    HmccWorker.beat_s = max(1, min(2, grace_s))
    return HmccWorker(
        [queue],
        connection=connection,
        serializer=JSONSerializer,
        job_class=AllowlistedJob,
        # A random suffix: a restarted container has the same host name and pid 1, and RQ
        # refuses a name whose registration has not expired yet.
        name=name or f"hmcc-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}",
        # 17 s: idle workers block 2 s in BLPOP between heartbeats (RQ waits ttl - 15), so
        # /readyz tells a killed worker from an idle one within a few seconds.
        worker_ttl=17,
        maintenance_interval=max(1, min(grace_s, 10)),
        default_result_ttl=result_ttl_s,
    )


class _Stop(Exception):
    """A stop signal arrived while no RQ worker was running (Redis away)."""


def run_worker(
    make: Callable[[], HmccWorker],
    compute: ComputePool,
    *,
    redis_url: str,
    burst: bool,
    logging_level: str,
) -> None:
    """Work until asked to stop (SIGINT/SIGTERM) or, with ``burst``, until the queue is empty;
    raises :class:`ComputePoolDead` when ``compute`` cannot be rebuilt (after the worker
    deregistered).

    RQ's worker quits on a Redis error (in its loop, its heartbeat, its maintenance), and
    making one needs Redis. So this loop makes a new worker whenever one ends without being
    asked to, backing off 0.5 s, 1 s, ... at most 5 s between attempts while Redis is away,
    and logs once per change (away, back). Jobs run on ``compute``, this process's child,
    which reads their input from ``redis_url`` itself."""
    set_compute(compute, redis_url)
    stop = threading.Event()

    def asked_to_stop(signum: int, frame: FrameType | None) -> None:
        stop.set()
        raise _Stop

    delay, away = 0.5, False
    while not stop.is_set():
        signal.signal(signal.SIGTERM, asked_to_stop)
        signal.signal(signal.SIGINT, asked_to_stop)
        worker: HmccWorker | None = None
        try:
            worker = make()
            worker.compute = compute
            if away:
                log.warning("Redis is reachable again; worker %s is working", worker.name)
            away, delay = False, 0.5
            worker.work(burst=burst, logging_level=logging_level, with_scheduler=False)
        except _Stop:
            break
        except (RedisError, OSError) as e:
            if not away:
                log.warning("Redis is unreachable (%s); trying again every few seconds", e)
            away = True
        except Exception:
            log.exception("the worker ended with an error; starting anew")
        if compute.dead:
            log.critical("the compute pool cannot be rebuilt; the worker stops")
            raise ComputePoolDead("the compute pool cannot be rebuilt")
        if burst or stop.is_set() or (worker is not None and worker.stopping):
            break
        if worker is not None and not away:
            log.warning("worker %s ended unexpectedly (Redis away?); starting anew", worker.name)
            away = True
        try:
            time.sleep(delay)
        except _Stop:
            break
        delay = min(2 * delay, 5.0)
