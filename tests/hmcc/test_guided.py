"""Matching guided by the rough POS: the prediction through the plane, the grid-bounded
matcher against brute force, and poses that are missing, wrong or far apart."""

from __future__ import annotations

import numpy as np
import pytest

from hmcc.camera import Camera
from hmcc.guided import (
    Features,
    GridIndex,
    GuidedOptions,
    match_brute_force,
    match_guided,
    match_within,
    predict_in_image2,
    predicted_overlap,
    project_points,
    wide_radius_px,
)
from hmcc.pose import Pose, rot_z, rotation_from_yaw_pitch_roll
from hmcc.simulate import SimulationOptions, simulate_pair

CAM = Camera(width=1200, height=900, fx=900.0, fy=900.0, cx=599.5, cy=449.5)
HEIGHT = 100.0
BASELINE = 30.0


def _pose(yaw: float = 0.0, x: float = 0.0, y: float = 0.0, pitch: float = 0.0) -> Pose:
    return Pose(rotation_from_yaw_pitch_roll(yaw, pitch, 0.0), np.array([x, y, HEIGHT]))


# --------------------------------------------------------------------------- prediction


@pytest.mark.parametrize("views", [("V", "V"), ("F", "F"), ("L", "V")])
def test_true_matches_are_predicted_within_a_few_pixels_with_exact_poses(views) -> None:
    """A flat simulated ground, the true poses: each true match's keypoint of image 2 lies
    where the plane puts its keypoint of image 1 (keypoint noise 0.5 px)."""
    options = SimulationOptions(
        views=views, relief_m=0.0, building_fraction=0.0, n_inliers=300, outlier_ratio=0.2
    )
    pair = simulate_pair(options, seed=3)
    truth = pair["ground_truth"]
    cam = options.camera
    poses = [
        Pose(np.array(p["R_world_to_cam"]), np.array(p["center"])) for p in truth["true_poses"]
    ]
    matches = np.asarray(pair["matches"])[truth["inliers"]]
    kp1 = np.asarray(pair["keypoints1"])[matches[:, 0], :2]
    kp2 = np.asarray(pair["keypoints2"])[matches[:, 1], :2]
    pred, valid = predict_in_image2(cam, poses[0], kp1, cam, poses[1], truth["mean_ground_z"])
    assert valid.all()
    error = np.hypot(*(pred - kp2).T)
    assert np.median(error) < 1.5
    assert error.max() < 5.0


def test_a_distorted_camera_projects_where_its_normalisation_comes_from() -> None:
    cam = Camera(1200, 900, 900.0, 900.0, 599.5, 449.5, (-0.1, 0.02, 0.001, -0.001, 0.0))
    pose = _pose(yaw=30.0)
    pixels = np.array([[10.0, 20.0], [600.0, 450.0], [1150.0, 880.0]])
    rays = cam.rays(pixels) @ pose.R_world_to_cam
    back, front = project_points(cam, pose, pose.center + 50.0 * rays)
    assert front.all()
    np.testing.assert_allclose(back, pixels, atol=1e-3)


def test_points_behind_camera_2_are_not_predicted() -> None:
    back, front = project_points(CAM, _pose(), np.array([[0.0, 0.0, HEIGHT + 10.0]]))
    assert not front.any() and (back == 0).all()


def test_the_wide_radius_adds_attitude_position_and_ground_terms() -> None:
    """f = 900 px, 100 m above Z0, 30 m apart: 3 deg -> 2 f tan 3 = 94.3 px; 3 m -> 2 f 3 /
    100 = 54 px; 10 % of the height -> f 0.3 0.1 / 0.9 = 30 px."""
    radius, terms = wide_radius_px(
        CAM, _pose(), _pose(x=BASELINE), 0.0, GuidedOptions(max_wide_fraction=2.0)
    )
    assert terms == {"attitude_px": 94.3, "position_px": 54.0, "ground_px": 30.0}
    assert radius == pytest.approx(94.34 + 54.0 + 30.0, abs=0.1)
    options = GuidedOptions(max_wide_fraction=0.1)
    capped, _ = wide_radius_px(CAM, _pose(), _pose(x=BASELINE), 0.0, options)
    assert capped == pytest.approx(0.1 * 1200)


