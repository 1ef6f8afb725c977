"""Each pair's outcome: encoded once, input problems and bugs as outcomes of their own pair."""

from __future__ import annotations

import json

import msgpack
import orjson
import pytest

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_schema import parse_batch, parse_pair
from hmcc_worker.outcomes import (
    crashed,
    encode_result,
    timed_out,
    unpack,
    unpack_msgpack,
    verify_flight,
    verify_flight_lean,
    verify_flight_lines,
)
from hmcc_worker.protocol import JobStatus
from tests.support.answers import as_json


def _pair(seed: int = 0) -> dict:
    pair = simulate_pair(SimulationOptions(n_inliers=80, outlier_ratio=0.4), seed)
    pair.pop("ground_truth")
    return pair


def test_a_finished_outcome_is_the_core_result_as_json() -> None:
    pair = _pair()
    flight = parse_pair(pair)
    (outcome,) = verify_flight(flight)
    assert outcome.status is JobStatus.finished
    status, body = unpack(outcome.pack())
    assert status is JobStatus.finished
    result = json.loads(body)
    expected = flight.verify(0).to_dict()
    assert result["inliers"] == expected["inliers"]
    assert set(result) == set(expected)
    timings = result["timings_ms"]
    assert timings["total"] == pytest.approx(sum(s["time_ms"] for s in result["stages"]))
    assert outcome.timings_ms["compute"] == pytest.approx(
        sum(v for k, v in outcome.timings_ms.items() if k != "compute")
    )


def test_the_lean_form_holds_inliers_model_and_total_time() -> None:
    pair = _pair()
    pair["params"] = {"result": "inliers"}
    (outcome,) = verify_flight(parse_pair(pair))
    result = orjson.loads(unpack(outcome.pack())[1])
    assert set(result) == {"method", "inliers", "model", "timings_ms"}
    assert set(result["timings_ms"]) == {"total"}
    assert outcome.timings_ms["compute"] > 0  # the metrics still see every stage


def _batch(n: int, short: int) -> tuple[list[dict], dict]:
    """``n`` simulated pairs as a batch of two images, pair ``short`` with too few matches
    for F (the core refuses it)."""
    pairs = [_pair(seed) for seed in range(n)]
    images = {"a": pairs[0]["image1"], "b": pairs[0]["image2"]}
    batch = {
        "images": images,
        "plane": pairs[0]["plane"],
        "pairs": [
            {
                "image1": "a",
                "image2": "b",
                "keypoints1": p["keypoints1"],
                "keypoints2": p["keypoints2"],
                "matches": p["matches"],
            }
            for p in pairs
        ],
    }
    batch["pairs"][short]["matches"] = batch["pairs"][short]["matches"][:5]
    return pairs, batch


def test_a_chunk_keeps_order_and_isolates_failures() -> None:
    pairs, batch = _batch(3, short=1)
    images = batch["images"]
    outcomes = verify_flight(parse_batch(json.dumps(batch), 100))
    assert [o.status for o in outcomes] == ["finished", "failed", "finished"]
    error = json.loads(unpack(outcomes[1].pack())[1])
    assert error["code"] == "invalid_input" and error["issues"][0]["field"] == "matches"
    assert error["issues"][0]["reason"] == "5 matches; a fundamental model needs 8"
    same = dict(pairs[2], image1=images["a"], image2=images["b"], plane=pairs[0]["plane"])
    alone = parse_pair(same).verify(0).to_dict()["inliers"]
    assert json.loads(unpack(outcomes[2].pack())[1])["inliers"] == alone


