"""The compute pool: a crash or a hang costs one pair; the pool and the other pairs go on."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

from hmcc.flight import Flight
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_batch
from hmcc_worker.outcomes import FAULT_CRASH_PAIR_ID, PairOutcome, unpack, verify_flight
from hmcc_worker.pool import FAULT_CHILD_START_FAILS, ComputePool, ComputePoolDead
from hmcc_worker.protocol import JobStatus
from tests.support.procs import wait_until

pytestmark = pytest.mark.procs


def _batch(ids: list[str], **pair_edits: object) -> dict:
    pairs = [
        simulate_pair(SimulationOptions(n_inliers=60, outlier_ratio=0.3), s)
        for s in range(len(ids))
    ]
    return {
        "images": {"a": pairs[0]["image1"], "b": pairs[0]["image2"]},
        "plane": pairs[0]["plane"],
        "pairs": [
            {
                "id": i,
                "image1": "a",
                "image2": "b",
                "keypoints1": p["keypoints1"],
                "keypoints2": p["keypoints2"],
                "matches": p["matches"],
                **pair_edits,
            }
            for i, p in zip(ids, pairs, strict=True)
        ],
    }


#: Spawned children (a service's pool) and children forked from a warm fork server
#: (``hmcc flight``'s): the same guarantees.
START = pytest.mark.parametrize("forked", [False, True], ids=["spawned", "forked"])


@pytest.fixture(scope="module", params=[False, True], ids=["spawned", "forked"])
def pool(request: pytest.FixtureRequest) -> Iterator[ComputePool]:
    os.environ[FAULT_CRASH_PAIR_ID] = "boom"  # read by the children, which start below
    pool = ComputePool(1, timeout_s=20, forked=request.param)
    try:
        pool.start()
        yield pool
    finally:
        pool.close(wait=False)
        del os.environ[FAULT_CRASH_PAIR_ID]


def test_a_crashing_pair_costs_that_pair_only(pool: ComputePool) -> None:
    flight = parse_batch(json.dumps(_batch(["p0", "boom", "p2", "p3"])), 100)
    outcomes = pool.run(flight)
    assert [o.status for o in outcomes] == ["finished", "failed", "finished", "finished"]
    error = json.loads(unpack(outcomes[1].pack())[1])
    assert error["code"] == "worker_crashed" and "SIGSEGV" in error["message"]
    # The pool replaced its child and goes on.
    again = pool.run(parse_batch(json.dumps(_batch(["q0", "q1"])), 100))
    assert [o.status for o in again] == ["finished", "finished"]


def _with_pid(flight: Flight) -> list[PairOutcome]:
    """verify_flight, each outcome marked with the pid of the process that ran it."""
    return [
        dataclasses.replace(o, timings_ms={**o.timings_ms, "pid": os.getpid()})
        for o in verify_flight(flight)
    ]


def test_the_callers_function_runs_in_the_child_after_a_crash_too(pool: ComputePool) -> None:
    flight = parse_batch(json.dumps(_batch(["p0", "boom", "p2"])), 100)
    outcomes = pool.run(flight, fn=_with_pid)
    assert [o.status for o in outcomes] == ["finished", "failed", "finished"]
    pids = {outcomes[0].timings_ms["pid"], outcomes[2].timings_ms["pid"]}  # pair by pair
    assert os.getpid() not in pids
    mapped = dict(pool.map_flight(parse_batch(json.dumps(_batch(["q0", "q1"])), 100), fn=_with_pid))
    assert sorted(mapped) == [0, 1] and all("pid" in o.timings_ms for o in mapped.values())


def test_a_single_crashing_pair(pool: ComputePool) -> None:
    (outcome,) = pool.run(parse_batch(json.dumps(_batch(["boom"])), 100))
    assert outcome.status is JobStatus.failed
    assert json.loads(outcome.body)["code"] == "worker_crashed"


@START
def test_a_pair_past_the_timeout_is_killed_and_reported(forked: bool) -> None:
    # Plain RANSAC capped at a million iterations on all-outlier matches: seconds of work.
    slow = _batch(["slow"])
    slow["method"] = "ransac"
    slow["params"] = {"ransac": {"max_iters": 1_000_000, "confidence": 0.999999}}
    pair = slow["pairs"][0]
    n = len(pair["keypoints1"])
    pair["matches"] = [[i, (i * 7919 + 13) % n] for i in range(n)] * 40
    quick = ComputePool(1, timeout_s=0.5, forked=forked)
    try:
        quick.start()
        (outcome,) = quick.run(parse_batch(json.dumps(slow), 100))
        assert json.loads(outcome.body)["code"] == "timeout"
        ok = quick.run(parse_batch(json.dumps(_batch(["fine"])), 100))
        assert ok[0].status is JobStatus.finished
    finally:
        quick.close(wait=False)


@START
def test_start_warms_every_child(forked: bool) -> None:
    """start() returns once each child has run a task (children are warm before their first
    task), not after the first child alone."""
    pool = ComputePool(2, forked=forked)
    try:
        pids = pool.start()
        assert len(pids) == 2 and os.getpid() not in pids
        alive = {int(p.pid) for p in multiprocessing.active_children()}
        assert pids <= alive
    finally:
        pool.close()


_PRESTART = """
import sys, time
from hmcc_worker.pool import ComputePool

