"""A flight's keypoints sent to the pool's children through a file: what a child unpickles
is the flight it would have got with the keypoints in every task."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from hmcc.flight import Flight
from hmcc.simulate import SimulationOptions, simulate_pair
from hmcc_colmap import shipping
from hmcc_colmap.shipping import keypoints_in_file, scratch_dir
from hmcc_schema import parse_batch


def _flight() -> Flight:
    p = simulate_pair(SimulationOptions(n_inliers=200, outlier_ratio=0.3), 0)
    body = {
        "images": {
            "a": {**p["image1"], "keypoints": p["keypoints1"]},
            "b": {**p["image2"], "keypoints": p["keypoints2"]},
        },
        "pairs": [{"id": "0", "image1": "a", "image2": "b", "matches": p["matches"]}],
    }
    return parse_batch(json.dumps(body), 10)


def test_the_images_pickle_as_a_place_in_the_file_and_come_back_equal() -> None:
    flight = _flight()
    with keypoints_in_file(flight) as shipped:
        back = pickle.loads(pickle.dumps(shipped.subset([0])))
        for name, image in flight.images.items():
            assert image.keypoints is not None
            kept = len(pickle.dumps(image)) - len(pickle.dumps(shipped.images[name]))
            assert kept > 0.9 * image.keypoints.nbytes  # its keypoints stay behind
            got = back.images[name]
            assert type(got).__name__ == "FlightImage"  # a plain one in the child
            assert got.camera == image.camera
            np.testing.assert_array_equal(got.pose.R_world_to_cam, image.pose.R_world_to_cam)
            np.testing.assert_array_equal(got.keypoints, image.keypoints)
            assert got.keypoints.dtype == np.float64 and got.keypoints.flags.writeable
        assert back.verify(0).inliers.tolist() == flight.verify(0).inliers.tolist()


def test_the_file_goes_to_memory_only_where_there_is_room(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(shipping, "_MEMORY_DIR", tmp_path)
    assert scratch_dir(1000) == str(tmp_path)
    assert scratch_dir(1 << 60) is None  # more than the disk holds: the temporary directory
    monkeypatch.setattr(shipping, "_MEMORY_DIR", tmp_path / "missing")
    assert scratch_dir(1000) is None
