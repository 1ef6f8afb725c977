"""Faults with real parts: a private redis-server, ``hmcc serve`` and ``hmcc worker``
processes, HTTP on loopback. Workers are SIGKILLed mid-job, Redis is killed and restarted,
and jobs that are not ours are injected straight into Redis."""

from __future__ import annotations

import json
import os
import pickle
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import redis
from rq import Queue, Worker
from rq.job import Job
from rq.serializers import JSONSerializer

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_worker.outcomes import FAULT_SLOW_PAIR_ID, FAULT_SLOW_S
from tests.support.procs import (
    Proc,
    RedisServer,
    redis_server,
    running,
    service_env,
    start_api,
    start_worker,
    wait_until,
)

pytestmark = pytest.mark.procs

QUEUE = "hmcc"


def _pair(n_inliers: int = 150, outlier_ratio: float = 0.5, seed: int = 1) -> dict[str, Any]:
    pair = simulate_pair(SimulationOptions(n_inliers=n_inliers, outlier_ratio=outlier_ratio), seed)
    pair.pop("ground_truth")
    return pair


def _slow_pair() -> dict[str, Any]:
    """A pair of 4000 matches; under ``slow_env`` every pair first sleeps 3 s, so a worker is
    busy with it for that long however fast the machine (plain RANSAC's own 1-2 s on 95 %
    outliers alone could race the tests' signals, which follow "started" within a poll)."""
    pair = _pair(n_inliers=200, outlier_ratio=0.95, seed=3)
    pair["method"] = "ransac"
    pair["params"] = {"ransac": {"max_iters": 100_000, "confidence": 0.999999}}
    return pair


@pytest.fixture
def redis_srv() -> Iterator[RedisServer]:
    with redis_server() as server:
        yield server


@pytest.fixture
def env(redis_srv: RedisServer) -> dict[str, str]:
    # grace 1 s: a dead worker's job is noticed within ~2 s.
    return service_env(REDIS_URL=redis_srv.url, HMCC_WORKER_GRACE_S="1")


@pytest.fixture
def slow_env(env: dict[str, str]) -> dict[str, str]:
    return {**env, FAULT_SLOW_PAIR_ID: "*", FAULT_SLOW_S: "3"}


def _status(url: str, job_id: str) -> str:
    return str(httpx.get(f"{url}/v1/verifications/{job_id}").json()["status"])


def _submit(url: str, pair: dict[str, Any]) -> str:
    r = httpx.post(f"{url}/v1/verifications", json=pair)
    assert r.status_code == 202, r.text
    return str(r.json()["job_id"])


def _logs(*procs: Proc) -> str:
    return "\n".join(f"--- {p.log_path.name}\n{p.log()[-3000:]}" for p in procs)


def test_a_job_whose_worker_is_killed_is_retried_on_another_worker(
    slow_env: dict[str, str],
) -> None:
    api, url = start_api(slow_env)
    first = start_worker(slow_env, "first")
    with running(api, first):
        assert wait_until(lambda: httpx.get(f"{url}/readyz").json()["workers"] == 1, 30)
        job_id = _submit(url, _slow_pair())
        assert wait_until(lambda: _status(url, job_id) == "started", 30), _logs(api, first)
        first.kill()  # SIGKILL: no cleanup, no goodbye

        second = start_worker(slow_env, "second")
        with running(second):
            r = httpx.get(f"{url}/v1/verifications/{job_id}?wait=60", timeout=70)
            body = r.json()
            assert body["status"] == "finished", _logs(api, second) + json.dumps(body)[:500]
            assert body["result"]["statistics"]["matches"] == 4000

        metrics = httpx.get(f"{url}/metrics").text
        assert 'hmcc_job_failures_total{reason="AbandonedJobError"} 1.0' in metrics, metrics


def test_a_job_whose_worker_dies_twice_is_failed_with_a_reason(slow_env: dict[str, str]) -> None:
    api, url = start_api(slow_env)
    with running(api):
        job_id = _submit(url, _slow_pair())
        for attempt in ("first", "second"):
            worker = start_worker(slow_env, attempt)
            assert wait_until(lambda: _status(url, job_id) == "started", 30), _logs(api, worker)
            worker.kill()
            if attempt == "first":
                assert wait_until(lambda: _status(url, job_id) == "queued", 15), _logs(api)

        r = httpx.get(f"{url}/v1/verifications/{job_id}?wait=20", timeout=30)
        body = r.json()
        assert body["status"] == "failed", body
        assert body["error"]["code"] == "worker_lost"
        assert "retried once" in body["error"]["message"]
        assert body["result"] is None
        # It ended, though no worker saw it end: the failure's time is its end.
        assert body["finished_at"] is not None, body
        assert body["submitted_at"] <= body["started_at"] <= body["finished_at"]
        assert body["timings_ms"]["turnaround"] is not None


