"""The real-data evaluation's truth and split (benchmarks/real_reference.py, bench_real.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks import bench_real, real_reference
from tests.support.shared_data import BRIGHTON


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _two_views() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """F of two nadir-ish cameras 40 m above a rough ground, and exact correspondences."""
    rng = np.random.default_rng(7)
    k = np.array([[1500.0, 0.0, 1000.0], [0.0, 1500.0, 562.5], [0.0, 0.0, 1.0]])
    r1 = _rotation(np.array([0.1, 0.2, 1.0]), 0.05)
    r2 = _rotation(np.array([0.3, -0.1, 1.0]), 0.4)
    c1, c2 = np.array([0.0, 0.0, -40.0]), np.array([12.0, 3.0, -41.0])
    t1, t2 = -r1 @ c1, -r2 @ c2
    points = np.column_stack((rng.uniform(-15, 15, (200, 2)), rng.uniform(-3, 3, 200)))

    def project(r: np.ndarray, t: np.ndarray) -> np.ndarray:
        x = (points @ r.T + t) @ k.T
        return x[:, :2] / x[:, 2:]

    f = real_reference.fundamental_from_poses(k, r1, t1, k, r2, t2)
    return f, project(r1, t1), project(r2, t2)


def test_sampson_labels_exact_correspondences_true_and_shifted_ones_false() -> None:
    f, p1, p2 = _two_views()
    assert real_reference.label_matches(f, p1, p2, 0.01).all()
    # shifted 10 px across their epipolar lines in image 2: about 7 px of Sampson distance
    lines = np.column_stack((p1, np.ones(len(p1)))) @ f.T
    normal = lines[:, :2] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    shifted = p2 + 10.0 * normal
    assert not real_reference.label_matches(f, p1, shifted, 2.0).any()
    # shifted along them: still on the pose's geometry
    along = p2 + 10.0 * normal @ np.array([[0.0, 1.0], [-1.0, 0.0]])
    assert real_reference.label_matches(f, p1, along, 0.01).all()


def test_split_is_deterministic_symmetric_and_uses_both_halves() -> None:
    names = [f"DJI_00{n}.JPG" for n in range(18, 36)]
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]]
    halves = [bench_real.half_of(a, b) for a, b in pairs]
    assert halves == [bench_real.half_of(b, a) for a, b in pairs]
    assert 0.3 < halves.count("held-out") / len(pairs) < 0.7


@pytest.mark.skipif(
    not real_reference.REFERENCE_FILE.is_file(), reason="the reference is not committed"
)
def test_reference_file_poses_are_rotations() -> None:
    reference = real_reference.load_reference()
    assert reference.meta["registered"] == len(reference.poses) >= 2
    for r, _ in reference.poses.values():
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)


def test_quick_run_writes_reports(tmp_path: Path, sift_cache: Path) -> None:
    """bench_real --quick: five images at 1000 px, a few pairs of each half, every method (the
    SIFT database shared with bench_colmap's quick run)."""
    pytest.importorskip("pycolmap")
    argv = ["--quick", "--out", str(tmp_path), "--cache", str(sift_cache)]
    assert bench_real.main([*argv, "--images", str(BRIGHTON / "images")]) == 0
    doc = json.loads((tmp_path / "real.json").read_text())
    assert "held-out" in (tmp_path / "real.md").read_text()
    assert {r["half"] for r in doc["records"]} == {"held-out", "tune"}
    assert {r["method"] for r in doc["records"]} == set(bench_real.METHODS)
    labels = doc["sets"]["strict"]["labels"]
    assert sum(labels[h]["true"]["2.0"] for h in labels) > 0


def test_relaxed_share_is_fixed_by_the_names() -> None:
    pairs = [(f"IMG_{i:04d}.jpg", f"IMG_{j:04d}.jpg") for i in range(30) for j in range(i)]
    kept = [bench_real.sampled(a, b, 4) for a, b in pairs]
    assert kept == [bench_real.sampled(b, a, 4) for a, b in pairs]
    assert 0.15 < sum(kept) / len(kept) < 0.35
    assert all(bench_real.sampled(a, b, 1) for a, b in pairs)


def test_caliterra_is_held_out_entirely_and_has_its_reference() -> None:
    fixture = bench_real.FIXTURES["caliterra"]
    assert fixture.all_held_out and fixture.track_attitude and not fixture.turned
    assert fixture.reference.is_file()
    reference = real_reference.load_reference(fixture.reference)
    assert len(reference.poses) == 75 and not reference.unregistered
