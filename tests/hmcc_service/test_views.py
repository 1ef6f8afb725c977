"""Queue records -> the API's answers: statuses, timestamps, timings, outcomes spliced in as
they were stored, expired results, and a batch's counts per state. Records built by hand."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any

import msgpack
import orjson
import pytest

from hmcc_schema.parse import JSON, MSGPACK
from hmcc_service.queue import JobRecord
from hmcc_service.views import (
    ITEM_STATUSES,
    answer_type,
    batch_counts,
    batch_item,
    batch_item_msgpack,
    batch_page_msgpack,
    job_view,
    job_view_msgpack,
)
from hmcc_worker.outcomes import PairOutcome
from hmcc_worker.protocol import JobKind, JobStatus
from tests.support.answers import as_json

T0 = datetime(2024, 5, 1, 12, 0, 0, 250000, tzinfo=UTC)
RESULT = b'{"inliers":[0,2,5],"model":{"F":[1.5,2.5]}}'
ERROR = b'{"code":"invalid_input","message":"too few matches"}'


def _record(status: JobStatus, **fields: Any) -> JobRecord:
    return JobRecord(job_id="job-1", kind=JobKind.pair, status=status, submitted_at=T0, **fields)


def _finished(**fields: Any) -> JobRecord:
    return _record(
        JobStatus.finished,
        started_at=T0 + timedelta(milliseconds=1500),
        finished_at=T0 + timedelta(milliseconds=1750),
        **fields,
    )


def test_item_statuses_are_the_job_statuses_and_expired() -> None:
    assert ITEM_STATUSES == ("queued", "started", "finished", "failed", "canceled", "expired")


def test_a_queued_job_has_no_times_but_its_submission_and_no_timings() -> None:
    view = orjson.loads(job_view(_record(JobStatus.queued), None))
    assert view == {
        "job_id": "job-1",
        "status": "queued",
        "submitted_at": "2024-05-01T12:00:00.250000Z",
        "started_at": None,
        "finished_at": None,
        "timings_ms": {"queue_wait": None, "run": None, "turnaround": None},
        "result": None,
        "error": None,
    }


def test_a_started_job_has_its_queue_wait_only() -> None:
    record = _record(JobStatus.started, started_at=T0 + timedelta(seconds=2))
    view = orjson.loads(job_view(record, None))
    assert view["status"] == "started"
    assert view["started_at"] == "2024-05-01T12:00:02.250000Z"
    assert view["timings_ms"] == {"queue_wait": 2000.0, "run": None, "turnaround": None}


def test_a_finished_job_answers_its_stored_result_as_it_is() -> None:
    view_bytes = job_view(_finished(), b"r" + RESULT)
    assert RESULT in view_bytes  # spliced, not re-encoded
    view = orjson.loads(view_bytes)
    assert view["status"] == "finished"
    assert view["result"] == orjson.loads(RESULT)
    assert view["error"] is None
    assert view["finished_at"] == "2024-05-01T12:00:02Z"
    assert view["timings_ms"] == pytest.approx(
        {"queue_wait": 1500.0, "run": 250.0, "turnaround": 1750.0}
    )


def test_a_finished_job_whose_pair_failed_answers_failed_with_the_stored_error() -> None:
    view = orjson.loads(job_view(_finished(failed=1), b"e" + ERROR))
    assert view["status"] == "failed"
    assert view["result"] is None
    assert view["error"] == orjson.loads(ERROR)


def test_a_failed_job_answers_the_error_of_its_record() -> None:
    error = {"code": "worker_lost", "message": "the worker verifying it was lost"}
    record = _record(JobStatus.failed, started_at=T0, finished_at=T0, error=error)
    view = orjson.loads(job_view(record, None))
    assert view["status"] == "failed"
    assert view["error"] == error
    assert view["result"] is None


def test_a_canceled_job_answers_canceled() -> None:
    view = orjson.loads(job_view(_record(JobStatus.canceled), None))
    assert view["status"] == "canceled"
    assert view["result"] is None and view["error"] is None


def test_timings_are_never_negative() -> None:
    """Clocks of different machines may disagree: a start before the submission is 0 ms."""
    record = _record(
        JobStatus.finished,
        started_at=T0 - timedelta(milliseconds=30),
        finished_at=T0 + timedelta(milliseconds=100),
    )
    timings = orjson.loads(job_view(record, b"r" + RESULT))["timings_ms"]
    assert timings["queue_wait"] == 0.0
    assert timings["run"] == pytest.approx(130.0)
    assert timings["turnaround"] == pytest.approx(100.0)


@pytest.mark.parametrize("us", [15, 36, 12_301, 12_300_113, 3_000_000_003, 1])
def test_timings_carry_no_float_noise(us: int) -> None:
    """The times hold microseconds: 0.015 ms reads 0.015, not 0.015000000000000001, in the JSON
    the API answers (both queues' records go through here)."""
    record = _record(
        JobStatus.finished,
        started_at=T0 + timedelta(microseconds=us),
        finished_at=T0 + timedelta(microseconds=2 * us),
    )
    text = job_view(record, b"r" + RESULT).decode()
    timings = orjson.loads(text)["timings_ms"]
    assert timings == {"queue_wait": us / 1e3, "run": us / 1e3, "turnaround": 2 * us / 1e3}
    for value in timings.values():
        assert f'":{value!r}' in text
        assert len(repr(value).partition(".")[2]) <= 3, value


def test_batch_items_map_records_and_outcomes_to_statuses() -> None:
    items = [
        batch_item(0, "a", _finished(), b"r" + RESULT),
        batch_item(1, "b", _finished(failed=1), b"e" + ERROR),
        batch_item(2, None, _record(JobStatus.queued), None),
        batch_item(3, "d", None, None),  # the chunk's record is gone
        batch_item(4, "e", _finished(), None),  # its outcome is gone
        batch_item(5, "f", _record(JobStatus.started, started_at=T0), None),
    ]
    answer = orjson.loads(orjson.dumps(items))
    assert [(i["index"], i["id"], i["status"]) for i in answer] == [
        (0, "a", "finished"),
        (1, "b", "failed"),
        (2, None, "queued"),
        (3, "d", "expired"),
        (4, "e", "expired"),
        (5, "f", "started"),
    ]
    assert answer[0]["result"] == orjson.loads(RESULT) and answer[0]["error"] is None
    assert answer[1]["error"] == orjson.loads(ERROR) and answer[1]["result"] is None
    assert all(i["result"] is None and i["error"] is None for i in answer[2:])


def test_a_batch_item_of_a_failed_chunk_carries_the_chunk_error() -> None:
    error = {"code": "input_expired", "message": "the batch's input is no longer kept"}
    item = batch_item(7, "x", _record(JobStatus.failed, error=error), None)
    assert item["status"] == "failed"
    assert item["error"] == error
    assert item["result"] is None


def test_batch_counts_count_the_pairs_of_each_chunk_by_state() -> None:
    chunks = [{"count": n} for n in (4, 4, 3, 2, 5, 1, 2)]
    records: list[JobRecord | None] = [
        _finished(pairs=4, failed=1),  # 3 finished, 1 failed
        _finished(pairs=4),  # failed unknown: all finished
        _record(JobStatus.failed, pairs=3),  # the chunk failed: all its pairs did
        _record(JobStatus.queued, pairs=2),
        _record(JobStatus.started, pairs=5),
        _record(JobStatus.canceled, pairs=1),
        None,  # the record is gone
    ]
    counts = batch_counts(chunks, records)
    assert counts == {
        "queued": 2,
        "started": 5,
        "finished": 7,
        "failed": 4,
        "canceled": 1,
        "expired": 2,
    }
    assert sum(counts.values()) == sum(c["count"] for c in chunks)


def test_batch_counts_of_no_chunks_are_all_zero() -> None:
    assert batch_counts([], []) == dict.fromkeys(ITEM_STATUSES, 0)


def test_batch_counts_need_one_record_per_chunk() -> None:
    with pytest.raises(ValueError):
        batch_counts([{"count": 1}, {"count": 2}], [None])


@pytest.mark.parametrize(
    "accept, expected",
    [
        (None, JSON),
        ("", JSON),
        ("application/json", JSON),
        ("text/html", JSON),  # cannot be served: JSON, as before (no 406)
        ("*/*", JSON),
        (MSGPACK, MSGPACK),
        (MSGPACK.upper(), MSGPACK),
        (f"{MSGPACK}, application/json;q=0.9", MSGPACK),
        (f"application/json, {MSGPACK}", MSGPACK),  # named as high as JSON
        (f"application/json;q=0.5, {MSGPACK};q=0.6", MSGPACK),
        (f"application/json, {MSGPACK};q=0.5", JSON),
        (f"*/*, {MSGPACK};q=0.5", JSON),
        (f"{MSGPACK};q=0", JSON),
        (f"{MSGPACK};q=nonsense", JSON),
        (f"{MSGPACK}x", JSON),
        (f"{MSGPACK} ; q=1 ; charset=x", MSGPACK),
    ],
)
def test_answer_type_reads_accept(accept: str | None, expected: str) -> None:
    assert answer_type(accept) == expected


def _json_form(packed: bytes) -> Any:
    return as_json(msgpack.unpackb(packed))


def _json_view(record: JobRecord, stored: bytes | None) -> Any:
    return orjson.loads(job_view(record, stored))


@pytest.mark.parametrize(
    "record, stored",
    [
        (_record(JobStatus.queued), None),
        (_finished(), b"r" + RESULT),  # a result stored as JSON only: converted
        (_finished(failed=1), b"e" + ERROR),
        (_record(JobStatus.failed, error={"code": "worker_lost", "message": "lost"}), None),
        (_record(JobStatus.canceled), None),
    ],
)
def test_a_job_in_messagepack_has_the_json_fields(record: JobRecord, stored: bytes | None) -> None:
    assert _json_form(job_view_msgpack(record, stored)) == _json_view(record, stored)


def test_a_result_stored_in_both_forms_is_spliced_in_as_it_is() -> None:
    arrays = {"dtype": "<i4", "shape": [2], "data": b"\x00\x00\x00\x00\x02\x00\x00\x00"}
    packed = msgpack.packb({"inliers": arrays, "model": {"F": [1.5, 2.5]}})
    stored = PairOutcome(JobStatus.finished, RESULT, msgpack=packed).pack()
    assert packed in job_view_msgpack(_finished(), stored)
    assert RESULT in job_view(_finished(), stored)
    item = batch_item_msgpack(0, "a", _finished(), stored)
    assert packed in b"".join(item)


def test_a_page_in_messagepack_has_the_json_fields_in_order() -> None:
    cases = [
        (0, "a", _finished(), b"r" + RESULT),
        (1, "b", _finished(failed=1), b"e" + ERROR),
        (2, None, _record(JobStatus.queued), None),
        (3, "d", None, None),
        (4, "e", _finished(), None),
    ]
    for n in (0, 5, 20, 70_000):  # map and array headers of each size class
        items = [cases[k % len(cases)] for k in range(n)]
        view = {"batch_id": "b", "total": n, "limit": n, "results": None}
        pack = msgpack.Packer().pack
        page = batch_page_msgpack(view, [batch_item_msgpack(*c, pack=pack) for c in items])
        decoded = msgpack.unpackb(page)
        assert list(decoded) == list(view)
        expected = orjson.loads(orjson.dumps([batch_item(*c) for c in items]))
        assert as_json(decoded["results"]) == expected
