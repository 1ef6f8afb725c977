"""The RQ queue's bookkeeping, against a real redis-server and ``hmcc serve`` with no worker (so
jobs stay queued): the depth cap holds under concurrent submitters, and a cancelled job ends
(``finished_at``) and leaves no input behind in Redis."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import httpx
import pytest
import redis
from rq import Queue

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_worker.protocol import IMAGES_KEY, PAYLOAD_KEY
from tests.support.procs import (
    RedisServer,
    redis_server,
    running,
    service_env,
    start_api,
    start_worker,
)

pytestmark = pytest.mark.procs

DEPTH = 20


@pytest.fixture(scope="module")
def redis_srv() -> Iterator[RedisServer]:
    with redis_server() as server:
        yield server


@pytest.fixture(scope="module")
def url(redis_srv: RedisServer) -> Iterator[str]:
    env = service_env(REDIS_URL=redis_srv.url, HMCC_MAX_QUEUE_DEPTH=str(DEPTH))
    api, base = start_api(env)
    try:
        yield base
    finally:
        api.stop()


@pytest.fixture
def conn(redis_srv: RedisServer, url: str) -> Iterator[redis.Redis]:
    """A client of the API's Redis; the database is emptied after each test."""
    client = redis.Redis.from_url(redis_srv.url)
    try:
        yield client
    finally:
        client.flushdb()
        client.close()


@pytest.fixture(scope="module")
def pair() -> dict[str, Any]:
    pair = simulate_pair(SimulationOptions(n_inliers=40), seed=1)
    pair.pop("ground_truth")
    return pair


def test_concurrent_submitters_cannot_overshoot_the_depth_cap(
    url: str, conn: redis.Redis, pair: dict[str, Any]
) -> None:
    """16 submitters post 4 pairs each, at once, at a queue capped at 20 jobs with no worker:
    20 are accepted, every other one is 429, and the queue holds exactly the accepted ones."""

    def submit_four(_: int) -> list[int]:
        with httpx.Client(timeout=60) as client:
            return [client.post(f"{url}/v1/verifications", json=pair).status_code for _ in range(4)]

    with ThreadPoolExecutor(16) as pool:
        statuses = [s for four in pool.map(submit_four, range(16)) for s in four]
    assert sorted(set(statuses)) == [202, 429], statuses
    assert statuses.count(202) == DEPTH
    assert Queue("hmcc", connection=conn).count == DEPTH


def test_cancelling_a_queued_job_ends_it_and_deletes_its_input(
    url: str, conn: redis.Redis, pair: dict[str, Any]
) -> None:
    r = httpx.post(f"{url}/v1/verifications", json=pair)
    assert r.status_code == 202, r.text
    job = r.json()
    payload = PAYLOAD_KEY.format(job_id=job["job_id"])
    assert conn.exists(payload)
    assert job["finished_at"] is None

    cancelled = httpx.delete(f"{url}/v1/verifications/{job['job_id']}")
    assert cancelled.status_code == 200, cancelled.text
    body = cancelled.json()
    assert body["status"] == "canceled"
    assert body["finished_at"] is not None and body["finished_at"] >= body["submitted_at"]
    assert not conn.exists(payload), "the cancelled job's input is still in Redis"
    again = httpx.get(f"{url}/v1/verifications/{job['job_id']}").json()
    assert (again["status"], again["finished_at"]) == ("canceled", body["finished_at"])
    assert Queue("hmcc", connection=conn).count == 0


def test_a_finished_batch_leaves_no_images_behind(
    redis_srv: RedisServer, url: str, conn: redis.Redis
) -> None:
    """The images a batch's jobs share are deleted once every job has ended (read by the
    API's batch view), not kept for the batch's TTL."""
    from tests.support.flights import small_flight

    flight = small_flight(4)
    flight.pop("truth")
    r = httpx.post(f"{url}/v1/batches", json=flight, timeout=30)
    assert r.status_code == 202, r.text
    batch_id = r.json()["batch_id"]
    key = IMAGES_KEY.format(batch_id=batch_id)
    assert conn.exists(key), "stored once for the batch's jobs"
    worker = start_worker(service_env(REDIS_URL=redis_srv.url))
    with running(worker):
        view = httpx.get(f"{url}/v1/batches/{batch_id}?wait=30", timeout=40).json()
        while view["status"] != "finished":
            view = httpx.get(f"{url}/v1/batches/{batch_id}?wait=30", timeout=40).json()
    assert view["finished"] == 4, view
    assert not conn.exists(key)
