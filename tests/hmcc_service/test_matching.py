"""Batches whose pairs ask for matching, refused through the real app (in process): bad
descriptors (shape, dtype, rows, missing), a pair that both brings matches and asks for
matching, a batch without the ground's height: each a 422 naming the field, in JSON and in
MessagePack; and the bodies that are fine are accepted."""

from __future__ import annotations

import copy
from collections.abc import AsyncIterator, Callable
from typing import Any

import httpx
import msgpack
import numpy as np
import orjson
import pytest

from hmcc_service.app import create_app
from hmcc_service.settings import Settings
from tests.support.matching import json_ready, matching_batch, msgpack_ready

pytestmark = [pytest.mark.anyio, pytest.mark.usefixtures("hermetic_env")]

KINDS = {"json": "application/json", "msgpack": "application/vnd.hmcc+msgpack"}


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


@pytest.fixture
async def client() -> AsyncIterator[httpx.AsyncClient]:
    app = create_app(Settings())
    transport = httpx.ASGITransport(app=app)
    try:
        async with httpx.AsyncClient(transport=transport, base_url="http://hmcc.test") as c:
            yield c
    finally:
        await app.state.queue.close()


@pytest.fixture(scope="module")
def body() -> dict[str, Any]:
    return matching_batch(0, n_inliers=40)[0]


def _encode(body: dict[str, Any], kind: str) -> bytes:
    if kind == "json":
        return orjson.dumps(json_ready(body))
    return msgpack.packb(msgpack_ready(body))


async def _post(client: httpx.AsyncClient, body: dict[str, Any], kind: str) -> httpx.Response:
    return await client.post(
        "/v1/batches", content=_encode(body, kind), headers={"Content-Type": KINDS[kind]}
    )


def _fields(response: httpx.Response) -> list[str]:
    assert response.status_code == 422, response.text
    error = response.json()["error"]
    assert error["code"] == "invalid_input"
    return [i["field"] for i in error["issues"]]


def _edit(body: dict[str, Any], change: Callable[[dict[str, Any]], None]) -> dict[str, Any]:
    edited = copy.deepcopy(body)
    change(edited)
    return edited


def _rows(n: int) -> Callable[[dict[str, Any]], None]:
    def change(b: dict[str, Any]) -> None:
        b["images"]["a"]["descriptors"] = b["images"]["a"]["descriptors"][:n]

    return change


def _drop(key: str) -> Callable[[dict[str, Any]], None]:
    def change(b: dict[str, Any]) -> None:
        del b["images"]["b"][key]

    return change


def _set_pair(**fields: Any) -> Callable[[dict[str, Any]], None]:
    def change(b: dict[str, Any]) -> None:
        b["pairs"][0].update(fields)

    return change


def _narrow(b: dict[str, Any]) -> None:
    b["images"]["b"]["descriptors"] = b["images"]["b"]["descriptors"][:, :64]


def _no_ground(b: dict[str, Any]) -> None:
    b["plane"] = {"z": "auto"}


CASES: dict[str, tuple[Callable[[dict[str, Any]], None], str]] = {
    "fewer rows than keypoints": (_rows(10), "images.a.descriptors"),
    "descriptors missing": (_drop("descriptors"), "images.b.descriptors"),
    "keypoints missing": (_drop("keypoints"), "images.b.descriptors"),
    "matches and match": (_set_pair(matches=np.array([[0, 0]], np.int32)), "pairs[0]"),
    "own keypoints and match": (
        _set_pair(keypoints1=np.array([[1.0, 2.0]])),
        "pairs[0]",
    ),
    "neither matches nor match": (_set_pair(match=False), "pairs[0]"),
    "descriptors of two lengths": (_narrow, "pairs[0]"),
    "no ground height": (_no_ground, "plane"),
}


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("case", CASES)
async def test_bad_matching_input_is_422_naming_the_field(
    client: httpx.AsyncClient, body: dict[str, Any], case: str, kind: str
) -> None:
    change, field = CASES[case]
    assert field in _fields(await _post(client, _edit(body, change), kind))


async def test_a_descriptor_buffer_of_another_dtype_is_422_naming_it(
    client: httpx.AsyncClient, body: dict[str, Any]
) -> None:
    doc = msgpack_ready(body)
    d = body["images"]["a"]["descriptors"].astype("<f8")
    doc["images"]["a"]["descriptors"] = {
        "dtype": "<f8",
        "shape": list(d.shape),
        "data": d.tobytes(),
    }
    r = await client.post(
        "/v1/batches", content=msgpack.packb(doc), headers={"Content-Type": KINDS["msgpack"]}
    )
    assert _fields(r) == ["images.a.descriptors"]
    assert "'|u1'" in r.json()["error"]["message"]


@pytest.mark.parametrize(
    ("value", "field"),
    [
        ([[1, 2], [3]], "images.a.descriptors"),  # rows of two lengths
        ([[1e39] * 128] * 3, "images.a.descriptors"),  # beyond float32
        ([[1, 2]] * 3, "images.a.descriptors"),  # rows != keypoints
        ([1, 2, 3], "images.a.descriptors"),  # not rows
    ],
)
async def test_bad_json_descriptors_are_422_naming_the_field(
    client: httpx.AsyncClient, body: dict[str, Any], value: Any, field: str
) -> None:
    doc = json_ready(body)
    doc["images"]["a"]["descriptors"] = value
    r = await client.post(
        "/v1/batches", content=orjson.dumps(doc), headers={"Content-Type": KINDS["json"]}
    )
    assert any(f.startswith(field) for f in _fields(r)), r.text


@pytest.mark.parametrize("kind", KINDS)
async def test_a_matching_batch_is_accepted_and_existing_bodies_still_are(
    client: httpx.AsyncClient, body: dict[str, Any], kind: str
) -> None:
    """The pair that asks for matching, a pair with its own matches beside it (images with
    descriptors or not), and float32 descriptors: all accepted."""
    mixed = _edit(
        body,
        lambda b: b["pairs"].append(
            {"image1": "a", "image2": "b", "matches": np.array([[0, 1], [2, 3]], np.int32)}
        ),
    )
    for doc in (body, mixed):
        r = await _post(client, doc, kind)
        assert r.status_code in (200, 202), r.text

    def floats(b: dict[str, Any]) -> None:
        for image in b["images"].values():
            image["descriptors"] = image["descriptors"].astype(np.float32) / 3.0

    r = await _post(client, _edit(body, floats), kind)
    assert r.status_code in (200, 202), r.text


@pytest.mark.parametrize("kind", KINDS)
async def test_an_image_without_a_pose_needs_a_method_that_ignores_poses(
    client: httpx.AsyncClient, body: dict[str, Any], kind: str
) -> None:
    """Without a pose: 422 naming the image's pose with the default method (it uses the
    poses), accepted with an estimator."""
    unposed = _edit(body, lambda b: b["images"]["b"].pop("pose"))
    assert _fields(await _post(client, unposed, kind)) == ["images.b.pose"]
    unposed["method"] = "ransac"
    r = await _post(client, unposed, kind)
    assert r.status_code in (200, 202), r.text
