"""``POST /v1/pairs`` in process (``httpx.ASGITransport``): the answer is the library's
choice, the options and the ground change it as documented, bad input is a 422 naming the
field. Real HTTP: ``tests/hmcc_client/test_client.py``."""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Any

import httpx
import msgpack
import pytest

from hmcc.footprint import PairOptions
from hmcc_schema import parse_pairs
from hmcc_service.app import create_app
from hmcc_service.routes import pairs as route
from hmcc_service.settings import Settings

pytestmark = [pytest.mark.anyio, pytest.mark.usefixtures("hermetic_env")]

#: 4000 x 3000 px at f = 3000 px, 100 m up: 133.3 x 100 m of ground.
CAMERA = {"width": 4000, "height": 3000, "focal": 3000.0}


def grid_images(
    strips: int = 3, per_strip: int = 5, along: float = 50.0, across: float = 75.0
) -> dict[str, Any]:
    """Nadir images on strips flown east (yaw 90: the image top east, its 133 m side
    north-south): ``along`` m apart (1 - 50/100 = half a footprint, and a little more at
    49 m), strips ``across`` m apart (1 - 75/133 = 0.44 overlap)."""
    return {
        f"s{s}-{i}": {
            "camera": CAMERA,
            "pose": {
                "position": {"x": along * i, "y": across * s, "z": 100.0},
                "attitude": {"yaw": 90.0, "pitch": 0.0, "roll": 0.0},
            },
        }
        for s in range(strips)
        for i in range(per_strip)
    }


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


async def test_the_answer_is_the_librarys_choice(client: httpx.AsyncClient) -> None:
    body = {"images": grid_images(along=49.0), "ground_z": 0.0}
    r = await client.post("/v1/pairs", json=body)
    assert r.status_code == 200, r.text
    doc = r.json()
    expected = parse_pairs(body).choose()
    assert [(p["image1"], p["image2"]) for p in doc["pairs"]] == [p[:2] for p in expected.pairs]
    assert [p["overlap"] for p in doc["pairs"]] == pytest.approx([p[2] for p in expected.pairs])
    # 49 m along a 100 m footprint: 0.51 with the next image, nothing across (0.44)
    assert {(p["image1"], p["image2"]) for p in doc["pairs"]} == {
        (f"s{s}-{i}", f"s{s}-{i + 1}") for s in range(3) for i in range(4)
    }
    assert doc["images"] == 15 and doc["ground"] == {"ground_z": 0.0}
    assert doc["params"]["min_overlap"] == 0.5 and doc["params"]["min_partners"] == 0
    assert doc["timings_ms"]["total"] > 0


async def test_options_and_the_ground_change_the_pairs(client: httpx.AsyncClient) -> None:
    images = grid_images(along=49.0)

    async def pairs(**extra: Any) -> set[tuple[str, str]]:
        r = await client.post("/v1/pairs", json={"images": images, **extra})
        assert r.status_code == 200, r.text
        return {(p["image1"], p["image2"]) for p in r.json()["pairs"]}

    rule = await pairs(ground_z=0.0)
    assert await pairs(flying_height=100.0) == rule  # every camera is 100 m up
    assert await pairs(ground_z=0.0, params={"min_overlap": 0.4}) > rule  # the strips meet
    assert await pairs(ground_z=0.0, params={"min_partners": 3}) > rule
    assert await pairs(ground_z=0.0, params={"min_overlap": 0.6}) == set()
    # the ground 50 m higher halves the footprints: 49 m apart no longer overlap by half
    assert await pairs(ground_z=50.0) == set()
    capped = await pairs(ground_z=0.0, params={"min_overlap": 0.0, "max_per_image": 1})
    assert capped < await pairs(ground_z=0.0, params={"min_overlap": 0.0})


