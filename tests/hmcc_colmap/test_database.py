"""hmcc_colmap.database: COLMAP's cameras, pixels and pair storage in our conventions."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from hmcc_colmap import ColmapInputError
from hmcc_colmap.database import (
    ColmapDatabase,
    Geometry,
    camera_object,
    fundamental_to_colmap,
    read_snapshot,
    snapshot_keypoints,
    snapshot_orientations,
)

CASES = {
    "SIMPLE_PINHOLE": [1000.0, 320.5, 240.5],
    "PINHOLE": [1000.0, 1010.0, 320.5, 240.5],
    "SIMPLE_RADIAL": [1000.0, 320.5, 240.5, 0.05],
    "RADIAL": [1000.0, 320.5, 240.5, 0.05, -0.02],
    "OPENCV": [1000.0, 1010.0, 320.5, 240.5, 0.05, -0.02, 0.001, -0.0005],
}


@pytest.mark.parametrize("model", sorted(CASES))
def test_each_camera_model_projects_as_colmap_does_in_our_pixels(model: str) -> None:
    """Our camera object (OpenCV's model, pixel centre at 0) puts a ray on COLMAP's pixel
    minus 0.5, distortion included: the models and the pixel convention agree."""
    camera = pycolmap.Camera(model=model, width=640, height=480, params=CASES[model])
    doc = camera_object(camera)
    assert doc["cx"] == 320.0 and doc["cy"] == 240.0
    assert ("distortion" in doc) == (model not in ("SIMPLE_PINHOLE", "PINHOLE"))
    rays = np.random.default_rng(0).uniform(-0.3, 0.3, (50, 2))
    colmap_px = np.asarray(camera.img_from_cam(np.column_stack((rays, np.ones(len(rays))))))
    K = np.array([[doc["fx"], 0, doc["cx"]], [0, doc["fy"], doc["cy"]], [0, 0, 1]])
    dist = np.array([*doc.get("distortion", [0, 0, 0, 0]), 0.0])
    ours, _ = cv2.projectPoints(
        np.column_stack((rays, np.ones(len(rays)))), np.zeros(3), np.zeros(3), K, dist
    )
    np.testing.assert_allclose(ours.reshape(-1, 2), colmap_px - 0.5, atol=1e-6)


def test_another_camera_model_is_refused_by_name() -> None:
    camera = pycolmap.Camera(
        model="OPENCV_FISHEYE", width=640, height=480, params=[500, 500, 320, 240, 0, 0, 0, 0]
    )
    with pytest.raises(ColmapInputError, match="OPENCV_FISHEYE is not supported"):
        camera_object(camera)


def _two_images(path: Path) -> list[int]:
    db = pycolmap.Database.open(str(path))
    cam = db.write_camera(
        pycolmap.Camera(model="PINHOLE", width=100, height=80, params=[90, 90, 50, 40])
    )
    ids = [db.write_image(pycolmap.Image(name=n, camera_id=cam)) for n in ("a.jpg", "b.jpg")]
    shapes = np.array(
        [[0.5, 0.5, 2.0, 0.0, 0.0, 2.0], [10.5, 20.5, 0.0, -3.0, 3.0, 0.0]], np.float32
    )
    db.write_keypoints(ids[0], shapes)
    db.write_keypoints(ids[1], np.array([[1.5, 2.5], [30.5, 40.5], [5.5, 5.5]], np.float32))
    # stored from the larger id's side: COLMAP swaps it into (smaller, larger)
    db.write_matches(ids[1], ids[0], np.array([[2, 0], [1, 1]], np.uint32))
    db.close()
    return ids


def test_keypoints_move_to_our_pixel_centre_and_keep_their_shape(tmp_path: Path) -> None:
    ids = _two_images(tmp_path / "db.db")
    with ColmapDatabase(tmp_path / "db.db") as db:
        np.testing.assert_allclose(db.keypoints(ids[0]), [[0, 0], [10, 20]])
        np.testing.assert_allclose(
            db.keypoints(ids[0], with_shape=True), [[0, 0, 2, 0], [10, 20, 3, 90]], atol=1e-9
        )
        np.testing.assert_allclose(db.keypoints(ids[1]), [[1, 2], [30, 40], [5, 5]])
    read_only = dict(snapshot_keypoints(tmp_path / "db.db", ids))
    np.testing.assert_allclose(read_only[ids[0]], [[0, 0], [10, 20]])
    np.testing.assert_allclose(read_only[ids[1]], [[1, 2], [30, 40], [5, 5]])


def test_orientations_come_from_the_affine_shapes_or_are_unknown(tmp_path: Path) -> None:
    """COLMAP's affine shape (a11, a12, a21, a22): the frame's x axis (a11, a21) turned by
    atan2(a21, a11) in the image; two-column keypoints hold no orientation."""
    ids = _two_images(tmp_path / "db.db")
    angles = dict(snapshot_orientations(tmp_path / "db.db", ids))
    np.testing.assert_allclose(angles[ids[0]], [0.0, np.pi / 2], atol=1e-7)
    assert angles[ids[1]].shape == (3,) and np.isnan(angles[ids[1]]).all()


def test_pairs_are_read_in_colmaps_stored_order(tmp_path: Path) -> None:
    """A pair matched from image 2's side is stored as (1, 2) with its columns swapped: our
    matches index image 1's keypoints first."""
    ids = _two_images(tmp_path / "db.db")
    assert read_snapshot(tmp_path / "db.db").matched == [(ids[0], ids[1], 2)]
    with ColmapDatabase(tmp_path / "db.db") as db:
        np.testing.assert_array_equal(db.matches(ids[0], ids[1]), [[0, 2], [1, 1]])


def test_a_fundamental_matrix_goes_back_to_colmaps_pixels() -> None:
    rng = np.random.default_rng(1)
    F = rng.normal(size=(3, 3))
    u, s, vt = np.linalg.svd(F)
    F = u @ np.diag([s[0], s[1], 0.0]) @ vt
    x1 = np.column_stack((rng.uniform(0, 500, 20), rng.uniform(0, 400, 20), np.ones(20)))
    lines = x1 @ F.T  # epipolar lines in image 2 (ours)
    xs = rng.uniform(0, 500, 20)
    x2 = np.column_stack((xs, -(lines[:, 0] * xs + lines[:, 2]) / lines[:, 1], np.ones(20)))
    assert np.abs(np.sum(x2 * (x1 @ F.T), axis=1)).max() < 1e-6
    shift = np.array([0.5, 0.5, 0.0])
    Fc = fundamental_to_colmap(F)
    residual = np.sum((x2 + shift) * ((x1 + shift) @ Fc.T), axis=1)
    assert np.abs(residual).max() < 1e-6
    assert np.abs(np.sum((x2 + shift) * ((x1 + shift) @ F.T), axis=1)).max() > 1e-3


def test_geometries_are_written_whole_in_the_stored_order(tmp_path: Path) -> None:
    ids = _two_images(tmp_path / "db.db")
    F = np.arange(9.0).reshape(3, 3)
    with ColmapDatabase(tmp_path / "db.db") as db:
        db.write([Geometry(ids[0], ids[1], np.array([[0, 2], [1, 1]]), F)], overwrite=False)
        db.write([Geometry(ids[0], ids[1], np.zeros((0, 2)))], overwrite=False)  # kept
    assert read_snapshot(tmp_path / "db.db").verified == {(ids[0], ids[1])}
    db2 = pycolmap.Database.open(str(tmp_path / "db.db"))
    g = db2.read_two_view_geometry(ids[0], ids[1])
    assert g.config == pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
    np.testing.assert_array_equal(g.inlier_matches, [[0, 2], [1, 1]])
    np.testing.assert_allclose(g.F, fundamental_to_colmap(F))
    db2.close()
    with ColmapDatabase(tmp_path / "db.db") as db:
        db.write([Geometry(ids[0], ids[1], np.zeros((0, 2)))], overwrite=True)
    db2 = pycolmap.Database.open(str(tmp_path / "db.db"))
    g = db2.read_two_view_geometry(ids[0], ids[1])
    assert g.config == pycolmap.TwoViewGeometryConfiguration.DEGENERATE
    assert len(g.inlier_matches) == 0
    db2.close()