def test_redis_down_then_back(env: dict[str, str], redis_srv: RedisServer) -> None:
    api, url = start_api(env)
    worker = start_worker(env)
    with running(api, worker):
        assert wait_until(lambda: httpx.get(f"{url}/readyz").status_code == 200, 30)
        done = httpx.post(f"{url}/v1/verifications?wait=30", json=_pair(), timeout=40).json()
        assert done["status"] == "finished"

        redis_srv.stop()
        ready = httpx.get(f"{url}/readyz", timeout=10)
        assert ready.status_code == 503
        assert ready.json()["redis"] == "unreachable"
        t0 = time.monotonic()
        r = httpx.post(f"{url}/v1/verifications", json=_pair(), timeout=10)
        assert r.status_code == 503, r.text
        assert time.monotonic() - t0 < 3, "a down Redis must be answered at once"
        assert r.json()["error"]["code"] == "queue_unavailable"
        assert int(r.headers["Retry-After"]) > 0
        assert httpx.get(f"{url}/v1/verifications/{done['job_id']}").status_code == 503
        assert httpx.get(f"{url}/healthz").status_code == 200  # the process itself is fine

        redis_srv.start()  # same port, empty (no persistence)
        assert wait_until(lambda: httpx.get(f"{url}/readyz").status_code == 200, 60), _logs(
            api, worker
        )
        again = httpx.post(f"{url}/v1/verifications?wait=30", json=_pair(), timeout=40)
        assert again.json().get("status") == "finished", again.text + _logs(api, worker)


def test_a_worker_runs_nothing_but_our_jobs(
    env: dict[str, str], redis_srv: RedisServer, tmp_path: Path
) -> None:
    """Jobs written straight into Redis: a JSON job naming another function, and a pickled
    job whose unpickling would run a command. Neither runs; both end failed; the worker
    lives on and still verifies pairs."""
    conn = redis.Redis.from_url(redis_srv.url)
    marker_json = tmp_path / "json-job-ran"
    marker_pickle = tmp_path / "pickle-job-ran"

    json_queue = Queue(QUEUE, connection=conn, serializer=JSONSerializer)
    json_job = json_queue.enqueue("os.system", f"touch {marker_json}")

    class Exploit:
        def __reduce__(self) -> tuple[Any, tuple[str]]:
            return (os.system, (f"touch {marker_pickle}",))

    pickle_queue = Queue(QUEUE, connection=conn)  # RQ's default: pickle
    pickle_job = pickle_queue.enqueue("hmcc_worker.jobs.verify_pair_job", Exploit())
    assert pickle.loads(pickle.dumps("sanity")) == "sanity"

    api, url = start_api(env)
    worker = start_worker(env)
    with running(api, worker):

        def ended(job_id: str) -> bool:
            job = Job.fetch(job_id, connection=conn, serializer=JSONSerializer)
            return job.get_status() in ("failed", "finished")

        assert wait_until(lambda: ended(json_job.id) and ended(pickle_job.id), 30), _logs(worker)
        for job_id in (json_job.id, pickle_job.id):
            assert Job.fetch(job_id, connection=conn, serializer=JSONSerializer).get_status() == (
                "failed"
            )
        assert not marker_json.exists()
        assert not marker_pickle.exists()
        ok = httpx.post(f"{url}/v1/verifications?wait=30", json=_pair(), timeout=40).json()
        assert ok["status"] == "finished"


def _ransac_batch(n_pairs: int) -> dict[str, Any]:
    """``n_pairs`` pairs between two images, each some 25 ms of plain RANSAC (400 matches,
    90 % outliers, 6000 iterations of the seven-point RANSAC): a batch that keeps two workers
    busy for seconds."""
    sims = [_pair(n_inliers=40, outlier_ratio=0.9, seed=20 + k) for k in range(5)]
    return {
        "images": {"A": sims[0]["image1"], "B": sims[0]["image2"]},
        "plane": sims[0]["plane"],
        "method": "ransac",
        "params": {"ransac": {"max_iters": 6000, "confidence": 0.999999}},
        "pairs": [
            {
                "id": f"p{k}",
                "image1": "A",
                "image2": "B",
                **{f: sims[k % 5][f] for f in ("keypoints1", "keypoints2", "matches")},
            }
            for k in range(n_pairs)
        ],
    }