def test_flight_lines_come_in_runs_of_one_status_in_order() -> None:
    # hmcc flight's lines: consecutive pairs of one status joined in one outcome (the
    # process collecting them unpickles and writes a few bytes objects, not one a pair)
    _, batch = _batch(4, short=1)
    flight = parse_batch(json.dumps(batch), 100)
    runs = verify_flight_lines(flight)
    assert [run.status for run in runs] == ["finished", "failed", "finished"]
    assert [run.body.count(b"\n") for run in runs] == [1, 1, 2]
    docs = [json.loads(line) for run in runs for line in run.body.splitlines()]
    assert [doc["index"] for doc in docs] == [0, 1, 2, 3]
    assert [doc["status"] for doc in docs] == ["finished", "failed", "finished", "finished"]
    assert [doc["id"] for doc in docs] == [pair.id for pair in flight.pairs]
    for i in (0, 2, 3):
        assert docs[i]["result"]["inliers"] == flight.verify(i).inliers.tolist()
    assert docs[1]["error"]["code"] == "invalid_input"


def test_lost_pairs_say_how() -> None:
    segv = json.loads(crashed(-11).body)
    assert segv == {
        "code": "worker_crashed",
        "message": "the process verifying this pair was killed by SIGSEGV; the pair is not "
        "retried (the service goes on)",
    }
    assert "exited with status 3" in json.loads(crashed(3).body)["message"]
    late = json.loads(timed_out(60).body)
    assert late["code"] == "timeout" and "60 s" in late["message"]


def test_a_matched_pairs_outcome_holds_its_matches_and_times_the_matcher() -> None:
    """A pair that asked for matching: the JSON holds the matches and the matcher's figures,
    and the metrics' timings count the matcher (``match``) in the compute time."""
    from tests.support.matching import matching_batch

    flight = parse_batch(matching_batch(0, n_inliers=60)[0], 10)
    (outcome,) = verify_flight(flight)
    assert outcome.status is JobStatus.finished
    result = json.loads(unpack(outcome.pack())[1])
    assert result["matches"] and max(result["inliers"]) < len(result["matches"])
    assert outcome.timings_ms["match"] == result["matching"]["time_ms"]
    assert outcome.timings_ms["compute"] == pytest.approx(
        sum(v for k, v in outcome.timings_ms.items() if k != "compute")
    )


@pytest.mark.parametrize("form", ["full", "inliers"])
def test_a_kept_result_is_stored_in_both_forms_with_the_same_fields(form: str) -> None:
    """The service keeps a result as JSON and as MessagePack: the same fields in the same
    order, the arrays raw ``<i4`` buffers of the JSON's numbers; an error is JSON only."""
    pair = _pair(seed=3)
    pair["params"] = {"result": form}
    (outcome,) = verify_flight(parse_pair(pair))
    stored = outcome.pack()
    status, body = unpack(stored)
    assert status is JobStatus.finished
    assert unpack_msgpack(stored)[0] is JobStatus.finished
    packed = unpack_msgpack(stored)[1]
    assert packed is not None
    result, binary = orjson.loads(body), msgpack.unpackb(packed)
    assert list(binary) == list(result)
    assert binary["inliers"]["dtype"] == "<i4" and binary["inliers"]["shape"] == [
        len(result["inliers"])
    ]
    assert as_json(binary) == result
    failed = crashed(-11).pack()
    assert unpack(failed)[0] is JobStatus.failed and unpack_msgpack(failed)[1] is None


def test_a_matched_pairs_kept_result_carries_its_matches_raw() -> None:
    from tests.support.matching import matching_batch

    flight = parse_batch(matching_batch(0, n_inliers=60)[0], 10)
    (outcome,) = verify_flight(flight)
    packed = unpack_msgpack(outcome.pack())[1]
    assert packed is not None
    binary, result = msgpack.unpackb(packed), orjson.loads(unpack(outcome.pack())[1])
    matches = binary["matches"]
    assert matches["shape"] == [len(result["matches"]), 2]
    assert as_json(binary) == result


def test_a_result_decoded_from_json_encodes_as_the_worker_does() -> None:
    """The API's path for a result stored as JSON only (:func:`encode_result` on the parsed
    JSON) gives what the worker stores."""
    (outcome,) = verify_flight(parse_pair(_pair(seed=4)))
    assert encode_result(orjson.loads(outcome.body)) == outcome.msgpack
    lean = verify_flight_lean(parse_pair(_pair(seed=4)))[0]
    assert lean.msgpack is None and lean.pack()[:1] == b"r"  # what hmcc flight keeps: JSON