# --------------------------------------------------------------------------- a scene


def _scene(seed: int = 0, n_points: int = 1500, n_clutter: int = 300):
    """Two nadir views 30 m apart over the plane Z = 0 from 100 m; SIFT-like (non-negative,
    uint8) descriptors per ground point, each view's a noisy copy; clutter keypoints seen in
    one image only. Returns the two poses, both features, and the true matches."""
    rng = np.random.default_rng(seed)
    pose1, pose2 = _pose(), _pose(x=BASELINE)
    world = np.column_stack(
        (rng.uniform(-70, 100, n_points), rng.uniform(-50, 50, n_points), np.zeros(n_points))
    )
    px1, ok1 = project_points(CAM, pose1, world)
    px2, ok2 = project_points(CAM, pose2, world)
    inside1, inside2 = ok1 & _in_image(px1), ok2 & _in_image(px2)
    seen = inside1 & inside2
    base = np.abs(rng.normal(size=(n_points, 128)))

    def view(keep: np.ndarray, px: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        idx = np.flatnonzero(keep)
        desc = base[idx] + np.abs(rng.normal(scale=0.25, size=(len(idx), 128)))
        kps = px[idx] + rng.normal(scale=0.5, size=(len(idx), 2))
        clutter = rng.uniform((0, 0), (CAM.width - 1, CAM.height - 1), (n_clutter, 2))
        clutter_desc = np.abs(rng.normal(size=(n_clutter, 128)))
        kps, desc = np.vstack((kps, clutter)), np.vstack((desc, clutter_desc))
        order = rng.permutation(len(kps))
        ids = np.concatenate((idx, np.full(n_clutter, -1)))[order]
        unit = desc[order] / np.linalg.norm(desc[order], axis=1, keepdims=True)
        return kps[order], np.clip(np.round(512 * unit), 0, 255).astype(np.uint8), ids

    kp1, d1, ids1 = view(inside1, px1)
    kp2, d2, ids2 = view(inside2, px2)
    where2 = {p: j for j, p in enumerate(ids2) if p >= 0}
    truth = {(i, where2[p]) for i, p in enumerate(ids1) if p >= 0 and seen[p]}
    return pose1, pose2, Features.from_raw(kp1, d1), Features.from_raw(kp2, d2), truth


def _in_image(px: np.ndarray) -> np.ndarray:
    return (px >= 0).all(axis=1) & (px[:, 0] <= CAM.width - 1) & (px[:, 1] <= CAM.height - 1)


def _pairs(matches: np.ndarray) -> set[tuple[int, int]]:
    return {(int(a), int(b)) for a, b in matches}


def test_brute_force_finds_the_true_matches() -> None:
    _, _, f1, f2, truth = _scene()
    result = match_brute_force(f1, f2, GuidedOptions())
    found = _pairs(result.matches)
    assert len(found & truth) >= 0.95 * len(truth)
    assert len(found - truth) <= 0.02 * len(found)
    assert result.stats["mode"] == "brute-force"
    assert result.stats["candidates_per_keypoint"] == len(f2)


def test_an_unbounded_radius_gives_exactly_the_brute_force_matches() -> None:
    pose1, pose2, f1, f2, _ = _scene(seed=1)
    options = GuidedOptions()
    pred, _ = predict_in_image2(CAM, pose1, f1.keypoints, CAM, pose2, 0.0)
    everywhere, compared = match_within(pred, np.ones(len(f1), bool), f1, f2, 1e9, options)
    assert compared == len(f1) * len(f2)
    np.testing.assert_array_equal(everywhere, match_brute_force(f1, f2, options).matches)
    without_check = GuidedOptions(cross_check=False)
    loose, _ = match_within(pred, np.ones(len(f1), bool), f1, f2, 1e9, without_check)
    assert _pairs(loose) == _pairs(match_brute_force(f1, f2, without_check).matches)


def _colmap_rules(d1: np.ndarray, d2: np.ndarray, options: GuidedOptions) -> set[tuple[int, int]]:
    """COLMAP's brute-force matching written out: the best and second best of each row by
    dot product, the distance and ratio rules on their angles, both ways, the two ways
    agreeing (its cross check)."""

    def one_way(dots: np.ndarray) -> np.ndarray:
        out = np.full(len(dots), -1)
        for i, row in enumerate(dots):
            order = np.argsort(-row, kind="stable")
            best = np.arccos(min(row[order[0]], 1.0))
            second = np.arccos(min(row[order[1]], 1.0)) if len(row) > 1 else np.inf
            if best <= options.max_distance_rad and best < options.max_ratio * second:
                out[i] = order[0]
        return out

    dots = d1.astype(np.float64) @ d2.astype(np.float64).T
    ab, ba = one_way(dots), one_way(dots.T)
    return {(i, int(j)) for i, j in enumerate(ab) if j >= 0 and ba[j] == i}


def test_brute_force_applies_colmaps_rules_both_ways() -> None:
    """200 features seen in both images, 40 of them twice in image 1 and 40 twice in image
    2 (repeated texture): a keypoint of image 2 whose best keypoint of image 1 is not clearly
    better than its second (the ratio rule taken the other way) is no match, as in COLMAP's
    cross check."""
    rng = np.random.default_rng(5)
    base = np.abs(rng.normal(size=(200, 128)))

    def noisy(rows: np.ndarray) -> np.ndarray:
        return rows + np.abs(rng.normal(scale=0.25, size=rows.shape))

    d1 = noisy(np.vstack((base, base[:40])))
    d2 = noisy(np.vstack((base, base[40:80])))
    kp1, kp2 = rng.uniform(0, 500, (len(d1), 2)), rng.uniform(0, 500, (len(d2), 2))
    f1, f2 = Features.from_raw(kp1, d1), Features.from_raw(kp2, d2)
    options = GuidedOptions(max_distance_rad=1.0)
    expected = _colmap_rules(f1.descriptors, f2.descriptors, options)
    assert 100 <= len(expected) <= 130  # the 120 unrepeated ones, give or take
    assert _pairs(match_brute_force(f1, f2, options).matches) == expected
    everywhere, _ = match_within(kp1, np.ones(len(d1), bool), f1, f2, 1e9, options)
    assert _pairs(everywhere) == expected


def test_a_repeat_within_the_ratio_radius_makes_a_match_ambiguous() -> None:
    """Image 2 repeats a feature 30 px from the true one (repeated texture): within a 10 px
    radius the match is clear, with a 40 px ratio radius the repeat competes (both ways)
    and the match is dropped; a repeat farther out does not compete."""
    rng = np.random.default_rng(7)
    desc = np.abs(rng.normal(size=(3, 128)))
    d1 = desc[:1] + np.abs(rng.normal(scale=0.05, size=(1, 128)))
    d2 = np.vstack([desc[0] + np.abs(rng.normal(scale=0.05, size=128)) for _ in range(2)])
    d2 = np.vstack((d2, desc[1]))
    f1 = Features.from_raw(np.array([[100.0, 100.0]]), d1)
    options = GuidedOptions()
    pred, active = np.array([[100.0, 100.0]]), np.ones(1, bool)
    for far, expected in ((30.0, 0), (60.0, 1)):
        kp2 = np.array([[101.0, 100.0], [100.0 + far, 100.0], [300.0, 300.0]])
        f2 = Features.from_raw(kp2, d2)
        plain, _ = match_within(pred, active, f1, f2, 10.0, options)
        assert _pairs(plain) == {(0, 0)}
        wider, compared = match_within(pred, active, f1, f2, 10.0, options, ratio_radius=40.0)
        assert len(wider) == expected
        assert compared == 2 - expected  # the repeat within 40 px is compared, not matched


def test_within_the_radius_the_guided_pass_keeps_brute_forces_true_matches() -> None:
    """Exact poses, a 20 px radius: every true match brute force finds is found, with a few
    dozen candidates per keypoint instead of all of image 2's."""
    pose1, pose2, f1, f2, truth = _scene(seed=2)
    options = GuidedOptions()
    pred, valid = predict_in_image2(CAM, pose1, f1.keypoints, CAM, pose2, 0.0)
    guided, compared = match_within(pred, valid, f1, f2, 20.0, options)
    brute = _pairs(match_brute_force(f1, f2, options).matches)
    assert (brute & truth) <= _pairs(guided)
    assert compared < 0.05 * len(f1) * len(f2)


def test_a_prediction_whose_circle_misses_the_grid_has_no_candidates() -> None:
    """Keypoints predicted far beyond image 2 (farther than the radius from any keypoint, on
    every side) compare nothing and match nothing; the one predicted on image 2 still
    matches. The grid's cells are never read beyond its ends."""
    rng = np.random.default_rng(3)
    desc = rng.uniform(0, 1, (5, 128))
    f1 = Features.from_raw(np.zeros((5, 2)), desc)
    f2 = Features.from_raw(np.array([[50.0, 50.0], [60.0, 60.0]]), desc[:2])
    far = [[1e6, 50.0], [-1e6, 50.0], [50.0, 1e6], [50.0, -1e6]]
    pred = np.array([[50.0, 50.0], *far])
    matches, compared = match_within(pred, np.ones(5, bool), f1, f2, 8.0, GuidedOptions())
    assert _pairs(matches) == {(0, 0)}
    assert compared == 1


def test_the_grid_lists_each_keypoint_once_in_its_cell() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 100, (500, 2))
    features = Features.from_raw(pts, rng.uniform(0, 1, (500, 8)))
    grid = GridIndex.build(features, 7.0)
    assert sorted(grid.order.tolist()) == list(range(500))
    np.testing.assert_array_equal(grid.points, pts[grid.order])
    np.testing.assert_array_equal(grid.descriptors, features.descriptors[grid.order])
    for c in range(grid.cols * grid.rows):
        for j in grid.order[grid.starts[c] : grid.starts[c + 1]]:
            col, row = ((pts[j] - grid.origin) // grid.cell).astype(int)
            assert row * grid.cols + col == c


@pytest.mark.parametrize(
    ("yaw_error", "shift_m"), [(0.0, (0.0, 0.0)), (2.5, (2.0, -2.0)), (-1.0, (-3.0, 1.0))]
)
def test_two_passes_recover_the_matches_under_rough_poses(yaw_error, shift_m) -> None:
    """Rough poses (camera 2 turned and moved within the POS errors, the ground 8 m off):
    the first pass finds the shift, the second the matches."""
    pose1, pose2, f1, f2, truth = _scene(seed=3)
    rough2 = Pose(
        pose2.R_world_to_cam @ rot_z(yaw_error).T, pose2.center + np.array([*shift_m, 0.0])
    )
    result = match_guided(CAM, pose1, f1, CAM, rough2, f2, -8.0, GuidedOptions())
    assert result.stats["mode"] == "guided"
    found = _pairs(result.matches)
    assert len(found & truth) >= 0.93 * len(truth)
    assert len(found - truth) <= 0.05 * len(found)
    assert result.stats["candidates_per_keypoint"] < 0.1 * len(f2)
    assert result.stats["matches"] == len(found)
    assert result.stats["time_ms"] > 0


@pytest.mark.parametrize(("yaw_error", "height_m"), [(4.0, 112.0), (-3.0, 90.0), (5.0, 100.0)])
def test_the_first_pass_absorbs_a_yaw_and_a_height_error(yaw_error, height_m) -> None:
    """Camera 2's rough yaw a few degrees off and its height off by up to 12 %: the
    predictions are off by a rotation and a scale about the image's centre, no shift (the
    outer keypoints 40 px off, the middle ones none). The first pass's affine map takes that
    out: the tight radius stays near its least, and within it the second pass finds every
    true match brute force finds."""
    pose1, pose2, f1, f2, truth = _scene(seed=5)
    rough2 = Pose(
        pose2.R_world_to_cam @ rot_z(yaw_error).T, np.array([*pose2.center[:2], height_m])
    )
    options = GuidedOptions()
    result = match_guided(CAM, pose1, f1, CAM, rough2, f2, 0.0, options)
    assert result.stats["mode"] == "guided"
    assert result.stats["tight_radius_px"] <= 2 * options.tight_min_px
    brute = _pairs(match_brute_force(f1, f2, options).matches)
    found = _pairs(result.matches)
    assert (brute & truth) <= found
    assert len(found - truth) <= 0.02 * len(found)


def test_a_turned_image_is_found_turned() -> None:
    """Image 2 turned by 180 deg after capture (its POS says the other way): the poses as
    given find no consistent shift, image 2 turned back does."""
    pose1, pose2, f1, f2, truth = _scene(seed=4)
    turned = Pose(rot_z(180.0) @ pose2.R_world_to_cam, pose2.center)
    result = match_guided(CAM, pose1, f1, CAM, turned, f2, 0.0, GuidedOptions())
    assert result.stats["mode"] == "guided-turned"
    assert result.stats["turn_deg"] == [0, 180]
    found = _pairs(result.matches)
    assert len(found & truth) >= 0.93 * len(truth)
    # 16 first passes over a small image still compare far less than brute force
    assert result.stats["candidates_per_keypoint"] < 0.3 * len(f2)


def _with_orientations(
    pose1: Pose, pose2: Pose, f1: Features, f2: Features, truth: set[tuple[int, int]], seed: int
) -> tuple[Features, Features]:
    """The features with keypoint orientations: random in image 1, image 1's turned as the
    true views turn the image there (3 deg of noise) in image 2; random for the clutter."""
    rng = np.random.default_rng(seed)
    o1 = rng.uniform(-np.pi, np.pi, len(f1))
    o2 = rng.uniform(-np.pi, np.pi, len(f2))
    for i, j in truth:
        p = f1.keypoints[i]
        q = p + 5.0 * np.array([np.cos(o1[i]), np.sin(o1[i])])
        pred, _ = predict_in_image2(CAM, pose1, np.stack((p, q)), CAM, pose2, 0.0)
        d = pred[1] - pred[0]
        o2[j] = np.arctan2(d[1], d[0]) + np.radians(rng.normal(scale=3.0))
    return Features(f1.keypoints, f1.descriptors, o1), Features(f2.keypoints, f2.descriptors, o2)


@pytest.mark.parametrize("yaw_error", [40.0, -125.0])
def test_a_yaw_off_by_any_angle_is_found_from_the_keypoints_orientations(yaw_error) -> None:
    """Camera 2's yaw off by an angle no quarter turn absorbs (a heading from the flight
    track): the orientations of a sample's brute-force matches give the rotation, and the
    pair is matched guided; without orientations it is not."""
    pose1, pose2, f1, f2, truth = _scene(seed=6)
    o1, o2 = _with_orientations(pose1, pose2, f1, f2, truth, seed=6)
    rough2 = Pose(pose2.R_world_to_cam @ rot_z(yaw_error).T, pose2.center + [4.0, -3.0, 0.0])
    result = match_guided(CAM, pose1, o1, CAM, rough2, o2, 0.0, GuidedOptions())
    assert result.stats["mode"] == "guided-rotated"
    found = _pairs(result.matches)
    assert len(found & truth) >= 0.9 * len(truth)
    assert len(found - truth) <= 0.05 * len(found)
    assert result.stats["candidates_per_keypoint"] < 0.5 * len(f2)
    blind = match_guided(CAM, pose1, f1, CAM, rough2, f2, 0.0, GuidedOptions())
    assert blind.stats["mode"] == "pose-mismatch-unmatched"


def test_a_wrong_pose_is_matched_by_brute_force_or_not_at_all() -> None:
    pose1, pose2, f1, f2, _ = _scene(seed=4)
    turned = Pose(rot_z(180.0) @ pose2.R_world_to_cam, pose2.center)
    strict = GuidedOptions(try_turns=False, brute_force_on_mismatch=False)
    none = match_guided(CAM, pose1, f1, CAM, turned, f2, 0.0, strict)
    assert none.stats["mode"] == "pose-mismatch-unmatched"
    assert len(none.matches) == 0
    options = GuidedOptions(try_turns=False, brute_force_on_mismatch=True)
    rescued = match_guided(CAM, pose1, f1, CAM, turned, f2, 0.0, options)
    assert rescued.stats["mode"] == "pose-mismatch"
    np.testing.assert_array_equal(rescued.matches, match_brute_force(f1, f2, options).matches)
    # 40 m off along the strip, 35 deg off in yaw: no turn fits either
    wrong = Pose(rot_z(35.0) @ pose2.R_world_to_cam, pose2.center + [-40.0, 0.0, 0.0])
    lost = match_guided(CAM, pose1, f1, CAM, wrong, f2, 0.0, GuidedOptions())
    assert lost.stats["mode"] == "pose-mismatch-unmatched" and len(lost.matches) == 0


def test_a_known_turn_spares_the_search() -> None:
    pose1, pose2, f1, f2, truth = _scene(seed=4)
    turned = Pose(rot_z(180.0) @ pose2.R_world_to_cam, pose2.center)
    options = GuidedOptions(try_turns=False)
    result = match_guided(CAM, pose1, f1, CAM, turned, f2, 0.0, options, turns=(0, 180))
    assert result.stats["mode"] == "guided-turned" and result.stats["turn_deg"] == [0, 180]
    assert len(_pairs(result.matches) & truth) >= 0.93 * len(truth)


def test_the_predicted_overlap_is_the_footprints_shared_share() -> None:
    """Nadir, 100 m up, f = 900 px: the footprint is 133 m wide; 30 m east shares 77 %."""
    assert predicted_overlap(CAM, _pose(), CAM, _pose(), 0.0) == 1.0
    shared = predicted_overlap(CAM, _pose(), CAM, _pose(x=BASELINE), 0.0, steps=64)
    assert shared == pytest.approx(1 - 30 / 133.2, abs=0.02)
    assert predicted_overlap(CAM, _pose(), CAM, _pose(x=500.0), 0.0) == 0.0


def test_cameras_far_apart_do_not_overlap_and_give_no_matches() -> None:
    pose1, _, f1, f2, _ = _scene(seed=5)
    far = _pose(x=1000.0)
    result = match_guided(CAM, pose1, f1, CAM, far, f2, 0.0, GuidedOptions())
    assert result.stats["mode"] == "no-overlap"
    assert len(result.matches) == 0


def test_empty_images_give_no_matches() -> None:
    pose1, pose2, f1, _, _ = _scene(seed=6)
    empty = Features.from_raw(np.zeros((0, 2)), np.zeros((0, 128), np.uint8))
    assert len(match_guided(CAM, pose1, f1, CAM, pose2, empty, 0.0, GuidedOptions()).matches) == 0
    assert len(match_brute_force(empty, f1, GuidedOptions()).matches) == 0


def test_a_camera_looking_up_predicts_nothing() -> None:
    up = Pose(rotation_from_yaw_pitch_roll(0.0, 180.0, 0.0), np.array([0.0, 0.0, HEIGHT]))
    _, valid = predict_in_image2(CAM, up, np.array([[600.0, 450.0]]), CAM, _pose(), 0.0)
    assert not valid.any()
