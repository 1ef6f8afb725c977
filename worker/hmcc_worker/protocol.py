"""Every name the API and the workers share, in one place (as rq keeps its own in ``keys.py``):
Redis keys, the job functions RQ stores by name, job statuses and error codes."""

from __future__ import annotations

import enum

__all__ = [
    "BATCH_KEY",
    "IMAGES_KEY",
    "JOB_FUNCTION",
    "METRICS_KEY",
    "ON_FAILURE",
    "ON_SUCCESS",
    "OUTCOMES_KEY",
    "PAYLOAD_KEY",
    "TERMINAL",
    "WORKER_CHILDREN_FIELD",
    "WORKER_FRESH_S",
    "WORKER_OWNER_FIELD",
    "BatchStatus",
    "ErrorCode",
    "ItemStatus",
    "JobKind",
    "JobStatus",
]

# -- Redis keys (RQ's own keys are RQ's: rq:job:<id>, rq:queue:<name>, rq:results:<id>) ---------

#: A job's input: the binary payload of :mod:`hmcc_worker.payload`.
PAYLOAD_KEY = "hmcc:payload:{job_id}"
#: A batch's images, one hash field per image (stored once, read by each of its chunks).
IMAGES_KEY = "hmcc:images:{batch_id}"
#: A job's outcomes: a list, one JSON document per pair, written by the worker.
OUTCOMES_KEY = "hmcc:outcomes:{job_id}"
#: A batch's description: its chunks' job ids, pair ids, TTL.
BATCH_KEY = "hmcc:batch:{batch_id}"
#: The job metrics every worker adds to (:mod:`hmcc_worker.metrics`).
METRICS_KEY = "hmcc:metrics"

# -- workers ------------------------------------------------------------------------------------

#: A worker counts as present while its last heartbeat is younger than this (workers beat
#: every 2 s, idle or busy; a killed one stops at once). A registration older than this may be
#: taken over by a new worker of the same name.
WORKER_FRESH_S = 7.0
#: Fields hmcc adds to RQ's worker hash (``rq:worker:<name>``): the live compute children, as
#: of the worker's last heartbeat (``/readyz`` counts a worker with none as absent), and the
#: process that registered the name (a worker made anew by that process takes it over).
WORKER_CHILDREN_FIELD = "hmcc_children"
WORKER_OWNER_FIELD = "hmcc_owner"

# -- job functions, by the dotted name RQ stores --------------------------------------------------

JOB_FUNCTION = "hmcc_worker.jobs.verify_job"
ON_SUCCESS = "hmcc_worker.jobs.on_job_success"
ON_FAILURE = "hmcc_worker.jobs.on_job_failure"


class JobKind(enum.StrEnum):
    """A job verifies one pair (``POST /v1/verifications``) or a chunk of a batch."""

    pair = "pair"
    chunk = "chunk"


class JobStatus(enum.StrEnum):
    """A job's (and a batch item's) status, as the API answers it."""

    queued = "queued"
    started = "started"
    finished = "finished"
    failed = "failed"
    canceled = "canceled"


TERMINAL = frozenset({JobStatus.finished, JobStatus.failed, JobStatus.canceled})


class ItemStatus(enum.StrEnum):
    """A batch item's status, as the API answers it: its job's (:class:`JobStatus`), or
    ``expired`` when its result is no longer kept (it outlived its TTL or, in embedded mode,
    the memory bound): it finished or failed, which is not known any more."""

    queued = "queued"
    started = "started"
    finished = "finished"
    failed = "failed"
    canceled = "canceled"
    expired = "expired"


class BatchStatus(enum.StrEnum):
    """A batch's status, as the API answers it: ``finished`` once every pair is finished,
    failed or canceled, ``queued`` while none has started."""

    queued = "queued"
    running = "running"
    finished = "finished"


class ErrorCode(enum.StrEnum):
    """The ``error.code`` of a failed job or pair, and of the API's error answers."""

    # a pair or job that ran
    invalid_input = "invalid_input"  # input only the core could refuse (with issues)
    worker_crashed = "worker_crashed"  # the pair killed the process verifying it; not retried
    worker_lost = "worker_lost"  # the worker process vanished twice (retried once)
    timeout = "timeout"  # the job ran longer than HMCC_JOB_TIMEOUT_S
    payload_expired = "payload_expired"  # the input expired before a worker took it
    internal_error = "internal_error"  # a bug: logged, the message says nothing more
    # the API's own answers
    not_found = "not_found"
    not_cancelable = "not_cancelable"
    queue_full = "queue_full"
    queue_unavailable = "queue_unavailable"
    body_too_large = "body_too_large"
    unsupported_media_type = "unsupported_media_type"
    unauthorized = "unauthorized"
    bad_request = "bad_request"
    method_not_allowed = "method_not_allowed"
    uri_too_long = "uri_too_long"
    headers_too_large = "headers_too_large"
    server_busy = "server_busy"  # too many bodies being read at once (503, retry)
    request_timeout = "request_timeout"  # the body did not arrive in time (408)
    shutting_down = "shutting_down"  # the API is shutting down and takes no new work (503)
