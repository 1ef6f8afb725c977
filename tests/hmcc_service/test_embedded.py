"""The embedded queue's memory bound, through a real ``hmcc serve``: with
``HMCC_RESULT_MEMORY_MB=1``, results beyond a megabyte push out the oldest first (a pair job
then reads 404, a batch's pairs ``expired``), and what stays readable fits in the bound."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import httpx
import orjson
import pytest

from hmcc.simulate import SimulationOptions, simulate_pair
from tests.support.procs import service_env, start_api, wait_until

pytestmark = pytest.mark.procs

MB = 1024 * 1024
PAIRS = 200


@pytest.fixture(scope="module")
def url() -> Iterator[str]:
    api, base = start_api(service_env(HMCC_RESULT_MEMORY_MB="1"))
    try:
        yield base
    finally:
        api.stop()


def _big_results_batch(n_pairs: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """A pair whose result is some 12 KB (2 000 inliers listed), and a batch of ``n_pairs``
    copies of it (the keypoints sent once, with the images)."""
    pair = simulate_pair(SimulationOptions(n_inliers=2000, outlier_ratio=0.2), seed=1)
    pair.pop("ground_truth")
    batch = {
        "images": {
            "A": {**pair["image1"], "keypoints": pair["keypoints1"]},
            "B": {**pair["image2"], "keypoints": pair["keypoints2"]},
        },
        "plane": pair["plane"],
        "pairs": [
            {"id": f"p{k}", "image1": "A", "image2": "B", "matches": pair["matches"]}
            for k in range(n_pairs)
        ],
    }
    return pair, batch


def test_results_beyond_the_memory_bound_are_forgotten_oldest_first(url: str) -> None:
    pair, batch = _big_results_batch(PAIRS)
    first = httpx.post(f"{url}/v1/verifications?wait=30", json=pair, timeout=40).json()
    assert first["status"] == "finished", first
    size = len(orjson.dumps(first["result"]))
    assert PAIRS * size > 2 * MB, "the batch's results must overflow the bound"

    r = httpx.post(f"{url}/v1/batches", json=batch, timeout=60)
    assert r.status_code == 202, r.text
    location = f"{url}{r.headers['Location']}"
    assert wait_until(
        lambda: httpx.get(f"{location}?limit=0").json()["status"] == "finished", 120, 0.5
    )

    # The oldest result (the single pair's) went first.
    gone = httpx.get(f"{url}/v1/verifications/{first['job_id']}")
    assert gone.status_code == 404 and gone.json()["error"]["code"] == "not_found"

    items = []
    for offset in range(0, PAIRS, 100):
        items += httpx.get(f"{location}?offset={offset}&limit=100", timeout=30).json()["results"]
    page = httpx.get(f"{location}?limit=0").json()
    statuses = [i["status"] for i in items]
    assert set(statuses) == {"expired", "finished"}, set(statuses)
    assert (page["expired"], page["finished"]) == (
        statuses.count("expired"),
        statuses.count("finished"),
    )
    assert statuses[-1] == "finished", "the newest results are kept"
    expired = [i for i in items if i["status"] == "expired"]
    assert all(i["result"] is None and i["error"] is None for i in expired)
    kept = sum(len(orjson.dumps(i["result"])) for i in items if i["status"] == "finished")
    assert kept <= MB, f"{kept} bytes of results kept, the bound is {MB}"
