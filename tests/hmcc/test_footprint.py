"""Footprints on the ground plane, their overlap, and the pairs chosen from them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hmcc import InputError
from hmcc.camera import Camera
from hmcc.flight import RoughPose
from hmcc.footprint import (
    FootprintOptions,
    PairOptions,
    clip_convex,
    flight_pairs,
    footprint,
    overlap_fraction,
    polygon_area,
    select_pairs,
)
from hmcc.pose import Pose, geodetic_to_enu, rotation_from_yaw_pitch_roll
from tests.support.shared_data import BRIGHTON

#: 1.2 x 0.8 of the flying height across (f = 1000 px).
CAM = Camera(width=1200, height=800, fx=1000.0, fy=1000.0, cx=599.5, cy=399.5)


def _pose(x: float = 0.0, y: float = 0.0, z: float = 100.0, **attitude: float) -> Pose:
    yaw, pitch, roll = (attitude.get(k, 0.0) for k in ("yaw", "pitch", "roll"))
    mounting = (0.0, attitude.get("mount_pitch", 0.0), 0.0)
    return Pose(rotation_from_yaw_pitch_roll(yaw, pitch, roll, mounting), np.array([x, y, z]))


def _extent(poly: np.ndarray) -> np.ndarray:
    return poly.max(axis=0) - poly.min(axis=0)


def test_a_nadir_footprint_is_altitude_times_sensor_over_focal() -> None:
    """100 m above the plane, yaw 0 (image right = east): 1200 px x 100 / 1000 = 120 m east,
    80 m north, centred under the camera; 4 corners."""
    poly = footprint(CAM, _pose(z=130.0), z0=30.0)
    assert len(poly) == 4
    np.testing.assert_allclose(_extent(poly), [120.0, 80.0], atol=1e-9)
    np.testing.assert_allclose(poly.mean(axis=0), [0.0, 0.0], atol=1e-9)
    assert polygon_area(poly) == pytest.approx(120.0 * 80.0)


def test_heading_turns_the_footprint() -> None:
    """Yaw 90 (nose east): the image's long side now runs north-south."""
    poly = footprint(CAM, _pose(yaw=90.0), z0=0.0)
    np.testing.assert_allclose(_extent(poly), [80.0, 120.0], atol=1e-9)
    # edges along north and east: their points' x (or y) equal but for rounding, the hull
    # still keeps the four corners
    for yaw in (90.0, 180.0, -90.0):
        poly = footprint(CAM, _pose(yaw=yaw), z0=0.0)
        assert len(poly) == 4 and polygon_area(poly) == pytest.approx(120.0 * 80.0)


def test_nadir_images_half_a_footprint_apart_overlap_by_half() -> None:
    a = footprint(CAM, _pose(), 0.0)
    b = footprint(CAM, _pose(x=60.0), 0.0)  # half of the 120 m along x
    assert overlap_fraction(a, b) == pytest.approx(0.5)
    assert overlap_fraction(b, a) == pytest.approx(0.5)
    c = footprint(CAM, _pose(x=60.0, y=40.0), 0.0)  # half each way: a quarter
    assert overlap_fraction(a, c) == pytest.approx(0.25)
    assert overlap_fraction(a, footprint(CAM, _pose(x=130.0), 0.0)) == 0.0


def test_overlap_is_of_the_smaller_footprint() -> None:
    """A camera flown twice as high sees the lower one's whole footprint: overlap 1."""
    low = footprint(CAM, _pose(z=50.0), 0.0)
    high = footprint(CAM, _pose(z=100.0), 0.0)
    assert polygon_area(high) == pytest.approx(4 * polygon_area(low))
    assert overlap_fraction(low, high) == pytest.approx(1.0)


def test_an_oblique_footprint_is_a_trapezoid_further_out() -> None:
    """A forward-tilted camera (mounting pitch 45, nose north) sees a trapezoid north of the
    nadir point, its far edge longer than its near edge."""
    poly = footprint(CAM, _pose(mount_pitch=45.0), 0.0)
    assert len(poly) == 4
    ys = np.sort(np.unique(np.round(poly[:, 1], 6)))
    assert len(ys) == 2 and ys[0] > 0.0  # near and far edges, both ahead of the camera
    near = np.ptp(poly[np.isclose(poly[:, 1], ys[0]), 0])
    far = np.ptp(poly[np.isclose(poly[:, 1], ys[1]), 0])
    assert far > near
    # the optical axis meets the ground 100 m ahead: inside the footprint
    assert ys[0] < 100.0 < ys[1]
    # the near edge: 45 - atan(400 / 1000) = 23.2 deg from nadir
    assert ys[0] == pytest.approx(100.0 * np.tan(np.radians(45.0) - np.arctan(0.4)))


