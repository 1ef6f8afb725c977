"""How a batch is split into queue jobs (``routes.batches.split``)."""

from __future__ import annotations

from typing import Any

import httpx
import numpy as np
import pytest

from hmcc.flight import FlightPair
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_service.app import create_app
from hmcc_service.routes.batches import MIN_CHUNK_PAIRS, MIN_JOBS, _first_waiting, split
from hmcc_service.settings import Settings
from hmcc_worker.protocol import JobStatus


def _pairs(*matches: int) -> list[FlightPair]:
    return [FlightPair("a", "b", np.zeros((m, 2), dtype=np.int64)) for m in matches]


def _sizes(chunks: list[range]) -> list[int]:
    return [len(c) for c in chunks]


def test_chunks_cover_the_pairs_in_order_once() -> None:
    pairs = _pairs(*([700] * 2000))
    chunks = split(pairs, 256, 256_000)
    assert [i for c in chunks for i in c] == list(range(2000))


def test_a_large_batch_makes_jobs_of_at_most_the_limits() -> None:
    assert _sizes(split(_pairs(*([10] * 5000)), 256, 256_000)) == [256] * 19 + [136]
    assert max(_sizes(split(_pairs(*([1000] * 2000)), 256, 64_000))) == 64


def test_a_small_batch_is_still_shared_among_several_jobs() -> None:
    sizes = _sizes(split(_pairs(*([100] * 200)), 256, 256_000))
    assert len(sizes) == MIN_JOBS and max(sizes) == 25
    assert _sizes(split(_pairs(*([100] * 40)), 256, 256_000)) == [MIN_CHUNK_PAIRS] * 2 + [8]


@pytest.mark.parametrize("limit", [1, 4])
def test_a_smaller_limit_wins(limit: int) -> None:
    assert set(_sizes(split(_pairs(*([5] * 8)), limit, 256_000))) == {limit}


def test_a_pair_over_the_match_limit_is_a_job_of_its_own() -> None:
    assert _sizes(split(_pairs(10, 5000, 10), 256, 1000)) == [1, 1, 1]


def test_pairs_to_match_weigh_their_first_images_keypoints() -> None:
    """Pairs that ask for matching have no matches yet: each counts its first image's
    keypoints, so 100 pairs of 16 000 keypoints make chunks of 4 under 64 000."""
    from hmcc.flight import Flight, FlightImage
    from hmcc_service.routes.batches import pair_weights

    image = FlightImage(None, None, np.zeros((16_000, 2)), np.zeros((16_000, 128), np.uint8))  # type: ignore[arg-type]
    pairs = [FlightPair("a", "b", np.zeros((0, 2), np.int64), match=True) for _ in range(100)]
    pairs.append(FlightPair("a", "b", np.zeros((50, 2), np.int64)))
    flight = Flight({"a": image, "b": image}, pairs)
    weights = pair_weights(flight)
    assert weights == [16_000] * 100 + [50]
    chunks = split(flight.pairs, 256, 64_000, weights)
    assert max(_sizes(chunks)) == 4
    assert [i for c in chunks for i in c] == list(range(101))


