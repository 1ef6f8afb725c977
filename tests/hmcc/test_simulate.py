"""Tests of the UAV pair simulator (hmcc.simulate)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from hmcc.pose import rotation_from_yaw_pitch_roll
from hmcc.simulate import MOUNTINGS, SimulationOptions, simulate_pair

VIEW_PAIRS = [("V", "V"), ("V", "F"), ("B", "F"), ("L", "F")]
EXACT = dict(
    keypoint_noise_px=0.0,
    gnss_sigma_m=(0.0, 0.0),
    imu_sigma_deg=(0.0, 0.0, 0.0),
    platform_attitude_sigma_deg=0.0,
)


def _K(cam: dict) -> np.ndarray:
    return np.array([[cam["fx"], 0.0, cam["cx"]], [0.0, cam["fy"], cam["cy"]], [0.0, 0.0, 1.0]])


def _true(pair: dict) -> list[tuple[np.ndarray, np.ndarray]]:
    return [
        (np.array(p["R_world_to_cam"]), np.array(p["center"]))
        for p in pair["ground_truth"]["true_poses"]
    ]


def _fundamental(pair: dict) -> np.ndarray:
    (R1, C1), (R2, C2) = _true(pair)
    R, t = R2 @ R1.T, R2 @ (C1 - C2)
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    K1inv = np.linalg.inv(_K(pair["image1"]["camera"]))
    K2inv = np.linalg.inv(_K(pair["image2"]["camera"]))
    return K2inv.T @ tx @ R @ K1inv


def _matched_points(pair: dict) -> tuple[np.ndarray, np.ndarray]:
    m = np.array(pair["matches"])
    kp1, kp2 = np.array(pair["keypoints1"]), np.array(pair["keypoints2"])
    return kp1[m[:, 0], :2], kp2[m[:, 1], :2]


def _epipolar_distance(F: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Distance (px) of p2 to the epipolar line of p1 in image 2."""
    h1 = np.column_stack((p1, np.ones(len(p1))))
    h2 = np.column_stack((p2, np.ones(len(p2))))
    lines = h1 @ F.T
    return np.abs(np.einsum("ij,ij->i", h2, lines)) / np.hypot(lines[:, 0], lines[:, 1])


def _plain(obj: object) -> bool:
    if isinstance(obj, dict):
        return all(isinstance(k, str) and _plain(v) for k, v in obj.items())
    if isinstance(obj, list):
        return all(_plain(v) for v in obj)
    return type(obj) in (int, float, str, bool)


def test_deterministic_for_a_seed() -> None:
    opts = SimulationOptions(n_inliers=100, outlier_ratio=0.6)
    a, b = simulate_pair(opts, 11), simulate_pair(opts, 11)
    assert json.dumps(a) == json.dumps(b)
    assert simulate_pair(opts, 12)["keypoints1"] != a["keypoints1"]


@pytest.mark.parametrize("mode", ["uniform", "mismatch"])
@pytest.mark.parametrize(("n_in", "ratio"), [(400, 0.5), (100, 0.9), (37, 0.3), (50, 0.0)])
def test_counts_and_format(mode: str, n_in: int, ratio: float) -> None:
    pair = simulate_pair(
        SimulationOptions(n_inliers=n_in, outlier_ratio=ratio, outlier_mode=mode), 3
    )
    assert _plain(pair)
    json.dumps(pair)
    n_out = round(n_in * ratio / (1 - ratio))
    gt = pair["ground_truth"]
    assert len(pair["matches"]) == n_in + n_out
    assert len(pair["keypoints1"]) == len(pair["keypoints2"]) == n_in + n_out
    assert len(gt["inliers"]) == n_in
    assert gt["inliers"] == sorted(set(gt["inliers"]))
    assert abs(gt["outlier_ratio"] - ratio) <= 1.0 / (n_in + n_out)
    assert gt["outlier_ratio"] == pytest.approx(n_out / (n_in + n_out))
    m = np.array(pair["matches"])
    assert sorted(m[:, 0]) == list(range(n_in + n_out))  # every keypoint used exactly once
    assert sorted(m[:, 1]) == list(range(n_in + n_out))
    assert pair["plane"]["ground_z"] == round(gt["mean_ground_z"], 1)
    assert gt["views"] == ["V", "V"] and gt["seed"] == 3
    assert pair["image1"]["camera"] == {
        "width": 6000, "height": 4000, "fx": 4000.0, "fy": 4000.0, "cx": 2999.5, "cy": 1999.5
    }  # fmt: skip
    assert "mounting" not in pair["image1"]["pose"]


