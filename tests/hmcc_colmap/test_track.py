"""A rough attitude from the flight track for images with a position only (Caliterra)."""

from __future__ import annotations

from datetime import datetime, timedelta

import numpy as np
import pytest

from hmcc_colmap.capture import read_capture
from hmcc_colmap.poses import ImagePose, read_image_poses
from hmcc_colmap.track import ESTIMATED, capture_order, track_headings, with_track_attitude
from tests.support.shared_data import SHARED

CALITERRA = SHARED / "fixtures" / "caliterra" / "images"


def test_headings_follow_the_track_and_skip_a_hover() -> None:
    """North, north, a repeated fix, then east: central differences, the repeat skipped."""
    xy = np.array([[0.0, 0.0], [0.0, 10.0], [0.0, 10.2], [0.0, 20.0], [10.0, 20.0]])
    h = track_headings(xy, min_step_m=1.0)
    np.testing.assert_allclose(h[:3], [0.0, 0.0, 0.0], atol=1e-9)
    assert h[3] == pytest.approx(np.degrees(np.arctan2(10.0, 9.8)))  # the chord across the turn
    assert h[4] == pytest.approx(90.0)
    assert np.isnan(track_headings(np.zeros((2, 2)))).all()


def test_capture_order_by_time_else_by_name() -> None:
    t0 = datetime(2020, 1, 1)
    times = {"b.jpg": t0, "a.jpg": t0 + timedelta(seconds=2), "c.jpg": t0 + timedelta(seconds=1)}
    assert capture_order(list(times), times) == ["b.jpg", "c.jpg", "a.jpg"]
    assert capture_order(list(times), {**times, "c.jpg": None}) == ["a.jpg", "b.jpg", "c.jpg"]


def test_only_missing_attitudes_are_estimated() -> None:
    poses = {
        "1": ImagePose("file", {"x": 0.0, "y": 0.0, "z": 50.0}),
        "2": ImagePose(
            "file", {"x": 10.0, "y": 0.0, "z": 50.0}, {"yaw": 7.0, "pitch": 0, "roll": 0}
        ),
        "3": ImagePose("file", {"x": 20.0, "y": 0.0, "z": 50.0}),
        "4": ImagePose("file"),
    }
    out, estimated = with_track_attitude(poses, ["1", "2", "3", "4"])
    assert estimated == ["1", "3"]
    assert out["1"].attitude == {"yaw": 90.0, "pitch": 0.0, "roll": 0.0}
    assert ESTIMATED in out["1"].source
    assert out["2"] is poses["2"] and out["4"] is poses["4"]


def test_caliterra_gets_headings_along_its_strips() -> None:
    """75 images, GPS only: every one gets an estimated attitude; on the north-bound strip
    (IMG_9366 to IMG_9372) the heading is within 20 deg of north."""
    names = sorted(p.name for p in CALITERRA.glob("*.jpg"))
    assert len(names) == 75
    poses = read_image_poses(CALITERRA, names)
    assert all(p.position is not None and p.attitude is None for p in poses.values())
    times = {n: read_capture(CALITERRA / n).time for n in names}
    out, estimated = with_track_attitude(poses, capture_order(names, times))
    assert sorted(estimated) == names
    for n in (f"IMG_93{k}.jpg" for k in range(67, 72)):
        yaw = out[n].attitude["yaw"]  # type: ignore[index]
        assert min(yaw, 360.0 - yaw) < 20.0, (n, yaw)