def test_a_camera_at_the_horizon_is_clipped_at_the_range() -> None:
    """Mounting pitch 90: the upper half of the image looks above the horizon. The footprint
    stops at max_range_ratio x the height and follows that circle."""
    options = FootprintOptions(max_range_ratio=4.0)
    poly = footprint(CAM, _pose(mount_pitch=90.0), 0.0, options)
    reach = np.hypot(*poly.T)
    assert reach.max() == pytest.approx(400.0)
    assert poly[:, 1].min() > 0.0  # all of it ahead (north)
    # the image bottom edge: atan(400 / 1000) = 21.8 deg below the horizon, 250 m ahead
    assert poly[:, 1].min() == pytest.approx(100.0 / np.tan(np.arctan(0.4)))
    assert len(poly) > 4  # the far edge follows the circle
    wider = footprint(CAM, _pose(mount_pitch=90.0), 0.0, FootprintOptions(max_range_ratio=8.0))
    assert polygon_area(wider) > polygon_area(poly)


def test_translating_both_changes_nothing() -> None:
    shift = np.array([1234.5, -987.25, 57.0])
    poses = [_pose(), _pose(x=45.0, y=10.0, yaw=20.0, mount_pitch=30.0)]
    moved = [Pose(p.R_world_to_cam, p.center + shift) for p in poses]
    a, b = (footprint(CAM, p, 0.0) for p in poses)
    ma, mb = (footprint(CAM, p, shift[2]) for p in moved)
    np.testing.assert_allclose(ma, a + shift[:2], atol=1e-6)
    assert overlap_fraction(ma, mb) == pytest.approx(overlap_fraction(a, b), abs=1e-9)


def test_a_camera_below_the_plane_has_no_footprint() -> None:
    with pytest.raises(ValueError, match="not above the plane"):
        footprint(CAM, _pose(z=10.0), 20.0)


def test_clip_of_disjoint_or_nested_polygons() -> None:
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert len(clip_convex(square, square + 5.0)) == 0
    inner = square * 0.5 + 0.25
    assert polygon_area(clip_convex(inner, square)) == pytest.approx(0.25)
    assert polygon_area(clip_convex(square, inner)) == pytest.approx(0.25)


def test_select_pairs_on_a_grid_keeps_neighbours_only() -> None:
    """3 strips of 6 nadir images, 40 m along (1/3 of 120 m: overlap 2/3) and 48 m across
    (overlap 0.4 of 80 m): only the along-strip neighbours pass 0.5."""
    poses = [_pose(x=40.0 * i, y=48.0 * s) for s in range(3) for i in range(6)]
    prints = [footprint(CAM, p, 0.0) for p in poses]
    pairs = select_pairs(prints, min_overlap=0.5)
    assert {(p.i, p.j) for p in pairs} == {
        (6 * s + i, 6 * s + i + 1) for s in range(3) for i in range(5)
    }
    assert all(p.overlap == pytest.approx(2.0 / 3.0) for p in pairs)
    wide = select_pairs(prints, min_overlap=0.1)
    assert len(wide) > len(pairs)
    # brute force agrees with the k-d tree's candidates
    brute = {
        (i, j)
        for i in range(len(prints))
        for j in range(i + 1, len(prints))
        if overlap_fraction(prints[i], prints[j]) > 0.1
    }
    assert {(p.i, p.j) for p in wide} == brute
    capped = select_pairs(prints, min_overlap=0.1, max_per_image=2)
    counts = np.bincount([k for p in capped for k in (p.i, p.j)], minlength=len(prints))
    assert counts.min() >= 2 and len(capped) < len(wide)


def _grid_prints() -> list[np.ndarray]:
    """The grid above: 3 strips of 6, overlap 2/3 along a strip, 0.4 across."""
    return [footprint(CAM, _pose(x=40.0 * i, y=48.0 * s), 0.0) for s in range(3) for i in range(6)]


def test_min_partners_gives_every_image_its_best_overlaps() -> None:
    """With min_partners K every image takes part in at least K pairs (its K largest overlaps
    above zero), the pairs above min_overlap all stay, and an image that has K already
    gains none of its own (the grid's inner images have 2 along the strip: K = 2 adds
    nothing)."""
    prints = _grid_prints()
    rule = {(p.i, p.j) for p in select_pairs(prints, 0.5)}
    assert {(p.i, p.j) for p in select_pairs(prints, 0.5, min_partners=1)} == rule
    everything = select_pairs(prints, 0.0)  # every overlap above zero
    met = np.bincount([n for p in everything for n in (p.i, p.j)], minlength=len(prints))
    for k in (3, 4, 6):
        chosen = select_pairs(prints, 0.5, min_partners=k)
        ij = {(p.i, p.j) for p in chosen}
        assert rule < ij
        counts = np.bincount([n for p in chosen for n in (p.i, p.j)], minlength=len(prints))
        assert (counts >= np.minimum(k, met)).all()
        for image in range(len(prints)):  # its k best of all its overlaps are in
            own = sorted((p for p in everything if image in (p.i, p.j)), key=lambda p: -p.overlap)
            assert {(p.i, p.j) for p in own[:k]} <= ij
    # the strip ends have one neighbour above 0.5: K = 2 gives them their best across-strip one
    two = select_pairs(prints, 0.5, min_partners=2)
    added = {(p.i, p.j) for p in two} - rule
    assert added and all(p.overlap <= 0.5 for p in two if (p.i, p.j) in added)
    with pytest.raises(ValueError, match="min_partners"):
        select_pairs(prints, 0.5, min_partners=-1)