@pytest.mark.parametrize("views", VIEW_PAIRS)
@pytest.mark.parametrize("mode", ["uniform", "mismatch"])
def test_keypoints_inside_images(views: tuple[str, str], mode: str) -> None:
    pair = simulate_pair(SimulationOptions(views=views, outlier_ratio=0.8, outlier_mode=mode), 5)
    for k in (1, 2):
        cam = pair[f"image{k}"]["camera"]
        kp = np.array(pair[f"keypoints{k}"])
        assert np.all((kp[:, 0] >= 0) & (kp[:, 0] <= cam["width"] - 1))
        assert np.all((kp[:, 1] >= 0) & (kp[:, 1] <= cam["height"] - 1))
        assert np.all((kp[:, 2] > 0) & (kp[:, 3] >= 0) & (kp[:, 3] < 360))


@pytest.mark.parametrize("views", VIEW_PAIRS)
def test_exact_matches_satisfy_true_geometry(views: tuple[str, str]) -> None:
    pair = simulate_pair(SimulationOptions(views=views, **EXACT), 21)
    gt = pair["ground_truth"]
    p1, p2 = _matched_points(pair)
    inl = np.array(gt["inliers"])
    F = _fundamental(pair)
    assert np.max(_epipolar_distance(F, p1[inl], p2[inl])) < 1e-6
    # triangulate with the true poses and reproject: exact
    (R1, C1), (R2, C2) = _true(pair)
    P1 = _K(pair["image1"]["camera"]) @ np.column_stack((R1, -R1 @ C1))
    P2 = _K(pair["image2"]["camera"]) @ np.column_stack((R2, -R2 @ C2))
    Xh = cv2.triangulatePoints(P1, P2, p1[inl].T.copy(), p2[inl].T.copy())
    X = (Xh[:3] / Xh[3]).T
    for P, p in ((P1, p1[inl]), (P2, p2[inl])):
        x = np.column_stack((X, np.ones(len(X)))) @ P.T
        assert np.max(np.abs(x[:, :2] / x[:, 2:] - p)) < 1e-6
    assert np.mean(X[:, 2]) == pytest.approx(gt["mean_ground_z"], abs=1e-6)
    assert np.all((X[:, 2] > 50.0 - 15.0 - 1e-6) & (X[:, 2] < 50.0 + 15.0 + 30.0 + 1e-6))
    # without pose noise the rough pose in the pair is the true pose
    for k, (R, C) in enumerate(_true(pair), start=1):
        pose = pair[f"image{k}"]["pose"]
        att, mnt = pose["attitude"], pose.get("mounting", {"yaw": 0, "pitch": 0, "roll": 0})
        R_rough = rotation_from_yaw_pitch_roll(
            att["yaw"], att["pitch"], att["roll"], (mnt["yaw"], mnt["pitch"], mnt["roll"])
        )
        assert np.allclose(R_rough, R, atol=1e-12)
        assert np.allclose([pose["position"][a] for a in "xyz"], C, atol=1e-9)
        assert tuple(mnt.values()) == MOUNTINGS[views[k - 1]]


@pytest.mark.parametrize("views", VIEW_PAIRS)
@pytest.mark.parametrize("mode", ["uniform", "mismatch"])
def test_noisy_inliers_and_outliers_vs_epipolar_lines(views: tuple[str, str], mode: str) -> None:
    pair = simulate_pair(SimulationOptions(views=views, outlier_ratio=0.7, outlier_mode=mode), 8)
    p1, p2 = _matched_points(pair)
    is_in = np.zeros(len(p1), bool)
    is_in[pair["ground_truth"]["inliers"]] = True
    d = _epipolar_distance(_fundamental(pair), p1, p2)
    assert np.median(d[is_in]) < 1.0 and np.max(d[is_in]) < 6.0
    assert np.mean(d[~is_in] > 5.0) > 0.9
    assert np.min(d[~is_in]) > 1.0


