"""The compute pool heals itself, and a named worker survives a Redis restart; with real
processes (redis-server, ``hmcc serve``, ``hmcc worker``) on loopback, every wait bounded.

* A compute child SIGKILLed while idle (pebble then fails its whole pool) is replaced, in the
  embedded queue and in an RQ worker: 1 000 pairs sent afterwards all finish, and ``/readyz``
  counts the live children.
* A pool that cannot be rebuilt (``HMCC_FAULT_CHILD_START_FAILS``: children die at start)
  makes ``/readyz`` answer 503 and the embedded API refuse jobs; an RQ worker stops taking
  jobs and exits non-zero, leaving the queue to other workers, with no pair failed.
* A worker started with ``--name`` works again within 10 s of a Redis restart that kept its
  data (RQ alone refuses the name until its registration expires, about a minute).
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_worker.outcomes import FAULT_SLOW_PAIR_ID, FAULT_SLOW_S
from hmcc_worker.pool import FAULT_CHILD_START_FAILS
from tests.support.procs import (
    Proc,
    RedisServer,
    compute_children,
    redis_server,
    running,
    service_env,
    start_api,
    start_worker,
    wait_until,
)

pytestmark = pytest.mark.procs

PAIRS = 1000
#: How long Redis stays away in a restart: longer than the rest of the slow job (at most 0.8 s
#: after the kill), so that it ends while Redis is away.
DOWN_S = 3.0


def _batch(n_pairs: int) -> dict[str, Any]:
    """``n_pairs`` copies of one small simulated pair (its keypoints sent once, with the
    images): quick to make and to verify, so that the test is about the pool."""
    pair = simulate_pair(SimulationOptions(n_inliers=30, outlier_ratio=0.3), seed=5)
    return {
        "images": {
            "A": {**pair["image1"], "keypoints": pair["keypoints1"]},
            "B": {**pair["image2"], "keypoints": pair["keypoints2"]},
        },
        "plane": pair["plane"],
        "pairs": [
            {"id": f"p{k}", "image1": "A", "image2": "B", "matches": pair["matches"]}
            for k in range(n_pairs)
        ],
    }


def _pair() -> dict[str, Any]:
    pair = simulate_pair(SimulationOptions(n_inliers=30, outlier_ratio=0.3), seed=6)
    pair.pop("ground_truth")
    return pair


def _logs(*procs: Proc) -> str:
    return "\n".join(f"--- {p.log_path.name}\n{p.log()[-4000:]}" for p in procs)


def _readyz(url: str) -> httpx.Response:
    return httpx.get(f"{url}/readyz", timeout=5, trust_env=False)


def _kill_an_idle_child(proc: Proc, children: int) -> int:
    """SIGKILL one of ``proc``'s compute children once it has ``children`` and they are idle
    (the service answered ready and ran nothing for a second); its pid."""
    assert wait_until(lambda: len(compute_children(proc.proc.pid)) == children, 60)
    time.sleep(1.0)
    pid = min(compute_children(proc.proc.pid))
    os.kill(pid, signal.SIGKILL)
    time.sleep(1.0)  # pebble notices the death while no task runs (and fails its whole pool)
    return pid


def _run_batch(url: str, n_pairs: int, timeout_s: float = 90) -> dict[str, Any]:
    """Send a batch of ``n_pairs`` and wait until it ends; its summary (``?limit=0``)."""
    r = httpx.post(f"{url}/v1/batches", json=_batch(n_pairs), timeout=30)
    assert r.status_code == 202, r.text
    location = f"{url}{r.headers['Location']}"

    def summary() -> dict[str, Any]:
        return dict(httpx.get(f"{location}?limit=0", timeout=10).json())

    wait_until(lambda: summary()["status"] == "finished", timeout_s, 0.5)
    return summary()


def test_embedded_a_child_killed_while_idle_is_replaced() -> None:
    api, url = start_api(service_env(HMCC_EMBEDDED_WORKERS="2"))
    with running(api):
        assert wait_until(lambda: _readyz(url).json()["workers"] == 2, 60), _logs(api)
        dead = _kill_an_idle_child(api, 2)

        done = _run_batch(url, PAIRS)
        assert (done["status"], done["finished"], done["failed"]) == ("finished", PAIRS, 0), (
            f"{done}\n{_logs(api)}"
        )
        # /readyz counts the live children: two again, the killed one not among them.
        assert wait_until(lambda: _readyz(url).json()["workers"] == 2, 30), _logs(api)
        children = compute_children(api.proc.pid)
        assert len(children) == 2 and dead not in children, children


def test_rq_a_workers_child_killed_while_idle_is_replaced() -> None:
    with redis_server() as srv:
        env = service_env(REDIS_URL=srv.url, HMCC_WORKER_GRACE_S="1")
        api, url = start_api(env)
        worker = start_worker(env, "heal")
        with running(api, worker):
            assert wait_until(lambda: _readyz(url).json()["workers"] == 1, 60), _logs(api, worker)
            dead = _kill_an_idle_child(worker, 1)

            done = _run_batch(url, PAIRS)
            assert (done["status"], done["finished"], done["failed"]) == (
                "finished",
                PAIRS,
                0,
            ), f"{done}\n{_logs(api, worker)}"
            assert worker.proc.poll() is None, _logs(worker)
            assert _readyz(url).json()["workers"] == 1
            children = compute_children(worker.proc.pid)
            assert len(children) == 1 and dead not in children, children


@pytest.fixture
def start_fails(tmp_path: Path) -> Iterator[Path]:
    """The file whose existence makes every compute child started from then on fail."""
    yield tmp_path / "children-fail"


def test_embedded_a_pool_that_cannot_be_rebuilt_is_not_ready(start_fails: Path) -> None:
    api, url = start_api(
        service_env(HMCC_EMBEDDED_WORKERS="2", **{FAULT_CHILD_START_FAILS: str(start_fails)})
    )
    with running(api):
        assert wait_until(lambda: _readyz(url).json()["workers"] == 2, 60), _logs(api)
        start_fails.touch()
        _kill_an_idle_child(api, 2)

        # 503 while the pool is rebuilt (no live child), then for good: the pool is dead.
        assert wait_until(lambda: "compute pool" in _readyz(url).json().get("error", ""), 60), (
            _logs(api)
        )
        ready = _readyz(url)
        assert ready.status_code == 503 and ready.json()["workers"] == 0, ready.text
        r = httpx.post(f"{url}/v1/verifications", json=_pair(), timeout=10)
        assert r.status_code == 503, r.text
        assert r.json()["error"]["code"] == "queue_unavailable"
        assert "compute pool" in r.json()["error"]["message"]


def test_rq_a_worker_whose_pool_cannot_be_rebuilt_exits_and_leaves_the_queue(
    start_fails: Path,
) -> None:
    with redis_server() as srv:
        env = service_env(REDIS_URL=srv.url, HMCC_WORKER_GRACE_S="1")
        api, url = start_api(env)
        doomed = start_worker({**env, FAULT_CHILD_START_FAILS: str(start_fails)}, "doomed")
        with running(api, doomed):
            assert wait_until(lambda: _readyz(url).json()["workers"] == 1, 60), _logs(api, doomed)
            start_fails.touch()
            _kill_an_idle_child(doomed, 1)
            r = httpx.post(f"{url}/v1/batches", json=_batch(40), timeout=30)
            assert r.status_code == 202, r.text
            location = f"{url}{r.headers['Location']}"

            # It exits non-zero (its supervisor restarts it) rather than failing the jobs.
            assert wait_until(lambda: doomed.proc.poll() is not None, 60), _logs(doomed)
            assert doomed.proc.returncode not in (0, None), _logs(doomed)
            assert wait_until(lambda: _readyz(url).status_code == 503, 15), _logs(api)
            page = httpx.get(f"{location}?limit=0", timeout=10).json()
            assert page["failed"] == 0 and page["status"] != "finished", page

            # A healthy worker finishes the batch, every pair of it.
            healthy = start_worker(env, "healthy")
            with running(healthy):

                def summary() -> dict[str, Any]:
                    return dict(httpx.get(f"{location}?limit=0", timeout=10).json())

                wait_until(lambda: summary()["status"] == "finished", 90, 0.5)
                done = summary()
                assert (done["status"], done["finished"], done["failed"]) == (
                    "finished",
                    40,
                    0,
                ), f"{done}\n{_logs(api, healthy)}"


def test_a_named_worker_works_within_10_s_of_a_redis_restart_that_kept_its_data() -> None:
    """Redis is SIGKILLed while the worker runs a job, which ends while Redis is away: RQ's
    worker quits, and its registration (never marked dead) comes back with Redis."""
    with redis_server(aof=True) as srv:
        env = service_env(
            REDIS_URL=srv.url,
            HMCC_WORKER_GRACE_S="1",
            **{FAULT_SLOW_PAIR_ID: "slow", FAULT_SLOW_S: "2"},
        )
        api, url = start_api(env)
        worker = start_worker(env, "named")  # hmcc worker --name named-<port>
        with running(api, worker):
            assert wait_until(lambda: _readyz(url).json()["workers"] == 1, 60), _logs(api, worker)
            busy = _batch(1)
            busy["pairs"][0]["id"] = "slow"
            r = httpx.post(f"{url}/v1/batches", json=busy, timeout=30)
            assert r.status_code == 202, r.text
            location = f"{url}{r.headers['Location']}"
            assert wait_until(
                lambda: httpx.get(f"{location}?limit=0", timeout=5).json()["started"] == 1, 30
            ), _logs(api, worker)
            time.sleep(1.2)  # the AOF is fsynced every second: the registration is on disk

            _restart(srv)
            back = time.monotonic()

            def verified() -> bool:
                r = httpx.post(f"{url}/v1/verifications?wait=2", json=_pair(), timeout=10)
                return bool(r.json()["status"] == "finished")

            assert wait_until(verified, 10, 0.2), _logs(api, worker)
            assert time.monotonic() - back <= 10.5
            assert worker.proc.poll() is None
            assert "There exists an active worker" not in worker.log(), _logs(worker)


def _restart(srv: RedisServer) -> None:
    """SIGKILL redis-server and start it again on its data (it replays its AOF) after
    :data:`DOWN_S` seconds."""
    srv.stop()
    time.sleep(DOWN_S)
    srv.start()