def test_max_candidates_refuses_before_clipping() -> None:
    prints = _grid_prints()
    assert select_pairs(prints, 0.5, max_candidates=10_000)
    with pytest.raises(ValueError, match="more than the 10 one call examines"):
        select_pairs(prints, 0.5, max_candidates=10)


def _rough(x: float, y: float, z: float, yaw: float = 0.0) -> RoughPose:
    return RoughPose(rotation_from_yaw_pitch_roll(yaw, 0.0, 0.0), np.array([x, y, z]))


def test_flight_pairs_same_from_metres_and_from_lat_lon() -> None:
    """A flight given in local metres and the same flight given in WGS84 (converted about a
    point) choose the same pairs with the same overlaps; flying_height is ground_z per camera."""
    local = {f"s{s}i{i}": _rough(40.0 * i, 48.0 * s, 100.0) for s in range(3) for i in range(6)}
    cameras = dict.fromkeys(local, CAM)
    by_metres = flight_pairs(cameras, local, ground_z=0.0)
    lat0, lon0 = 46.8, -92.0
    # degrees per metre north and east there (the ENU frame's own, to 1e-6 of these)
    steps = geodetic_to_enu([lat0 + 1e-4, lat0], [lon0, lon0 + 1e-4], [0, 0], (lat0, lon0, 0))
    north, east = steps[0, 1] / 1e-4, steps[1, 0] / 1e-4
    geodetic = {}
    for name, pose in local.items():
        x, y, z = pose.position
        ll = np.array([lat0 + y / north, lon0 + x / east, 180.0 + z])
        geodetic[name] = RoughPose(pose.R_world_to_cam, ll, geodetic=True)
    by_degrees = flight_pairs(cameras, geodetic, flying_height=100.0)
    assert [p[:2] for p in by_degrees.pairs] == [p[:2] for p in by_metres.pairs]
    np.testing.assert_allclose(
        [p[2] for p in by_degrees.pairs], [p[2] for p in by_metres.pairs], atol=1e-3
    )
    assert {p[:2] for p in by_metres.pairs} == {
        (f"s{s}i{i}", f"s{s}i{i + 1}") for s in range(3) for i in range(5)
    }
    wider = flight_pairs(cameras, local, ground_z=0.0, options=PairOptions(min_partners=3))
    assert set(by_metres.pairs) < set(wider.pairs)


def test_flight_pairs_name_the_image_that_does_not_fit() -> None:
    poses = {"a": _rough(0, 0, 100), "b": _rough(40, 0, 100)}
    cameras = dict.fromkeys(poses, CAM)
    with pytest.raises(InputError) as e:
        low = {**poses, "c": _rough(0, 0, 5)}
        flight_pairs(dict.fromkeys(low, CAM), low, ground_z=10.0)
    assert e.value.field == "images.c.pose.position"
    mixed = {**poses, "d": RoughPose(np.eye(3), np.array([1.0, 2.0, 3.0]), geodetic=True)}
    with pytest.raises(InputError) as e:
        flight_pairs(dict.fromkeys(mixed, CAM), mixed, ground_z=0.0)
    assert e.value.field == "images.d.pose.position"
    with pytest.raises(ValueError, match="exactly one"):
        flight_pairs(cameras, poses, ground_z=0.0, flying_height=100.0)
    with pytest.raises(ValueError, match="exactly one"):
        flight_pairs(cameras, poses)


def test_brighton_overlaps_match_the_fixtures() -> None:
    """The fixtures' ``footprint_overlap`` (intersection over the smaller footprint on Z0,
    from the stored K and poses) is what :func:`overlap_fraction` gives, to its rounding."""
    files = sorted(BRIGHTON.glob("pair_*.json"))
    assert len(files) == 14
    for path in files:
        doc = json.loads(path.read_text())
        prints = []
        for key in ("image1", "image2"):
            image = doc[key]
            K = np.asarray(image["K"])
            camera = Camera(image["width"], image["height"], K[0, 0], K[1, 1], K[0, 2], K[1, 2])
            pose = Pose(np.asarray(image["R_world_to_cam"]), np.asarray(image["C_enu"]))
            prints.append(footprint(camera, pose, doc["Z0"]))
        assert overlap_fraction(*prints) == pytest.approx(doc["footprint_overlap"], abs=0.011), path