def test_views_and_oblique_overlap() -> None:
    for views in [*VIEW_PAIRS, ("F", "V"), ("R", "L"), ("B", "V"), ("R", "F")]:
        pair = simulate_pair(SimulationOptions(views=views, n_inliers=400), 1)
        assert len(pair["ground_truth"]["inliers"]) == 400
        for k in (1, 2):
            mount = pair[f"image{k}"]["pose"].get("mounting")
            if views[k - 1] == "V":
                assert mount is None
            else:
                assert tuple(mount.values()) == MOUNTINGS[views[k - 1]]


def test_nadir_heading_zero_image_top_is_north() -> None:
    pair = simulate_pair(SimulationOptions(**EXACT), 0)
    (R, C), _ = _true(pair)
    K = _K(pair["image1"]["camera"])
    ground = C + np.array([[0.0, 10.0, -120.0], [10.0, 0.0, -120.0]])  # north, east of C
    x = (ground - C) @ R.T @ K.T
    px = x[:, :2] / x[:, 2:]
    assert px[0, 1] < K[1, 2] and px[0, 0] == pytest.approx(K[0, 2])  # north: above
    assert px[1, 0] > K[0, 2] and px[1, 1] == pytest.approx(K[1, 2])  # east: right


def test_keypoint_angles_and_sizes_follow_the_view_rotation() -> None:
    # nadir pair, second exposure heading east: image 2 is rotated by -90 deg (its top is east,
    # so north points left): angle2 - angle1 = 270 deg (mod 360), scale ~ 1
    opts = SimulationOptions(heading_deg=(0.0, 90.0), outlier_ratio=0.0, **EXACT)
    pair = simulate_pair(opts, 4)
    m = np.array(pair["matches"])
    kp1, kp2 = np.array(pair["keypoints1"])[m[:, 0]], np.array(pair["keypoints2"])[m[:, 1]]
    dang = np.mod(kp2[:, 3] - kp1[:, 3], 360.0)
    assert np.median(dang) == pytest.approx(270.0, abs=3.0)
    ratio = kp2[:, 2] / kp1[:, 2]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.1)
    assert np.all((kp1[:, 2] >= 2.0) & (kp1[:, 2] <= 20.0))


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("views", ("V", "X")),
        ("views", ("V",)),
        ("altitude_m", -1.0),
        ("altitude_m", 20.0),  # below relief + building height
        ("ground_height_m", float("nan")),
        ("relief_m", -1.0),
        ("building_fraction", 1.5),
        ("building_height_m", (30.0, 5.0)),
        ("heading_deg", (0.0,)),
        ("baseline_m", -5.0),
        ("forward_overlap", 1.0),
        ("width_px", 0),
        ("height_px", 12.5),
        ("focal_px", 0.0),
        ("n_inliers", 0),
        ("outlier_ratio", 1.0),
        ("outlier_ratio", -0.1),
        ("outlier_mode", "random"),
        ("keypoint_noise_px", -0.5),
        ("gnss_sigma_m", (1.0, -1.0)),
        ("imu_sigma_deg", (1.0, 1.0)),
        ("platform_attitude_sigma_deg", -1.0),
    ],
)
def test_invalid_options_name_the_field(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        SimulationOptions(**{field: value})


def test_lists_are_accepted_and_bad_seed_or_overlap_raise() -> None:
    opts = SimulationOptions(views=["V", "F"], heading_deg=[0, 0])  # type: ignore[arg-type]
    assert opts.views == ("V", "F") and hash(opts)
    with pytest.raises(ValueError, match="seed"):
        simulate_pair(opts, -1)
    with pytest.raises(ValueError, match="visible"):
        simulate_pair(SimulationOptions(baseline_m=2000.0), 0)
