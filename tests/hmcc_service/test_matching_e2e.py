"""Matching through the whole service, real processes: ``hmcc serve`` in embedded mode, and
``hmcc serve`` with a real redis-server and a real ``hmcc worker`` (the descriptors travel in
the batch's stored images, once per batch). The thin client sends images with descriptors
and pairs that ask for matching (MessagePack with raw buffers, and JSON from the async
client); each pair's result holds the matches found, which are the simulated scene's true
correspondences, and the inliers among them."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from hmcc_client import AsyncHmccClient, HmccClient, HmccError
from tests.support.matching import matching_batch
from tests.support.procs import redis_server, service_env, start_api, start_worker, wait_until

pytestmark = pytest.mark.procs

#: Attitude within about a degree (see tests/hmcc/test_pair_matching.py).
GOOD_IMU: dict[str, Any] = {"imu_sigma_deg": (1.0, 0.5, 0.5), "platform_attitude_sigma_deg": 0.5}


@pytest.fixture(scope="module", params=["embedded", "rq"])
def url(request: pytest.FixtureRequest) -> Iterator[str]:
    if request.param == "embedded":
        api, base = start_api(service_env())
        try:
            yield base
        finally:
            api.stop()
        return
    with redis_server() as redis:
        env = service_env(REDIS_URL=redis.url)
        api, base = start_api(env)
        worker = start_worker(env)
        try:
            assert wait_until(lambda: httpx.get(f"{base}/readyz").status_code == 200, 30), (
                worker.log()
            )
            yield base
        finally:
            worker.stop()
            api.stop()


def _flight(n: int) -> tuple[dict[str, Any], list[dict[str, Any]], dict[str, Any], list[set]]:
    """``n`` simulated pairs as one flight (images ``a0, b0, a1, ...``), each asking for
    matching, and each pair's true correspondences. The scenes share their ground height."""
    images: dict[str, Any] = {}
    pairs, truths = [], []
    plane: dict[str, Any] = {}
    for k in range(n):
        body, truth = matching_batch(k, n_inliers=200, **GOOD_IMU)
        for name, image in body["images"].items():
            images[f"{name}{k}"] = image
        pairs.append({"id": f"p{k}", "image1": f"a{k}", "image2": f"b{k}", "match": True})
        truths.append(truth)
        plane = body["plane"]
    return images, pairs, plane, truths


def _check(result: Any, truth: set[tuple[int, int]]) -> None:
    assert result is not None
    matches = [tuple(m) for m in result.matches]
    found = set(matches)
    inliers = {matches[k] for k in result.inliers}
    assert len(found & truth) >= 0.97 * len(found)
    assert len(found & truth) >= 0.8 * len(truth)
    assert len(inliers & truth) >= 0.99 * len(inliers)
    assert len(inliers) >= 0.95 * len(found & truth)
    assert result.matching["mode"] == "guided"
    assert result.matching["matches"] == len(found)
    assert result.matching["candidates_per_keypoint"] > 0
    assert result.matching["time_ms"] > 0


def test_the_client_has_a_flight_matched_and_verified(url: str) -> None:
    images, pairs, plane, truths = _flight(3)
    with HmccClient(url) as hmcc:
        items = list(hmcc.verify_flight(images, pairs, plane=plane, timeout=120))
    assert [i.index for i in items] == [0, 1, 2]
    for item, truth in zip(items, truths, strict=True):
        assert item.status == "finished", item.error
        _check(item.result, truth)


def test_the_async_client_sends_json_and_reads_the_same(url: str) -> None:
    images, pairs, plane, truths = _flight(1)

    async def run() -> list[Any]:
        async with AsyncHmccClient(url) as hmcc:
            return [
                item
                async for item in hmcc.verify_flight(
                    images,
                    pairs,
                    plane=plane,
                    binary=False,
                    matching={"max_ratio": 0.8, "cross_check": True},
                    params={"result": "inliers"},
                    timeout=120,
                )
            ]

    (item,) = asyncio.run(run())
    assert item.status == "finished", item.error
    _check(item.result, truths[0])
    assert item.result.stages is None  # the short form, matches and figures kept


def test_a_pair_without_descriptors_is_refused_naming_the_field(url: str) -> None:
    images, pairs, plane, _ = _flight(1)
    del images["b0"]["descriptors"]
    with HmccClient(url) as hmcc, pytest.raises(HmccError) as refused:
        list(hmcc.verify_flight(images, pairs, plane=plane, timeout=60))
    assert refused.value.status == 422
    assert "images.b0.descriptors" in str(refused.value)
