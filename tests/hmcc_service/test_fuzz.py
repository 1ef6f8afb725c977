"""Property-based fuzzing of every operation (schemathesis) against the app's own OpenAPI
document, in-process over ASGI with the embedded queue: valid and invalid requests alike never
get a 5xx, and every response matches what the document promises (status code, content type,
headers, body schema). Derandomized and bounded, so CI sees the same cases every run.

Generated bodies are practically never valid pairs (match indices must fit the keypoints), so
the success path - finished and failed jobs, batch pages - is checked with explicit cases."""

from __future__ import annotations

import time
from typing import Any

import msgpack
import pytest
import schemathesis
from fastapi import FastAPI
from hypothesis import HealthCheck, settings
from schemathesis.checks import (
    content_type_conformance,
    not_a_server_error,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_service.app import create_app
from hmcc_service.settings import Settings

pytestmark = pytest.mark.procs  # the app's lifespan starts its compute children


def new_app() -> FastAPI:
    """The app under the field defaults of the settings, whatever the environment says (no
    REDIS_URL: the embedded queue; no HMCC_API_KEY: the /v1 routes are reachable)."""
    return create_app(Settings.model_construct())


@schemathesis.serializer("application/vnd.hmcc+msgpack")
def _messagepack(ctx: Any, value: Any) -> bytes:
    """Generated bodies in the API's binary encoding too (arrays as plain lists; integers
    MessagePack cannot hold become floats)."""
    return bytes(msgpack.packb(_fits(value)))


def _fits(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _fits(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_fits(v) for v in value]
    if isinstance(value, int) and not isinstance(value, bool) and not -(2**63) <= value < 2**64:
        return float(value)
    return value


#: An explicit config: no schemathesis.toml found on disk can change what runs.
schema = schemathesis.openapi.from_asgi("/openapi.json", new_app(), config=schemathesis.Config())

CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
]


@pytest.fixture
def app() -> FastAPI:
    """A fresh app per test: schemathesis ends the ASGI lifespan after each test, and the
    app's lifespan closes its queue for good."""
    return new_app()


@schema.parametrize()
@settings(
    max_examples=40,
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[
        HealthCheck.too_slow,
        HealthCheck.filter_too_much,
        HealthCheck.function_scoped_fixture,
    ],
)
def test_operation_never_fails_server_side(app: FastAPI, case: schemathesis.Case) -> None:
    """No 5xx, and the response conforms to the document."""
    case.call_and_validate(checks=CHECKS, app=app)


# --------------------------------------------------------------------------- success path


def call(app: FastAPI, operation_id: str, **kwargs: Any) -> Any:
    """An explicit case of one operation, sent and checked like the generated ones."""
    if "body" in kwargs:
        kwargs["media_type"] = "application/json"
    case = schema.find_operation_by_id(operation_id).Case(**kwargs)
    return case.call_and_validate(checks=CHECKS, app=app).json()


@pytest.fixture(scope="module")
def images() -> dict[str, Any]:
    """A valid pair (small simulation) whose images are ``a`` and ``b``; image ``far`` gives
    its position as lat/lon, so a pair of ``a`` and ``far`` passes the schema but fails in
    the job (positions given two ways)."""
    pair = simulate_pair(SimulationOptions(n_inliers=20), seed=1)
    far = {
        **pair["image2"],
        "pose": {**pair["image2"]["pose"], "position": {"lat": 45.0, "lon": 7.0, "alt": 500.0}},
    }
    points = {k: pair[k] for k in ("keypoints1", "keypoints2", "matches")}
    return {"a": pair["image1"], "b": pair["image2"], "far": far, "points": points}


@pytest.mark.parametrize(("second", "status"), [("b", "finished"), ("far", "failed")])
def test_verification_lifecycle_conforms(
    app: FastAPI, images: dict[str, Any], second: str, status: str
) -> None:
    """Submit (long poll), read and try to cancel a job that ends finished or failed."""
    body = {"image1": images["a"], "image2": images[second], **images["points"]}
    job = call(app, "submit_verification", body=body, query={"wait": 30})
    assert job["status"] == status, job
    assert (job["result"] is None) is (status == "failed")
    path = {"job_id": job["job_id"]}
    assert call(app, "get_verification", path_parameters=path) == job
    refused = call(app, "cancel_verification", path_parameters=path)
    assert refused["error"]["code"] == "not_cancelable"


def test_batch_lifecycle_conforms(app: FastAPI, images: dict[str, Any]) -> None:
    """Submit a batch of a good and a failing pair; its pages once it has finished."""
    pairs = [
        {"id": f"p{i}", "image1": "a", "image2": second, **images["points"]}
        for i, second in enumerate(("b", "far"))
    ]
    body = {"images": {k: images[k] for k in ("a", "b", "far")}, "pairs": pairs}
    batch = call(app, "submit_batch", body=body)
    path = {"batch_id": batch["batch_id"]}
    deadline = time.monotonic() + 30
    while (view := call(app, "get_batch", path_parameters=path))["status"] != "finished":
        assert time.monotonic() < deadline, view
        time.sleep(0.05)
    assert [(r["id"], r["status"]) for r in view["results"]] == [
        ("p0", "finished"),
        ("p1", "failed"),
    ]
    second_page = call(app, "get_batch", path_parameters=path, query={"offset": 1, "limit": 1})
    assert [r["index"] for r in second_page["results"]] == [1]
    assert second_page["next_offset"] is None


def test_pairs_conform(app: FastAPI, images: dict[str, Any]) -> None:
    """The pairs of the simulated pair's two images (they overlap), and a 422."""
    body = {"images": {k: images[k] for k in ("a", "b")}, "flying_height": 300.0}
    chosen = call(app, "choose_pairs", body={**body, "params": {"min_overlap": 0.0}})
    assert [(p["image1"], p["image2"]) for p in chosen["pairs"]] == [("a", "b")]
    refused = call(app, "choose_pairs", body={**body, "ground_z": 0.0})
    assert refused["error"]["code"] == "invalid_input"
