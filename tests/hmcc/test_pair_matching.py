"""A pair that asks for matching (:mod:`hmcc.pair_matching`): on simulated scenes with
SIFT-like descriptors the matches found are the true correspondences and the inliers are
true; poses that cannot predict give brute force, counted; too few matches still finish."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from hmcc.flight import Flight
from hmcc_schema import parse_batch
from tests.support.matching import matching_batch

#: A POS of a survey UAV: attitude within about a degree (the simulator's default IMU noise,
#: 2 deg of yaw plus 2 deg of wobble, is far worse than the matcher's documented 3 deg bound
#: for the prediction's shift model; see the report on the simulator's default below).
GOOD_IMU: dict[str, Any] = {"imu_sigma_deg": (1.0, 0.5, 0.5), "platform_attitude_sigma_deg": 0.5}


def _flight(seed: int, **scene: Any) -> tuple[Flight, set[tuple[int, int]]]:
    body, truth = matching_batch(seed, **scene)
    return parse_batch(body, 10), truth


def _found(result: dict[str, Any]) -> tuple[set[tuple[int, int]], set[tuple[int, int]]]:
    matches = [tuple(m) for m in result["matches"]]
    return set(matches), {matches[k] for k in result["inliers"]}


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_matching_finds_the_true_correspondences(seed: int) -> None:
    flight, truth = _flight(seed, **GOOD_IMU)
    result = flight.verify(0).to_dict()
    found, inliers = _found(result)
    assert len(found & truth) >= 0.97 * len(found)  # precision
    assert len(found & truth) >= 0.8 * len(truth)  # recall
    assert len(inliers & truth) >= 0.99 * len(inliers)
    assert len(inliers & truth) >= 0.95 * len(found & truth)
    matching = result["matching"]
    assert matching["mode"] == "guided"
    assert matching["matches"] == len(found)
    # a few dozen candidates per keypoint, not all of image 2's
    assert matching["candidates_per_keypoint"] < 0.2 * len(flight.images["b"].keypoints)
    assert matching["params"]["max_ratio"] == 0.8
    assert result["statistics"]["matches"] == len(found)


def test_the_result_indexes_the_matches_and_keeps_the_short_form() -> None:
    flight, _ = _flight(1, **GOOD_IMU)
    short = dataclasses.replace(
        flight, options=dataclasses.replace(flight.options, result="inliers")
    )
    result = short.verify(0).to_dict()
    assert set(result) == {"method", "matches", "inliers", "model", "timings_ms", "matching"}
    assert "params" not in result["matching"]
    assert max(result["inliers"]) < len(result["matches"])
    matches = np.asarray(result["matches"])
    assert matches[:, 0].max() < len(flight.images["a"].keypoints)
    assert matches[:, 1].max() < len(flight.images["b"].keypoints)


def test_a_camera_not_above_the_ground_is_matched_by_brute_force() -> None:
    """The ground given above the cameras (a datum mix-up): the poses cannot predict, so
    brute force, which finds the correspondences all the same; the figures say why. (A
    method that uses the poses would then refuse the pair's plane: an estimator here.)"""
    body, truth = matching_batch(2, **GOOD_IMU)
    body["plane"] = {"ground_z": 10_000.0}
    body["method"] = "ransac"
    result = parse_batch(body, 10).verify(0).to_dict()
    matching = result["matching"]
    assert matching["mode"] == "brute-force"
    assert "not above the ground" in matching["pose_unusable"]
    assert matching["candidates_per_keypoint"] == len(body["images"]["b"]["keypoints"])
    found, _ = _found(result)
    assert len(found & truth) >= 0.97 * len(found)
    assert len(found & truth) >= 0.9 * len(truth)


def test_poses_that_do_not_fit_go_to_brute_force_when_asked() -> None:
    """Image 2's yaw off by 45 degrees (no quarter turn explains it): the first passes do not
    fit; with ``brute_force_on_mismatch`` the pair is matched by brute force, else not."""
    body, truth = matching_batch(1, **GOOD_IMU)
    attitude = body["images"]["b"]["pose"]["attitude"]
    body["images"]["b"]["pose"]["attitude"] = {**attitude, "yaw": attitude["yaw"] + 45.0}
    body["method"] = "ransac"
    unmatched = parse_batch(body, 10).verify(0).to_dict()
    assert unmatched["matching"]["mode"] == "pose-mismatch-unmatched"
    body["matching"] = {"brute_force_on_mismatch": True}
    result = parse_batch(body, 10).verify(0).to_dict()
    assert result["matching"]["mode"] == "pose-mismatch"
    found, _ = _found(result)
    assert len(found & truth) >= 0.9 * len(truth)


def test_images_that_do_not_overlap_finish_without_inliers() -> None:
    """Image 2's camera moved a kilometre away: no overlap, no matches; the pair finishes
    (not an error) with no inliers, no model, and why it was not verified."""
    body, _ = matching_batch(3, **GOOD_IMU)
    position = body["images"]["b"]["pose"]["position"]
    body["images"]["b"]["pose"]["position"] = {**position, "x": position["x"] + 1000.0}
    result = parse_batch(body, 10).verify(0).to_dict()
    assert result["matching"]["mode"] == "no-overlap"
    assert result["matches"] == [] and result["inliers"] == []
    assert result["model"]["type"] is None
    assert "needs" in result["statistics"]["unverified"]


def test_float32_descriptors_match_like_their_uint8() -> None:
    body, truth = matching_batch(0, **GOOD_IMU)
    for image in body["images"].values():
        image["descriptors"] = image["descriptors"].astype(np.float32) / 512.0
    flight = parse_batch(body, 10)
    assert flight.images["a"].descriptors.dtype == np.float32
    found, _ = _found(flight.verify(0).to_dict())
    assert len(found & truth) >= 0.8 * len(truth)


def test_an_images_features_are_made_once_and_a_few_images_are_kept() -> None:
    from hmcc import flight as flight_module

    flight, _ = _flight(0)
    image = flight.images["a"]
    assert image.features is image.features
    others = [dataclasses.replace(image) for _ in range(flight_module.FEATURES_KEPT + 1)]
    for other in others:
        assert other.features is not image.features
    assert len(flight_module._features) == flight_module.FEATURES_KEPT
    assert image.features is not None  # made again, not a stale entry


def test_an_image_without_a_pose_is_matched_by_brute_force_and_counted() -> None:
    """Image 2 sent without a pose, an estimator as the method: brute force, which finds
    the correspondences; the figures say which image had none."""
    body, truth = matching_batch(1, **GOOD_IMU)
    del body["images"]["b"]["pose"]
    body["method"] = "magsac++"
    result = parse_batch(body, 10).verify(0).to_dict()
    assert result["matching"]["mode"] == "brute-force"
    assert result["matching"]["pose_unusable"] == "image2 has no pose"
    found, inliers = _found(result)
    assert len(found & truth) >= 0.97 * len(found)
    assert len(found & truth) >= 0.9 * len(truth)
    assert len(inliers & truth) >= 0.95 * len(inliers)
