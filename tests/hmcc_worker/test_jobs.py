"""The RQ job and its callbacks: what they refuse, how they classify failures."""

from __future__ import annotations

import importlib
import json
from contextlib import closing
from datetime import UTC, datetime, timedelta
from types import SimpleNamespace

import msgpack
import pytest
import redis

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_batch
from hmcc_worker import jobs, rq_compat
from hmcc_worker.metrics import RedisJobMetrics
from hmcc_worker.outcomes import unpack, unpack_msgpack
from hmcc_worker.payload import encode_flight, encode_image
from hmcc_worker.pool import ComputePool
from hmcc_worker.protocol import (
    IMAGES_KEY,
    JOB_FUNCTION,
    ON_FAILURE,
    ON_SUCCESS,
    OUTCOMES_KEY,
    PAYLOAD_KEY,
    JobStatus,
)
from tests.support.answers import as_json
from tests.support.procs import redis_server


def test_the_allow_list_names_importable_functions() -> None:
    assert set(jobs.JOB_FUNCTIONS) == {JOB_FUNCTION, ON_FAILURE, ON_SUCCESS}
    for name, func in jobs.JOB_FUNCTIONS.items():
        module, _, attr = name.rpartition(".")
        assert getattr(importlib.import_module(module), attr) is func


def test_the_job_refuses_to_run_outside_a_worker() -> None:
    with pytest.raises(RuntimeError, match="outside an RQ worker"):
        jobs.verify_job()


@pytest.mark.parametrize(
    ("exc_type", "code"),
    [
        (jobs.PayloadExpired, "payload_expired"),
        (rq_compat.AbandonedJobError, "worker_lost"),
        (rq_compat.JobTimeoutException, "timeout"),
        (ValueError, "internal_error"),
        (None, "internal_error"),
    ],
)
def test_failures_are_classified_by_exception_type(exc_type: type | None, code: str) -> None:
    error = jobs.classify_failure(exc_type)
    assert error["code"] == code and error["message"]


@pytest.mark.procs
def test_the_compute_child_reads_verifies_and_stores_a_job_itself() -> None:
    """verify_stored runs in the child: it reads the payload and the batch's images from
    Redis, stores the outcomes and counts their metrics, and hands back only the counts of
    pairs and failed pairs; an expired payload is PayloadExpired on the worker's side of the
    process boundary (its failure code)."""
    pairs = [simulate_pair(SimulationOptions(n_inliers=60, outlier_ratio=0.3), s) for s in (0, 1)]
    flight = parse_batch(
        {
            "images": {"a": pairs[0]["image1"], "b": pairs[0]["image2"]},
            "plane": pairs[0]["plane"],
            "pairs": [
                {"id": f"p{k}", "image1": "a", "image2": "b"}
                | {key: p[key] for key in ("keypoints1", "keypoints2", "matches")}
                for k, p in enumerate(pairs)
            ],
        },
        max_pairs=2,
    )
    with redis_server() as srv, closing(ComputePool(1)) as pool:
        connection = redis.Redis.from_url(srv.url)
        connection.hset(
            IMAGES_KEY.format(batch_id="b1"),
            mapping={name: encode_image(image) for name, image in flight.images.items()},
        )
        connection.set(PAYLOAD_KEY.format(job_id="j1"), encode_flight(flight, images=False))

        counts = pool.call(jobs.verify_stored, srv.url, "j1", "b1", 60)

        stored = connection.lrange(OUTCOMES_KEY.format(job_id="j1"), 0, -1)
        assert [unpack(s)[0] for s in stored] == [JobStatus.finished] * 2
        expected = [flight.verify(i).inliers.tolist() for i in range(2)]
        assert [json.loads(unpack(s)[1])["inliers"] for s in stored] == expected
        # kept in MessagePack too, the inliers raw (what an Accept: msgpack answer splices in)
        packed = [msgpack.unpackb(unpack_msgpack(s)[1]) for s in stored]  # type: ignore[arg-type]
        assert [as_json(p)["inliers"] for p in packed] == expected
        assert counts == (2, 0)
        metrics = RedisJobMetrics(connection).snapshot()
        assert metrics.outcomes == {"finished": 2}
        assert metrics.stages["compute"][0][-1] == 2 and metrics.stages["compute"][1] > 0
        assert "job" not in metrics.stages  # the job's time is the worker's to count
        assert 0 < connection.ttl(OUTCOMES_KEY.format(job_id="j1")) <= 60

        with pytest.raises(jobs.PayloadExpired):
            pool.call(jobs.verify_stored, srv.url, "gone", "b1", 60)


