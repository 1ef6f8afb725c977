"""Tests of the simulated flight (hmcc.simulate_flight): its shape, its ground truth and that
the verifier recovers that truth."""

from __future__ import annotations

import numpy as np
import orjson
import pytest

from hmcc.simulate_flight import FlightOptions, simulate_flight
from hmcc_schema import parse_batch

SMALL = FlightOptions(
    strips=2, stations_per_strip=4, keypoints_per_image=600, pairs=40, relief_m=5.0
)


@pytest.fixture(scope="module")
def flight():
    return simulate_flight(SMALL, seed=3)


def test_the_block_has_every_camera_and_at_most_the_asked_pairs(flight) -> None:
    images = flight.body["images"]
    assert len(images) == SMALL.strips * SMALL.stations_per_strip * len(SMALL.views)
    assert sorted(set(flight.image_views.values())) == sorted(SMALL.views)
    pairs = flight.body["pairs"]
    assert 0 < len(pairs) <= SMALL.pairs
    assert len({p["id"] for p in pairs}) == len(pairs)
    for image in images.values():
        kps = image["keypoints"]
        assert kps.shape[1] == 2 and 0 < len(kps) <= SMALL.keypoints_per_image
        assert kps.min() >= 0 and kps[:, 0].max() <= SMALL.width_px - 1
        assert kps[:, 1].max() <= SMALL.height_px - 1


def test_matches_index_keypoints_and_the_outlier_share_is_as_asked(flight) -> None:
    images = flight.body["images"]
    true, total = 0, 0
    for pair in flight.body["pairs"]:
        m = pair["matches"]
        assert m.dtype == np.int32 and m.shape[1] == 2
        assert m[:, 0].max() < len(images[pair["image1"]]["keypoints"])
        assert m[:, 1].max() < len(images[pair["image2"]]["keypoints"])
        t = flight.truth[pair["id"]]
        assert np.all(np.diff(t) > 0) and (len(t) == 0 or t[-1] < len(m))
        true += len(t)
        total += len(m)
    assert total == flight.matches
    assert 1 - true / total == pytest.approx(SMALL.outlier_ratio, abs=0.02)


def test_the_same_seed_gives_the_same_flight(flight) -> None:
    again = simulate_flight(SMALL, seed=3)
    other = simulate_flight(SMALL, seed=4)
    pair, same = flight.body["pairs"][0], again.body["pairs"][0]
    assert pair["id"] == same["id"] and np.array_equal(pair["matches"], same["matches"])
    assert [p["id"] for p in again.body["pairs"]] == [p["id"] for p in flight.body["pairs"]]
    assert not all(
        np.array_equal(a["keypoints"], b["keypoints"])
        for a, b in zip(flight.body["images"].values(), other.body["images"].values(), strict=True)
    )


def test_the_verifier_recovers_the_truth(flight) -> None:
    body = orjson.dumps(flight.body, option=orjson.OPT_SERIALIZE_NUMPY)
    parsed = parse_batch(body, max_pairs=len(flight.body["pairs"]))
    kept = found = true = 0
    for i, pair in enumerate(flight.body["pairs"]):
        inliers = parsed.verify(i).inliers
        truth = flight.truth[pair["id"]]
        kept += len(inliers)
        found += len(np.intersect1d(inliers, truth))
        true += len(truth)
    assert found / kept > 0.98  # precision
    assert found / true > 0.9  # recall


def test_options_outside_their_bounds_name_the_field() -> None:
    with pytest.raises(ValueError, match="strips"):
        FlightOptions(strips=0)
    with pytest.raises(ValueError, match="outlier_ratio"):
        FlightOptions(outlier_ratio=1.0)
