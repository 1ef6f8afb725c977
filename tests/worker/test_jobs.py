"""The job functions: JSON in, JSON-ready outcome out; input problems are outcomes."""

from __future__ import annotations

import json
from typing import Any

import pytest

from hmcc.schema import BatchRequest, PairRequest
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_worker import jobs


def _pair(seed: int = 0) -> dict[str, Any]:
    pair = simulate_pair(SimulationOptions(n_inliers=80, outlier_ratio=0.4), seed)
    pair.pop("ground_truth")
    return pair


def test_run_pair_gives_the_same_result_from_text_or_model() -> None:
    pair = _pair()
    from_text = jobs.run_pair(json.dumps(pair))
    from_model = jobs.run_pair(PairRequest.model_validate(pair))
    assert from_text["status"] == from_model["status"] == "finished"
    assert from_text["result"]["inliers"] == from_model["result"]["inliers"]
    timings = from_text["result"]["timings_ms"]
    assert "total" not in timings  # the service adds its own total
    assert timings["job"] >= timings["compute"] > 0
    json.dumps(from_text)  # JSON-ready


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda p: p.update(matches=p["matches"][:4]), "matches"),  # core: too few for F
        (lambda p: p.update(method="nope"), "method"),  # schema
        (lambda p: p["keypoints1"].__setitem__(0, [1.0]), "keypoints1[0]"),
    ],
)
def test_bad_input_is_a_failed_outcome_naming_the_field(edit: Any, field: str) -> None:
    pair = _pair()
    edit(pair)
    outcome = jobs.run_pair(json.dumps(pair))
    assert outcome["status"] == "failed"
    assert outcome["error"]["code"] == "invalid_input"
    assert outcome["error"]["issues"][0]["field"] == field
    assert field in outcome["error"]["message"]


def test_run_chunk_keeps_order_and_isolates_failures() -> None:
    pairs = [_pair(seed) for seed in range(3)]
    images = {"a": pairs[0]["image1"], "b": pairs[0]["image2"]}
    chunk = {
        "images": images,
        "plane": pairs[0]["plane"],
        "pairs": [
            {"image1": "a", "image2": "b", "keypoints1": p["keypoints1"],
             "keypoints2": p["keypoints2"], "matches": p["matches"]}
            for p in pairs
        ],
    }
    chunk["pairs"][1]["matches"] = chunk["pairs"][1]["matches"][:3]
    outcomes = jobs.run_chunk(json.dumps(chunk))
    assert [o["status"] for o in outcomes] == ["finished", "failed", "finished"]
    same = dict(pairs[2], image1=images["a"], image2=images["b"], plane=pairs[0]["plane"])
    assert outcomes[2]["result"]["inliers"] == jobs.run_pair(json.dumps(same))["result"]["inliers"]
    parsed = jobs.run_chunk(BatchRequest.model_validate(chunk))
    assert [o["status"] for o in parsed] == ["finished", "failed", "finished"]
    assert parsed[0]["result"]["inliers"] == outcomes[0]["result"]["inliers"]


def test_a_chunk_that_is_not_a_batch_raises() -> None:
    with pytest.raises(ValueError):
        jobs.run_chunk('{"pairs": 3}')


def test_the_allow_list_names_importable_functions() -> None:
    import importlib

    for name, func in jobs.JOB_FUNCTIONS.items():
        module, _, attr = name.rpartition(".")
        assert getattr(importlib.import_module(module), attr) is func


def test_rq_entry_points_refuse_to_run_outside_a_worker() -> None:
    with pytest.raises(RuntimeError, match="outside an RQ worker"):
        jobs.verify_pair_job()


def test_warm_up_runs() -> None:
    jobs.warm_up()
