"""Yaw corrections from pairs' matches: one pair's fit, and the images' solve."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hmcc.camera import Camera
from hmcc.guided import project_points
from hmcc.pose import Pose, rotation_from_yaw_pitch_roll
from hmcc.yaw import (
    PairYaws,
    fit_pair_yaws,
    solve_position_corrections,
    solve_yaw_corrections,
    yawed,
)

CAM = Camera(width=1600, height=1200, fx=1330.0, fy=1330.0, cx=799.5, cy=599.5)
HEIGHT = 62.0


def _fit(yaw1: float, yaw2: float) -> PairYaws:
    """A pair's fit of these yaws, its matches' means the same point seen from nadir points
    14 m apart."""
    return PairYaws(yaw1, yaw2, 14.0, 100, (7.0, 0.0), (-7.0, 0.0), (14.0, 0.0), 62.0)


def _angle_between(a: Pose, b: Pose) -> float:
    r = a.R_world_to_cam @ b.R_world_to_cam.T
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def _pair(yaw1: float, yaw2: float, offset_m: tuple[float, float] = (0.0, 0.0), seed: int = 0):
    """Two nadir cameras 20 m apart whose true yaws (clockwise from north) are 90 + yaw1 and
    90 + yaw2; the rough poses say 90 for both, camera 1's position ``offset_m`` off. The
    matches: ground points both see, 0.5 px of noise and 10 % wrong."""
    rng = np.random.default_rng(seed)
    world = np.column_stack(
        (rng.uniform(-40, 60, 3000), rng.uniform(-40, 40, 3000), np.zeros(3000))
    )
    true1 = Pose(rotation_from_yaw_pitch_roll(90 + yaw1, 0, 0), np.array([0.0, 0.0, HEIGHT]))
    true2 = Pose(rotation_from_yaw_pitch_roll(90 + yaw2, 0, 0), np.array([20.0, 3.0, HEIGHT]))
    p1, f1 = project_points(CAM, true1, world)
    p2, f2 = project_points(CAM, true2, world)
    seen = np.flatnonzero(f1 & f2 & CAM.in_frame(p1) & CAM.in_frame(p2))
    kp1 = p1[seen] + rng.normal(scale=0.5, size=(len(seen), 2))
    kp2 = p2[seen] + rng.normal(scale=0.5, size=(len(seen), 2))
    matches = np.column_stack((np.arange(len(seen)), np.arange(len(seen))))
    wrong = rng.choice(len(seen), len(seen) // 10, replace=False)
    matches[wrong, 1] = rng.permutation(matches[wrong, 1])
    rough1 = Pose(rotation_from_yaw_pitch_roll(90, 0, 0), true1.center + np.array([*offset_m, 0.0]))
    rough2 = Pose(rotation_from_yaw_pitch_roll(90, 0, 0), true2.center)
    return (true1, true2), (rough1, rough2), kp1, kp2, matches


@pytest.mark.parametrize(("yaw1", "yaw2"), [(37.0, -80.0), (-170.0, 5.0), (0.0, 0.0)])
def test_a_pairs_matches_give_both_cameras_yaw(yaw1: float, yaw2: float) -> None:
    """Exact positions: each rough pose turned by its fitted correction is the true one."""
    true, rough, kp1, kp2, matches = _pair(yaw1, yaw2)
    fit = fit_pair_yaws(CAM, rough[0], kp1, CAM, rough[1], kp2, matches, 0.0)
    assert fit is not None and fit.used >= 0.8 * len(matches)
    assert _angle_between(yawed(rough[0], fit.yaw1_deg), true[0]) < 0.3
    assert _angle_between(yawed(rough[1], fit.yaw2_deg), true[1]) < 0.3
    assert fit.baseline_m == pytest.approx(np.hypot(20, 3))


def test_a_position_error_moves_both_yaws_alike() -> None:
    """Camera 1 2 m off: the absolute corrections are off by about 2 / 20 rad, both alike;
    the relative one stays within a fraction of a degree."""
    true, rough, kp1, kp2, matches = _pair(25.0, -60.0, offset_m=(0.0, 2.0))
    fit = fit_pair_yaws(CAM, rough[0], kp1, CAM, rough[1], kp2, matches, 0.0)
    assert fit is not None
    relative = fit.yaw2_deg - fit.yaw1_deg
    assert relative == pytest.approx(-(-60.0 - 25.0), abs=0.3)  # clockwise yaw, CCW fix
    assert _angle_between(yawed(rough[0], fit.yaw1_deg), true[0]) < 8.0


def test_too_few_matches_or_no_baseline_give_no_fit() -> None:
    _, rough, kp1, kp2, matches = _pair(10.0, 10.0)
    assert fit_pair_yaws(CAM, rough[0], kp1, CAM, rough[1], kp2, matches[:5], 0.0) is None
    same = Pose(rough[0].R_world_to_cam, rough[1].center)
    assert fit_pair_yaws(CAM, same, kp1, CAM, rough[1], kp2, matches, 0.0) is None


def test_the_solve_keeps_the_relative_yaws_and_drops_a_wrong_pair() -> None:
    """A chain of six images, their true corrections anywhere: each pair's relative
    correction exact, its absolute ones 6 deg off at random; one pair's fit wrong by 40 deg.
    The solved corrections keep every relative one within a degree, and their common
    error is below the pairs' own."""
    rng = np.random.default_rng(3)
    true = rng.uniform(-180, 180, 6)
    fits = []
    for a in range(5):
        for b in (a + 1, a + 2):
            if b > 5:
                continue
            noise = rng.normal(scale=6.0)
            fits.append((a, b, _fit(true[a] + noise, true[b] + noise)))
    a, b, f = fits[3]
    fits[3] = (a, b, replace(f, yaw2_deg=f.yaw2_deg + 40.0))
    solved = solve_yaw_corrections(fits, position_error_m=1.5)
    assert sorted(solved) == list(range(6))
    error = np.array([(solved[i] - true[i] + 180) % 360 - 180 for i in range(6)])
    assert np.ptp(error) < 1.0
    assert abs(error.mean()) < 6.0
    assert solve_yaw_corrections([], 3.0) == {}


