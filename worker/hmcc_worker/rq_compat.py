"""Everything hmcc uses of RQ beyond queues and workers, in one place: RQ's key names and how
it writes a job's times, its exception types, the current job, the registry cleanup, a
worker's registration. The
project pins ``rq>=3,<4``; a new major version of RQ is checked here first."""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from typing import Any

from rq import Queue, get_current_job
from rq.exceptions import AbandonedJobError
from rq.job import Job
from rq.registry import StartedJobRegistry
from rq.results import Result
from rq.timeouts import JobTimeoutException, TimerDeathPenalty
from rq.utils import str_to_date

__all__ = [
    "JOB_RECORD_FIELDS",
    "AbandonedJobError",
    "AllowlistedJob",
    "UnsafeJobError",
    "JobTimeoutException",
    "cleanup_abandoned",
    "current_job",
    "job_key",
    "record_time",
    "registration_is_stale",
    "results_stream_key",
]


log = logging.getLogger("hmcc.worker")

#: The fields of RQ's job hash (:func:`job_key`) a job's record is read from, in this order
#: (one ``HMGET``): RQ's status, its ``created_at``, ``started_at`` and ``ended_at``, the meta.
JOB_RECORD_FIELDS = ("status", "created_at", "started_at", "ended_at", "meta")


#: The length of a time as RQ writes it (``rq.utils.utcformat``: ``2026-11-26T16:00:01.250000Z``).
_RQ_TIME_CHARS = 27


def record_time(value: bytes | str | None) -> datetime | None:
    """A time of a job's record (``created_at``, ``started_at``, ``ended_at`` of
    :data:`JOB_RECORD_FIELDS`, as RQ writes them), or None when it is not set.

    RQ's own form is read by ``datetime.fromisoformat`` (well under a microsecond) rather than
    RQ's ``strptime`` (about 20 us): every poll of a batch reads three times of each of its
    jobs. Any other form goes through RQ's parser, as before."""
    if not value:
        return None
    text = value.decode() if isinstance(value, bytes) else value
    if len(text) == _RQ_TIME_CHARS and text[10] == "T" and text[-1] == "Z":
        return datetime.fromisoformat(text)
    return str_to_date(text)


class UnsafeJobError(RuntimeError):
    """A job in Redis names a callable this worker does not run."""


class AllowlistedJob(Job):
    """A job that can only run :data:`hmcc_worker.jobs.JOB_FUNCTIONS` (a Redis client cannot
    make a worker import or call anything else) and sends no webhooks."""

    @property
    def func(self) -> Any:
        from .jobs import JOB_FUNCTIONS

        name = self.func_name
        if self.instance is not None or name not in JOB_FUNCTIONS:
            raise UnsafeJobError(f"refusing to run {name!r}: not an hmcc job function")
        return JOB_FUNCTIONS[name]

    def _allowed(self, name: str | None) -> Any:
        from .jobs import JOB_FUNCTIONS

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


def current_job() -> Job:
    """The job this RQ worker is running (an error outside a job)."""
    job = get_current_job()
    if job is None:
        raise RuntimeError("an RQ job function called outside an RQ worker")
    return job


def job_key(job_id: str) -> str:
    """The hash RQ keeps a job in (``rq:job:<id>``)."""
    return str(Job.key_for(job_id))


def results_stream_key(job_id: str) -> str:
    """The stream RQ appends a job's results to (``rq:results:<id>``); blocking on it wakes a
    waiting request as soon as the job ends."""
    return str(Result.get_key(job_id))


def cleanup_abandoned(queue: Queue) -> None:
    """Retry (once) or fail the started jobs whose worker stopped renewing them. A thread can
    run it: the death penalty is a timer, not SIGALRM."""
    StartedJobRegistry(queue=queue, death_penalty_class=TimerDeathPenalty).cleanup()


def registration_is_stale(
    connection: Any, key: str, *, owner: str, owner_field: str, fresh_s: float
) -> bool:
    """Whether the worker registration at ``key`` (RQ's worker hash, which RQ refuses to
    replace while it exists without a ``death`` field, up to ``worker_ttl`` + 60 s after its
    last heartbeat) can be taken over: ``owner`` wrote it (this process, whose earlier worker
    ended, e.g. on a Redis restart that kept its data), or its ``last_heartbeat`` is older than
    ``fresh_s`` (its worker is gone)."""
    exists = connection.exists(key)
    death, beat, who = connection.hmget(key, "death", "last_heartbeat", owner_field)
    if not exists or death is not None:
        return False  # RQ registers over it anyway
    if who is not None and who.decode() == owner:
        return True
    last = str_to_date(beat) if beat else None
    return last is None or (datetime.now(UTC) - last).total_seconds() > fresh_s
