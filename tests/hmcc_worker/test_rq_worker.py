"""The RQ worker's guards, without a worker process: what a job read from Redis may call."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import redis
from rq import Callback, Queue
from rq.serializers import JSONSerializer

from hmcc_worker.jobs import verify_job
from hmcc_worker.rq_compat import AllowlistedJob, UnsafeJobError
from hmcc_worker.rq_worker import HmccWorker
from tests.support.procs import redis_server

pytestmark = pytest.mark.procs


@pytest.fixture(scope="module")
def queue() -> Iterator[Queue]:
    with redis_server() as server:
        conn = redis.Redis.from_url(server.url)
        yield Queue("t", connection=conn, serializer=JSONSerializer)


def _fetch(queue: Queue, job_id: str) -> AllowlistedJob:
    return AllowlistedJob.fetch(job_id, connection=queue.connection, serializer=JSONSerializer)


def test_our_function_resolves(queue: Queue) -> None:
    job = queue.enqueue("hmcc_worker.jobs.verify_job")
    assert _fetch(queue, job.id).func is verify_job


def test_any_other_function_is_refused(queue: Queue) -> None:
    job = queue.enqueue("os.system", "echo pwned")
    with pytest.raises(UnsafeJobError, match="os.system"):
        _ = _fetch(queue, job.id).func


def test_callbacks_outside_the_allow_list_are_dropped(queue: Queue) -> None:
    job = queue.enqueue(
        "hmcc_worker.jobs.verify_job",
        on_success=Callback("os.system"),
        on_failure=Callback("hmcc_worker.jobs.on_job_failure"),
    )
    fetched = _fetch(queue, job.id)
    assert fetched.success_callback is None
    assert fetched.failure_callback is not None
    assert fetched.webhooks == []


def test_a_running_job_is_vouched_for_until_its_deadline(queue: Queue) -> None:
    job = queue.enqueue("hmcc_worker.jobs.verify_job", job_timeout=30)
    worker = HmccWorker([queue], connection=queue.connection, serializer=JSONSerializer)
    worker.beat_s, worker.grace_s = 2, 3
    assert worker.get_heartbeat_ttl(job, working_time=0.0) == 5
    assert worker.get_heartbeat_ttl(job, working_time=32.0) == 5
    assert worker.get_heartbeat_ttl(job, working_time=34.0) == 1  # past timeout + grace
