"""The embedded queue's memory bound: through a real ``hmcc serve``, with
``HMCC_RESULT_MEMORY_MB=1``, results beyond a megabyte push out the oldest first (a pair job
then reads 404, a batch's pairs ``expired``), and what stays readable fits in the bound; in
process (the compute pool replaced by one that finishes every pair at once), the bound counts
each kept job's own memory besides its results, so it bounds the number of jobs kept too."""

from __future__ import annotations

import asyncio
import gc
import os
import threading
import tracemalloc
from collections.abc import Iterator
from typing import Any

import httpx
import orjson
import pytest

from hmcc.flight import Flight
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_pair
from hmcc_service import embedded
from hmcc_service.embedded import KEPT_JOB_BYTES, EmbeddedQueue
from hmcc_service.settings import Settings
from hmcc_worker.outcomes import PairOutcome, StoredOutcomes
from hmcc_worker.protocol import JobKind, JobStatus
from hmcc_worker.shared_flight import SharedFlight
from tests.support.procs import service_env, start_api, wait_until

MB = 1024 * 1024
PAIRS = 200


@pytest.fixture(scope="module")
def url() -> Iterator[str]:
    # one compute child: a batch's jobs end in order, its last one the newest (a job of 25 of
    # these results, kept as JSON and as MessagePack, takes half the bound: one more job and
    # the older goes)
    api, base = start_api(service_env(HMCC_RESULT_MEMORY_MB="1", HMCC_EMBEDDED_WORKERS="1"))
    try:
        yield base
    finally:
        api.stop()