def _moved(pose: Pose, east: float, north: float) -> Pose:
    return Pose(pose.R_world_to_cam, pose.center + np.array([east, north, 0.0]))


@pytest.mark.parametrize(("yaw1", "yaw2"), [(0.0, 0.0), (30.0, -50.0)])
def test_a_pairs_fit_gives_the_difference_of_its_cameras_position_errors(
    yaw1: float, yaw2: float
) -> None:
    """Camera 1's position 8 m east and 5 m north of the truth, its yaw and camera 2's off:
    with the true yaw corrections, the fit's means give camera 2's correction less camera
    1's, (8, 5) m, within a few decimetres (0.5 px of noise on 62 m, 10 % wrong matches)."""
    true, rough, kp1, kp2, matches = _pair(yaw1, yaw2, offset_m=(8.0, 5.0))
    fit = fit_pair_yaws(CAM, rough[0], kp1, CAM, rough[1], kp2, matches, 0.0)
    assert fit is not None and fit.height_m == pytest.approx(HEIGHT)
    # the rough yaws are 90 clockwise, the true ones 90 + yaw: corrections -yaw (CCW)
    solved = solve_position_corrections([(1, 2, fit)], {1: -yaw1, 2: -yaw2})
    step = np.subtract(solved[2], solved[1])
    assert step == pytest.approx([8.0, 5.0], abs=0.3)
    assert np.add(solved[1], solved[2]) == pytest.approx([0.0, 0.0], abs=1e-9)  # mean kept


#: Two strips of four images (0-3 one way, 7-4 back beside them): each image paired with its
#: neighbours along the strip, across and diagonally across (3 to 5 pairs an image, as a
#: flight's anchors). A sparser set (a ladder: along and straight across only) has pairs no
#: solve can tell a wrong one from: an image in two pairs only, or two pairs that are the
#: only links between two halves.
_STRIP_PAIRS = (
    [(a, a + 1) for a in (0, 1, 2, 4, 5, 6)]
    + [(a, 7 - a) for a in range(4)]
    + [(a, 6 - a) for a in range(3)]
    + [(a, 8 - a) for a in range(1, 4)]
)


@pytest.mark.parametrize("wrong", range(len(_STRIP_PAIRS)))
def test_the_offsets_solve_recovers_each_images_error_and_drops_a_wrong_pair(wrong: int) -> None:
    """Two strips flown opposite ways, each position 6 m behind the camera along its track (a
    late fix) plus 2 m of noise; the pairs' steps exact but one (each in turn), 60 m off.
    The solved corrections are the errors' negatives up to their common mean, within
    centimetres; the wrong pair is dropped; an image in no pair gets none."""
    rng = np.random.default_rng(5)
    error = {
        i: np.array([-6.0 if i < 4 else 6.0, 0.0]) + rng.normal(scale=2.0, size=2) for i in range(8)
    }
    pairs = _STRIP_PAIRS
    fits = []
    for a, b in pairs:
        step = error[a] - error[b]  # e_b - e_a with e = -error
        fits.append(
            (a, b, PairYaws(0.0, 0.0, 14.0, 100, (step[0], step[1]), (0.0, 0.0), (0.0, 0.0), 62.0))
        )
    a, b, f = fits[wrong]
    fits[wrong] = (a, b, replace(f, mean1_m=(f.mean1_m[0] + 60.0, f.mean1_m[1])))
    solved = solve_position_corrections(fits + [(8, 9, fits[0][2])], {i: 0.0 for i in range(8)})
    assert sorted(solved) == list(range(8))
    mean = np.mean([error[i] for i in range(8)], axis=0)
    for i in range(8):
        assert solved[i] == pytest.approx(mean - error[i], abs=0.05)
    assert solve_position_corrections([], {}) == {}