def test_a_redis_outage_mid_batch_loses_no_accepted_pair() -> None:
    """Redis (AOF, fsync every second, as docker-compose.yml runs it) is SIGKILLed mid-batch,
    stays away 10 s (past WORKER_FRESH_S, 7 s, and past the 7.5 s after which the workers'
    reconnection back-off waits its longest, 5 s), and comes back on the same data directory.
    Every pair of the batch, accepted well over a second before the kill, ends (finished, or
    failed with a reason); the batch stays readable; the same two worker processes reconnect
    and finish it."""
    with redis_server(aof=True) as srv:
        env = service_env(REDIS_URL=srv.url, HMCC_WORKER_GRACE_S="1", HMCC_BATCH_CHUNK_PAIRS="4")
        api, url = start_api(env)
        workers = [start_worker(env, "a"), start_worker(env, "b")]
        with running(api, *workers):
            assert wait_until(lambda: httpx.get(f"{url}/readyz").json()["workers"] == 2, 60), _logs(
                api, *workers
            )
            r = httpx.post(f"{url}/v1/batches", json=_ransac_batch(300), timeout=30)
            assert r.status_code == 202, r.text
            accepted = time.monotonic()
            location = f"{url}{r.headers['Location']}"

            def progress() -> dict[str, Any]:
                return dict(httpx.get(f"{location}?limit=0", timeout=10).json())

            # Mid-batch: some pairs ended, the batch was accepted more than a second ago.
            assert wait_until(
                lambda: progress()["finished"] > 0 and time.monotonic() - accepted > 1.5, 60
            ), _logs(api, *workers)
            before = progress()
            srv.stop()  # SIGKILL
            assert before["queued"] > 0, f"the batch ended before the kill: {before}"

            time.sleep(10)
            assert all(w.proc.poll() is None for w in workers), _logs(*workers)
            srv.start()

            def ended() -> bool:
                return bool(progress()["status"] == "finished")

            assert wait_until(ended, 120, interval=0.5), f"{progress()}\n" + _logs(api, *workers)
            page = httpx.get(f"{location}?limit=1000", timeout=30).json()
            assert page["total"] == 300
            assert page["finished"] + page["failed"] == 300, page | {"results": "..."}
            for item in page["results"]:
                assert item["status"] in ("finished", "failed"), item
                if item["status"] == "failed":
                    assert item["error"]["code"] and item["error"]["message"], item

            # The same processes, registered again under their own pids.
            assert all(w.proc.poll() is None for w in workers), _logs(*workers)
            pids = {w.proc.pid for w in workers}
            with redis.Redis.from_url(srv.url) as conn:
                assert wait_until(lambda: {w.pid for w in Worker.all(connection=conn)} == pids, 30)
            assert wait_until(lambda: httpx.get(f"{url}/readyz").json()["workers"] == 2, 30)


def test_sigterm_stops_an_idle_worker_at_once(env: dict[str, str]) -> None:
    worker = start_worker(env)
    with running(worker):
        assert wait_until(lambda: "Listening on" in worker.log(), 60), _logs(worker)
        worker.send_signal(signal.SIGTERM)
        # At once: an idle worker that kept waiting would only end past this (SIGKILL).
        assert worker.proc.wait(10) == 0, _logs(worker)


def test_sigterm_lets_a_busy_worker_finish_its_job_then_stop(slow_env: dict[str, str]) -> None:
    api, url = start_api(slow_env)
    worker = start_worker(slow_env)
    with running(api, worker):
        job_id = _submit(url, _slow_pair())
        assert wait_until(lambda: _status(url, job_id) == "started", 30), _logs(api, worker)
        worker.send_signal(signal.SIGTERM)
        waiting = _submit(url, _pair())
        assert worker.proc.wait(90) == 0, _logs(worker)
        body = httpx.get(f"{url}/v1/verifications/{job_id}").json()
        assert body["status"] == "finished", body
        assert body["result"]["statistics"]["matches"] == 4000
        assert _status(url, waiting) == "queued", "a stopping worker takes no new job"


def test_readiness_drops_a_killed_worker_within_seconds(env: dict[str, str]) -> None:
    """/readyz counts the workers that beat in the last WORKER_FRESH_S (7 s; idle workers beat
    every 2 s), not the registrations, which outlive a SIGKILLed worker by a minute or more."""
    api, url = start_api(env)
    worker = start_worker(env)
    with running(api, worker):
        assert wait_until(lambda: httpx.get(f"{url}/readyz").json()["workers"] == 1, 60), _logs(
            api, worker
        )
        worker.kill()
        assert wait_until(lambda: httpx.get(f"{url}/readyz").json()["workers"] == 0, 12)
        ready = httpx.get(f"{url}/readyz")
        assert ready.status_code == 503 and ready.json()["ready"] is False
