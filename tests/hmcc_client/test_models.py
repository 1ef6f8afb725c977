"""The client's answers and names agree with the server's: the dataclasses of
``hmcc_client.models`` have the fields of ``hmcc_service.models`` (the OpenAPI document's),
the statuses are the protocol's, the media types those ``hmcc_schema.parse`` reads."""

from __future__ import annotations

import dataclasses
import typing

import numpy as np
import pytest
from pydantic import BaseModel

import hmcc_client
import hmcc_service.models as server
from hmcc_client import models as client
from hmcc_schema import parse
from hmcc_worker import protocol

PAIRS: list[tuple[type, type[BaseModel]]] = [
    (client.Issue, server.Issue),
    (client.ErrorBody, server.ErrorBody),
    (client.FittedModel, server.FittedModel),
    (client.Stage, server.Stage),
    (client.VerificationResult, server.VerificationResult),
    (client.JobTimings, server.JobTimings),
    (client.Job, server.JobView),
    (client.BatchItem, server.BatchItem),
    (client.Batch, server.BatchView),
    (client.Limits, server.Limits),
    (client.ChosenPair, server.ChosenPair),
    (client.Pairs, server.PairsView),
]


@pytest.mark.parametrize("ours, theirs", PAIRS, ids=[p[0].__name__ for p in PAIRS])
def test_each_answer_has_the_servers_fields(ours: type, theirs: type[BaseModel]) -> None:
    fields = {f.name for f in dataclasses.fields(ours) if not f.name.startswith("_")}
    assert fields == set(theirs.model_fields)
    required = {
        f.name
        for f in dataclasses.fields(ours)
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    }
    # what the server may leave out, the client does not require
    assert required <= {name for name, f in theirs.model_fields.items() if f.is_required()}


def test_statuses_and_names_are_the_servers() -> None:
    assert set(typing.get_args(client.JobStatus)) == {s.value for s in protocol.JobStatus}
    assert set(typing.get_args(client.ItemStatus)) == {s.value for s in protocol.ItemStatus}
    assert set(typing.get_args(client.BatchStatus)) == {s.value for s in protocol.BatchStatus}
    assert client.TERMINAL == {s.value for s in protocol.TERMINAL}
    assert client.MAX_WAIT_S == server.MAX_WAIT_S
    assert (hmcc_client.JSON, hmcc_client.MSGPACK) == (parse.JSON, parse.MSGPACK)


def test_a_result_keeps_the_json_it_was_read_from() -> None:
    doc = {
        "method": "hmcc",
        "inliers": [0, 2],
        "model": {"type": None, "matrix": None},
        "timings_ms": {"total": 1.5},
        "future_key": 1,
    }
    result = client.VerificationResult.from_json(doc)
    assert result.inliers.tolist() == [0, 2] and result.inliers.dtype == np.int64
    assert (result.model.type, result.stages) == (None, None)
    assert result.to_dict() == doc
    job = client.Job.from_json(
        {"job_id": "j", "status": "finished", "submitted_at": "2024-01-01T00:00:00Z"}
    )
    assert job.done and job.submitted_at.tzinfo is not None and job.timings_ms.run is None


def test_a_result_with_raw_arrays_equals_its_json_form() -> None:
    """MessagePack answers carry ``inliers`` and ``matches`` as raw buffers: read as the same
    int64 arrays as from JSON, and :meth:`to_dict` gives the JSON object again."""
    matches = np.array([[0, 5], [1, 7], [70_000, 2]], dtype="<i4")
    inliers = np.array([0, 2], dtype="<i4")

    def raw(a: np.ndarray) -> dict[str, object]:
        return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}

    doc = {
        "method": "hmcc",
        "matches": matches.tolist(),
        "inliers": inliers.tolist(),
        "model": {"type": None, "matrix": None},
        "timings_ms": {"total": 1.5},
    }
    binary = client.VerificationResult.from_json(
        {**doc, "matches": raw(matches), "inliers": raw(inliers)}
    )
    plain = client.VerificationResult.from_json(doc)
    assert binary == plain and binary.to_dict() == doc
    assert binary.matches is not None and binary.matches.shape == (3, 2)
    assert binary.inliers.dtype == binary.matches.dtype == np.int64
    assert binary.matches[binary.inliers].tolist() == [[0, 5], [70_000, 2]]
    assert binary != client.VerificationResult.from_json({**doc, "inliers": [0, 1]})