async def test_lat_lon_images_and_msgpack(client: httpx.AsyncClient) -> None:
    """WGS84 positions (about 49 m apart east-west), a body in MessagePack."""
    images = {
        f"im{i}": {
            "camera": CAMERA,
            "pose": {
                "position": {"lat": 46.84, "lon": -91.99 + i * 49.0 / 76_200.0, "alt": 300.0},
                "attitude": {"yaw": 90.0, "pitch": 0.0, "roll": 0.0},
            },
        }
        for i in range(4)
    }
    body = msgpack.packb({"images": images, "ground_z": 200.0})
    r = await client.post(
        "/v1/pairs", content=body, headers={"content-type": "application/vnd.hmcc+msgpack"}
    )
    assert r.status_code == 200, r.text
    assert [(p["image1"], p["image2"]) for p in r.json()["pairs"]] == [
        ("im0", "im1"),
        ("im1", "im2"),
        ("im2", "im3"),
    ]


@pytest.mark.parametrize(
    "change, field",
    [
        ({"ground_z": None}, "ground_z"),  # no ground
        ({"flying_height": 100.0}, "flying_height"),  # both
        ({"ground_z": 150.0}, "images.s0-0.pose.position"),  # above the cameras
        ({"flying_height": -1.0, "ground_z": None}, "flying_height"),
        ({"params": {"min_overlap": 1.5}}, "params.min_overlap"),
        ({"params": {"max_per_image": 0}}, "params.max_per_image"),
        ({"params": {"min_partners": -1}}, "params.min_partners"),
        ({"params": {"footprint": {"border_samples": 10**9}}}, "params.footprint.border_samples"),
        ({"params": {"unknown": 1}}, "params.unknown"),
        ({"images": {"only": grid_images()["s0-0"]}}, "images"),
        ({"images": {**grid_images(), "x": {"camera": CAMERA}}}, "images.x.pose"),
        (
            {"images": {**grid_images(), "x": {**grid_images()["s0-0"], "keypoints": [[1, 2]]}}},
            "images.x.keypoints",
        ),
        (
            {
                "images": {
                    **grid_images(),
                    "x": {
                        "camera": CAMERA,
                        "pose": {
                            "position": {"lat": 1.0, "lon": 2.0, "alt": 3.0},
                            "attitude": {"yaw": 0.0, "pitch": 0.0, "roll": 0.0},
                        },
                    },
                }
            },
            "images.x.pose.position",
        ),  # metres and degrees mixed
    ],
)
async def test_bad_input_is_422_naming_the_field(
    client: httpx.AsyncClient, change: dict[str, Any], field: str
) -> None:
    body = {"images": grid_images(), "ground_z": 0.0, **change}
    body = {k: v for k, v in body.items() if v is not None}
    r = await client.post("/v1/pairs", json=body)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "invalid_input"
    assert field in {i["field"] for i in error["issues"]}, error


async def test_too_much_work_is_refused(
    client: httpx.AsyncClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(route, "MAX_CANDIDATES", 5)
    r = await client.post("/v1/pairs", json={"images": grid_images(), "ground_z": 0.0})
    assert r.status_code == 422
    assert r.json()["error"]["issues"][0]["field"] == "images"
    assert "more than the 5" in r.json()["error"]["message"]


async def test_not_json_is_415_and_not_a_body_is_422(client: httpx.AsyncClient) -> None:
    r = await client.post("/v1/pairs", content=b"x", headers={"content-type": "text/plain"})
    assert r.status_code == 415
    r = await client.post(
        "/v1/pairs", content=b"[1, 2", headers={"content-type": "application/json"}
    )
    assert r.status_code == 422
    deep = b"[" * 10_000 + b"]" * 10_000
    r = await client.post(
        "/v1/pairs", content=deep, headers={"content-type": "application/vnd.hmcc+msgpack"}
    )
    assert r.status_code == 422


def test_the_request_defaults_are_the_librarys() -> None:
    assert parse_pairs({"images": grid_images(), "ground_z": 0.0}).params == PairOptions()