@pytest.mark.procs  # a Redis server
def test_a_failed_attempt_is_counted_once_whoever_cleans_it_up() -> None:
    """The API's and every worker's registry cleanup can find the same dead worker's job at
    once, each calling the failure callback: the attempt counts once; its retry's failure (a
    new start) counts again."""
    with redis_server() as srv:
        connection = redis.Redis.from_url(srv.url)
        started = datetime(2026, 11, 26, 12, 0, tzinfo=UTC)
        job = SimpleNamespace(id="j1", meta={}, started_at=started, save_meta=lambda: None)
        for _ in range(2):  # the API and a worker, the same attempt
            jobs.on_job_failure(job, connection, rq_compat.AbandonedJobError, None, None)
        assert RedisJobMetrics(connection).snapshot().failures == {"AbandonedJobError": 1}
        assert job.meta["error"]["code"] == "worker_lost"
        job.started_at = started + timedelta(seconds=5)  # the retry
        jobs.on_job_failure(job, connection, rq_compat.AbandonedJobError, None, None)
        assert RedisJobMetrics(connection).snapshot().failures == {"AbandonedJobError": 2}


def test_a_records_times_read_as_rq_writes_them() -> None:
    """A job hash's times as RQ writes them come back as the same UTC time; unset, None."""
    from datetime import UTC, datetime, timedelta

    from rq.utils import str_to_date, utcformat

    at = datetime(2026, 11, 26, 16, 0, 1, 250000, tzinfo=UTC)
    assert rq_compat.record_time(utcformat(at).encode()) == at
    assert rq_compat.record_time(None) is None and rq_compat.record_time(b"") is None
    # RQ's own parser's answer, in every form it reads (the fast path takes RQ's usual one)
    for text in (utcformat(at), utcformat(at.replace(microsecond=0)), "2026-11-26T16:00:01Z"):
        read = rq_compat.record_time(text)
        assert read == str_to_date(text) and read is not None and read.utcoffset() == timedelta(0)


def test_the_image_cache_holds_a_bounded_number_of_bytes(monkeypatch: pytest.MonkeyPatch) -> None:
    """Images with descriptors are large: the decoded images a process keeps are bounded in
    bytes too (oldest out first), and a chunk whose own images pass the bound still gets them."""
    from tests.support.matching import matching_batch

    body, _ = matching_batch(0, n_inliers=60)
    flight = parse_batch(body, 10)
    blobs = {
        f"{name}{k}": encode_image(image) for k in range(4) for name, image in flight.images.items()
    }
    one = sum(a.nbytes for a in (flight.images["a"].keypoints, flight.images["a"].descriptors))

    class Store:
        def hmget(self, key: str, names: list[str]) -> list[bytes]:
            return [blobs[n] for n in names]

    monkeypatch.setattr(jobs, "_images", type(jobs._images)())
    monkeypatch.setattr(jobs, "_image_bytes", 0)
    monkeypatch.setattr(jobs, "_IMAGE_CACHE_BYTES", int(3.5 * one))
    names = sorted(blobs)
    got = jobs._fetch_images(Store(), "batch", names)
    assert sorted(got) == names
    assert len(jobs._images) == 3
    assert [n for _, n in jobs._images] == names[-3:]
    assert jobs._image_bytes <= 3.5 * one
