"""Job metrics: the same counters whether kept in memory or in Redis."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator

import pytest
import redis

from hmcc_worker.metrics import (
    STAGE_BUCKETS_S,
    MemoryJobMetrics,
    RedisJobMetrics,
    children_cpu_s,
    process_cpu_s,
)
from hmcc_worker.outcomes import PairOutcome, StoredOutcomes
from hmcc_worker.protocol import JobStatus
from tests.support.procs import redis_server


def _outcome(**timings_ms: float) -> PairOutcome:
    return PairOutcome(JobStatus.finished, b"{}", timings_ms)


OUTCOMES = [
    _outcome(direction=0.3, ransac=1.5, compute=1.8),
    _outcome(direction=0.7, ransac=40.0, compute=40.7),
    _outcome(direction=0.2, ransac=1e6, compute=1e6),  # 1000 s: the +Inf bucket
    PairOutcome(JobStatus.failed, b'{"code": "invalid_input"}'),
]


@pytest.fixture(scope="module")
def redis_client() -> Iterator[redis.Redis]:
    with redis_server() as server:
        yield redis.Redis.from_url(server.url)


def test_buckets_are_cumulative_and_sums_in_seconds() -> None:
    metrics = MemoryJobMetrics()
    metrics.record(OUTCOMES)
    metrics.record_failure("AbandonedJobError")
    snap = metrics.snapshot()
    cumulative, total = snap.stages["direction"]
    assert len(cumulative) == len(STAGE_BUCKETS_S) + 1
    assert cumulative[STAGE_BUCKETS_S.index(0.0005)] == 2  # 0.2 and 0.3 ms
    assert cumulative[STAGE_BUCKETS_S.index(0.001)] == 3
    assert cumulative[-1] == 3
    assert total == pytest.approx(1.2e-3)
    ransac, _ = snap.stages["ransac"]
    assert ransac[STAGE_BUCKETS_S.index(0.002)] == 1
    assert ransac[STAGE_BUCKETS_S.index(0.05)] == 2
    assert ransac[-2] == 2 and ransac[-1] == 3
    assert snap.outcomes == {"finished": 3, "failed": 1}
    assert snap.failures == {"AbandonedJobError": 1}


def test_a_jobs_stored_outcomes_count_as_its_outcomes_do() -> None:
    """What a child hands back for the service to store (:class:`StoredOutcomes`): each pair's
    stored form, the failures, and increments that count as the outcomes themselves do."""
    stored = StoredOutcomes.of(OUTCOMES)
    assert stored.packed == [o.pack() for o in OUTCOMES]
    assert stored.failed == 1
    by_outcomes, by_increments = MemoryJobMetrics(), MemoryJobMetrics()
    by_outcomes.record(OUTCOMES, 2.5)
    by_increments.add(stored.increments, 2.5)
    assert by_increments.snapshot() == by_outcomes.snapshot()
    assert by_increments.snapshot().stages["job"][1] == 2.5


@pytest.mark.procs
def test_redis_counters_equal_memory_counters(redis_client: redis.Redis) -> None:
    memory, shared = MemoryJobMetrics(), RedisJobMetrics(redis_client)
    for m in (memory, shared):
        m.record(OUTCOMES[:2])
        m.record(OUTCOMES[2:])
        m.record_failure("JobTimeoutException")
    a, b = shared.snapshot(), memory.snapshot()
    assert (a.outcomes, a.failures) == (b.outcomes, b.failures)
    assert a.stages.keys() == b.stages.keys()
    for stage, (buckets, total) in a.stages.items():
        assert buckets == b.stages[stage][0]
        assert total == pytest.approx(b.stages[stage][1])


def test_process_cpu_counts_a_live_child_then_an_ended_one() -> None:
    # the serial share's two halves: a process's own CPU, and its children's (live ones read
    # from /proc, ended ones from getrusage once they were waited for)
    me = process_cpu_s()
    assert me is not None and me[0] > 0
    before = children_cpu_s([])
    burn = "import sys; sum(range(3 * 10**7)); sys.stdout.write('x'); sys.stdout.flush(); input()"
    child = subprocess.Popen(
        [sys.executable, "-c", burn], stdin=subprocess.PIPE, stdout=subprocess.PIPE
    )
    try:
        assert child.stdout is not None and child.stdout.read(1) == b"x"  # it has burned
        live = children_cpu_s([child.pid])
        assert live > before  # counted while it lives
        assert children_cpu_s([]) == pytest.approx(before, abs=0.02)  # not yet ended
    finally:
        child.communicate(b"\n", timeout=30)
    assert children_cpu_s([]) >= live - 0.02  # ended and waited for: getrusage has it
    assert process_cpu_s(2**22 + os.getpid()) is None  # no such process