if __name__ == "__main__":
    pool = ComputePool(2, forked=True)
    t0 = time.perf_counter()
    started = pool.prestart()
    returned = time.perf_counter() - t0
    pids = started.result(timeout=120)
    warm = time.perf_counter() - t0
    pool.close()
    print(returned, warm, len(set(pids)))
"""


def test_prestart_returns_at_once_and_its_future_holds_each_warm_child(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """In a fresh process (no fork server yet, which takes about a second to import and warm
    the core): prestart() returns before the children are warm, so that ``hmcc flight``
    parses its file meanwhile; its future then holds the pids of the children that ran its
    short tasks."""
    script = tmp_path / "prestart.py"
    script.write_text(_PRESTART)
    out = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=180, check=True
    )
    returned, warm, children = out.stdout.split()
    # one short task a child; on a slow machine one child may take both
    assert 1 <= int(children) <= 2
    assert float(warm) > 0.3  # the fork server's own start, before any child runs a task
    assert float(returned) < float(warm) / 3


def _kill_idle_child(pool: ComputePool) -> int:
    """SIGKILL one of the pool's children while it is idle; its pid."""
    pid = min(pool.live_children())
    os.kill(pid, signal.SIGKILL)
    return pid


@START
def test_a_child_killed_while_idle_is_replaced_and_the_pool_serves_on(forked: bool) -> None:
    pool = ComputePool(2, timeout_s=20, forked=forked)
    try:
        pool.start()
        time.sleep(0.5)  # idle: no task anywhere in the pool
        dead = _kill_idle_child(pool)
        time.sleep(0.5)  # pebble notices the death (and, unhealed, breaks the pool)
        outcomes = pool.run(parse_batch(json.dumps(_batch(["p0", "p1", "p2"])), 100))
        assert [o.status for o in outcomes] == ["finished"] * 3
        assert wait_until(lambda: len(pool.live_children()) == 2, 30)
        assert dead not in pool.live_children() and not pool.dead
    finally:
        pool.close(wait=False)


@START
def test_a_pool_whose_children_cannot_start_is_dead(tmp_path, forked: bool) -> None:  # type: ignore[no-untyped-def]
    flag = tmp_path / "children-fail"
    os.environ[FAULT_CHILD_START_FAILS] = str(flag)  # read by the children, which start below
    pool = ComputePool(1, timeout_s=20, forked=forked)
    try:
        pool.start()
        flag.touch()
        _kill_idle_child(pool)
        assert wait_until(lambda: pool.dead, 60)
        assert pool.live_children() == set()
        with pytest.raises(ComputePoolDead):
            pool.run(parse_batch(json.dumps(_batch(["p0"])), 100))
    finally:
        del os.environ[FAULT_CHILD_START_FAILS]
        pool.close(wait=False)