def _big_results_batch(n_pairs: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """A pair whose result is some 12 KB (2 000 inliers listed), and a batch of ``n_pairs``
    copies of it (the keypoints sent once, with the images)."""
    pair = simulate_pair(SimulationOptions(n_inliers=2000, outlier_ratio=0.2), seed=1)
    pair.pop("ground_truth")
    batch = {
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
    return pair, batch


@pytest.mark.procs
def test_results_beyond_the_memory_bound_are_forgotten_oldest_first(url: str) -> None:
    pair, batch = _big_results_batch(PAIRS)
    first = httpx.post(f"{url}/v1/verifications?wait=30", json=pair, timeout=40).json()
    assert first["status"] == "finished", first
    size = len(orjson.dumps(first["result"]))
    assert PAIRS * size > 2 * MB, "the batch's results must overflow the bound"

    r = httpx.post(f"{url}/v1/batches", json=batch, timeout=60)
    assert r.status_code == 202, r.text
    location = f"{url}{r.headers['Location']}"
    assert wait_until(
        lambda: httpx.get(f"{location}?limit=0").json()["status"] == "finished", 120, 0.5
    )

    # The oldest result (the single pair's) went first.
    gone = httpx.get(f"{url}/v1/verifications/{first['job_id']}")
    assert gone.status_code == 404 and gone.json()["error"]["code"] == "not_found"

    items = []
    for offset in range(0, PAIRS, 100):
        items += httpx.get(f"{location}?offset={offset}&limit=100", timeout=30).json()["results"]
    page = httpx.get(f"{location}?limit=0").json()
    statuses = [i["status"] for i in items]
    assert set(statuses) == {"expired", "finished"}, set(statuses)
    assert (page["expired"], page["finished"]) == (
        statuses.count("expired"),
        statuses.count("finished"),
    )
    assert statuses[-1] == "finished", "the newest results are kept"
    expired = [i for i in items if i["status"] == "expired"]
    assert all(i["result"] is None and i["error"] is None for i in expired)
    kept = sum(len(orjson.dumps(i["result"])) for i in items if i["status"] == "finished")
    assert kept <= MB, f"{kept} bytes of results kept, the bound is {MB}"


# --------------------------------------------------------------------------- in process


class _InstantPool:
    """Stands in for the compute pool: every pair of a flight finishes at once, its result
    ``{}``, so what a kept job holds is the queue's own bookkeeping."""

    dead = False
    started = True

    def __init__(self, processes: int, timeout_s: float | None = None) -> None:
        self.processes = processes

    def live_children(self) -> set[int]:
        return set(range(self.processes))

    def start(self) -> None:
        pass

    def run(self, flight: Flight) -> list[PairOutcome]:
        return [PairOutcome(JobStatus.finished, b"{}") for _ in flight.pairs]

    def call(self, fn: Any, flight: Flight) -> StoredOutcomes:
        """The queue's one call (``verify_flight_stored``): :meth:`run`'s outcomes, stored."""
        return StoredOutcomes.of(self.run(flight))

    def close(self, wait: bool = True) -> None:
        pass


@pytest.fixture
def flight() -> Flight:
    pair = simulate_pair(SimulationOptions(n_inliers=20), seed=1)
    pair.pop("ground_truth")
    return parse_pair(pair)


def _finish_jobs(queue: EmbeddedQueue, flight: Flight, n: int) -> list[str]:
    """``n`` single-pair jobs submitted and finished, 50 at a time; their ids."""

    async def run() -> list[str]:
        ids: list[str] = []
        for _ in range(0, n, 50):
            records = await queue.submit(JobKind.pair, [flight] * 50)
            for record in records:
                done = await queue.wait(record.job_id, 10)
                assert done is not None and done.status is JobStatus.finished
            ids += [r.job_id for r in records]
        return ids

    return asyncio.run(run())


def _queue(monkeypatch: pytest.MonkeyPatch, memory_mb: int) -> EmbeddedQueue:
    monkeypatch.setattr(embedded, "ComputePool", _InstantPool)
    return EmbeddedQueue(Settings.model_construct(result_memory_mb=memory_mb))


def test_the_memory_bound_counts_each_kept_jobs_own_memory(
    monkeypatch: pytest.MonkeyPatch, flight: Flight
) -> None:
    """With 1 MB, a thousand jobs of a 3-byte result each: only as many are kept as their
    bookkeeping fits in the megabyte (the results' bytes alone would keep them all)."""
    queue = _queue(monkeypatch, memory_mb=1)
    ids = _finish_jobs(queue, flight, 1000)
    kept = sum(r is not None for r in asyncio.run(queue.fetch(ids)))
    assert MB // (KEPT_JOB_BYTES + 200) <= kept <= MB // KEPT_JOB_BYTES, kept
    # the newest ended are kept: jobs end in their batch of 50's order, not within it
    newest = ids[-(kept - kept % 50) :]
    assert all(r is not None for r in asyncio.run(queue.fetch(newest))), "newest kept"


def test_a_kept_jobs_counted_bytes_cover_what_it_holds(
    monkeypatch: pytest.MonkeyPatch, flight: Flight
) -> None:
    """The memory that finished jobs hold (tracemalloc: what the queue allocated for them and
    still holds) is no more than the bound counts for them, and not far less."""
    queue = _queue(monkeypatch, memory_mb=1024)
    _finish_jobs(queue, flight, 50)  # warm: the threads, the first allocations
    gc.collect()
    tracemalloc.start()
    try:
        held, counted = tracemalloc.get_traced_memory()[0], queue._kept_bytes
        _finish_jobs(queue, flight, 500)
        gc.collect()
        held, counted = tracemalloc.get_traced_memory()[0] - held, queue._kept_bytes - counted
    finally:
        tracemalloc.stop()
    assert held <= counted <= 2 * held, (held / 500, counted / 500)


def test_cancelled_jobs_count_against_the_bound_too(
    monkeypatch: pytest.MonkeyPatch, flight: Flight
) -> None:
    """A cancelled job is kept (it reads ``canceled``) until its TTL like a finished one, so the
    bound counts it too: a thousand cancellations keep no more than fit in 1 MB."""
    release = threading.Event()

    class HeldPool(_InstantPool):
        def run(self, flight: Flight) -> list[PairOutcome]:
            release.wait(10)
            return super().run(flight)

    monkeypatch.setattr(embedded, "ComputePool", HeldPool)
    settings = Settings.model_construct(
        result_memory_mb=1, embedded_workers=1, max_queue_depth=10_000
    )
    queue = EmbeddedQueue(settings)

    async def cancel_all_but_the_first() -> list[str]:
        records = await queue.submit(JobKind.pair, [flight] * 1001)
        try:
            for record in records[1:]:  # the first one holds the only thread
                await queue.cancel(record.job_id)
        finally:
            release.set()
        return [r.job_id for r in records[1:]]

    ids = asyncio.run(cancel_all_but_the_first())
    kept = sum(r is not None for r in asyncio.run(queue.fetch(ids)))
    assert 0 < kept <= MB // KEPT_JOB_BYTES, kept


def test_a_batchs_chunks_share_one_file_removed_after_its_last_job(
    monkeypatch: pytest.MonkeyPatch, flight: Flight
) -> None:
    """A batch's chunks reach the pool as shared flights of one file (their pairs in order),
    which stays while any of its jobs has not ended (a cancelled one counts as ended) and is
    removed after the last; a single pair's job is handed over as it is."""
    release = threading.Event()
    seen: list[Flight] = []

    class HeldPool(_InstantPool):
        def run(self, flight: Flight) -> list[PairOutcome]:
            seen.append(flight)
            assert os.path.isdir(flight.folder) if isinstance(flight, SharedFlight) else True
            release.wait(10)
            return super().run(flight)

    monkeypatch.setattr(embedded, "ComputePool", HeldPool)
    queue = EmbeddedQueue(
        Settings.model_construct(embedded_workers=1, max_queue_depth=100, result_memory_mb=64)
    )
    batch = Flight(
        flight.images,
        flight.pairs * 5,
        flight.method,
        flight.options,
        flight.plane_z,
        flight.ground_z,
        flight.match_options,
    )
    chunks = [batch.subset(r) for r in (range(0, 2), range(2, 4), range(4, 5))]

    async def run() -> None:
        records = await queue.submit(JobKind.chunk, chunks, batch_id="b", images=batch.images)
        pair = await queue.submit(JobKind.pair, [flight])
        assert wait_until(lambda: len(seen) == 1, 10)
        folder = seen[0].folder
        await queue.cancel(records[2].job_id)
        release.set()
        for record in [*records[:2], *pair]:
            done = await queue.wait(record.job_id, 10)
            assert done is not None and done.status is JobStatus.finished
        assert wait_until(lambda: not os.path.exists(folder), 10)
        assert [f.indices for f in seen[:2]] == [(0, 1), (2, 3)]
        assert type(seen[2]) is Flight

    asyncio.run(run())
    asyncio.run(queue.close())


def test_a_batch_that_cannot_be_shared_reaches_the_pool_with_int64_matches(
    monkeypatch: pytest.MonkeyPatch, flight: Flight
) -> None:
    """The batches route keeps each pair's matches as sent (uint16, say); a batch whose
    shared file cannot be written is pickled to the pool as it is, its matches converted to
    the core's int64 first."""
    from dataclasses import replace

    import numpy as np

    seen: list[Flight] = []

    class SeeingPool(_InstantPool):
        def run(self, flight: Flight) -> list[PairOutcome]:
            seen.append(flight)
            return super().run(flight)

    def no_room(*args: Any) -> Any:
        raise OSError("no room")

    monkeypatch.setattr(embedded, "ComputePool", SeeingPool)
    monkeypatch.setattr(embedded, "_share", no_room)
    queue = EmbeddedQueue(
        Settings.model_construct(embedded_workers=1, max_queue_depth=100, result_memory_mb=64)
    )
    (pair,) = flight.pairs
    sent = replace(pair, matches=pair.matches.astype("<u2"))
    batch = replace(flight, pairs=[sent, pair])

    async def run() -> None:
        (record,) = await queue.submit(JobKind.chunk, [batch], batch_id="b", images=batch.images)
        done = await queue.wait(record.job_id, 10)
        assert done is not None and done.status is JobStatus.finished

    asyncio.run(run())
    asyncio.run(queue.close())
    (ran,) = seen
    assert [p.matches.dtype for p in ran.pairs] == [np.int64, np.int64]
    assert np.array_equal(ran.pairs[0].matches, pair.matches)
    assert ran.pairs[1] is pair  # int64 already: as it was