def test_pairs_as_columns_split_and_subset_as_their_rows_without_being_built(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A batch whose pairs are columns weighs and splits by its counts and keeps each chunk
    as columns with the images it names: the same chunks as its rows, no pair built."""
    from hmcc.flight import Flight, FlightImage
    from hmcc_schema.columns import PairColumns
    from hmcc_service.routes.batches import pair_weights, subset

    counts = np.array([700] * 300 + [5000, 10, 10])
    starts = np.concatenate([[0], np.cumsum(counts)])
    names = [f"i{k % 7}" for k in range(len(counts))]
    columns = PairColumns(
        names, names[1:] + names[:1], None, np.zeros((starts[-1], 2), np.uint16), starts
    )
    image = FlightImage(None, None, np.zeros((10, 2)))  # type: ignore[arg-type]
    flight = Flight({f"i{k}": image for k in range(9)}, columns)
    rows = _pairs(*counts)
    want = split(rows, 64, 20_000)

    def built(*args: Any) -> None:
        raise AssertionError("a pair of columns was built")

    monkeypatch.setattr(PairColumns, "__getitem__", built)
    weights = pair_weights(flight)
    assert weights == counts.tolist()
    assert split(flight.pairs, 64, 20_000, weights) == want
    part = subset(flight, want[1])
    assert isinstance(part.pairs, PairColumns) and part.pairs.counts().tolist() == [
        int(counts[i]) for i in want[1]
    ]
    assert sorted(part.images) == sorted({f"i{k}" for k in range(7)})


def test_an_ended_page_stops_at_the_first_chunk_still_waiting() -> None:
    """``?ended=true``'s end: the first pair from the offset on whose chunk is queued or
    started; an expired chunk (no record) has ended, as have finished and failed ones."""
    from types import SimpleNamespace

    chunks = [{"start": s, "count": 4} for s in (0, 4, 8, 12)]

    def records(*statuses: JobStatus | None) -> list[Any]:
        return [None if s is None else SimpleNamespace(status=s) for s in statuses]

    done, failed, started, queued = (
        JobStatus.finished,
        JobStatus.failed,
        JobStatus.started,
        JobStatus.queued,
    )
    assert _first_waiting(chunks, records(done, failed, started, queued), 0) == 8
    assert _first_waiting(chunks, records(done, None, started, queued), 9) == 9
    assert _first_waiting(chunks, records(done, queued, done, queued), 0) == 4
    assert _first_waiting(chunks, records(started, done, done, done), 0) == 0
    assert _first_waiting(chunks, records(started, done, done, done), 5) > 16


@pytest.mark.usefixtures("hermetic_env")
def test_jobs_are_larger_with_rq_unless_set(monkeypatch: pytest.MonkeyPatch) -> None:
    """A job costs bookkeeping outside the compute with RQ (its worker, Redis, the API), little
    embedded: the default job size follows; a size set is kept in either mode."""
    assert Settings().chunk_limits() == (256, 256_000)
    monkeypatch.setenv("REDIS_URL", "redis://127.0.0.1:6379/0")
    assert Settings().chunk_limits() == (1024, 1_000_000)
    monkeypatch.setenv("HMCC_BATCH_CHUNK_PAIRS", "64")
    assert Settings().chunk_limits() == (64, 1_000_000)
    monkeypatch.delenv("REDIS_URL")
    assert Settings(batch_chunk_matches=5000).chunk_limits() == (64, 5000)


def test_a_batch_makes_at_least_one_job_a_worker() -> None:
    sizes = _sizes(split(_pairs(*([100] * 400)), 1024, 1_000_000, min_jobs=20))
    assert len(sizes) == 20 and set(sizes) == {20}
    # never below MIN_CHUNK_PAIRS a job, however many workers
    assert _sizes(split(_pairs(*([100] * 400)), 1024, 1_000_000, min_jobs=100)) == [16] * 25


@pytest.mark.anyio
@pytest.mark.procs
@pytest.mark.parametrize(("workers", "jobs"), [(3, MIN_JOBS), (20, 20)])
@pytest.mark.usefixtures("hermetic_env")
async def test_the_service_splits_a_batch_by_how_many_workers_it_has(
    workers: int, jobs: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The API asks its queue how many jobs run at once (the live RQ workers, the embedded
    children) and makes at least that many jobs of a batch, and at least MIN_JOBS."""
    pair = simulate_pair(SimulationOptions(n_inliers=20), seed=1)
    body = {
        "images": {"a": pair["image1"], "b": pair["image2"]},
        "plane": pair["plane"],
        "pairs": [
            {"image1": "a", "image2": "b", **{k: pair[k] for k in ("keypoints1", "keypoints2")}}
            | {"matches": pair["matches"]}
            for _ in range(400)
        ],
    }
    app = create_app(Settings())

    async def live() -> int:
        return workers

    monkeypatch.setattr(app.state.queue, "workers", live)
    transport = httpx.ASGITransport(app=app)
    try:
        async with httpx.AsyncClient(transport=transport, base_url="http://hmcc.test") as client:
            r = await client.post("/v1/batches", json=body)
        assert r.status_code == 202, r.text
        assert r.json()["jobs"] == jobs
    finally:
        await app.state.queue.close()
