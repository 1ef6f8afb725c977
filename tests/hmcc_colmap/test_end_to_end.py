"""From the real DJI images to a model: COLMAP's SIFT extraction and exhaustive matching
without verification, ``hmcc colmap`` here and through a running ``hmcc serve``, then
``pycolmap.incremental_mapping`` registers every image in one model.

A subset of the 18 Brighton Beach images, extracted at 2000 px as the issue and the benchmark
do (the fixtures' working frame), keeps this about a minute: the north-east ends of the three
strips, three images of strip 1 among them, whose pixels were
turned by 180 deg after capture (their DJI attitude tags no longer fit their pixels: the
report must say so, and they must register all the same). Then the same features unmatched:
``hmcc match --verify`` writes what ``hmcc match`` then ``hmcc colmap`` write, in one command.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from hmcc_cli import main
from tests.hmcc_colmap.dbs import geometry, rows
from tests.support.procs import running, service_env, start_api
from tests.support.shared_data import BRIGHTON

pytestmark = pytest.mark.procs  # the compute pool's children, hmcc serve

STRIP1 = ["DJI_0024.JPG", "DJI_0025.JPG", "DJI_0026.JPG"]
SUBSET = [
    "DJI_0021.JPG",
    "DJI_0022.JPG",
    "DJI_0023.JPG",
    *STRIP1,
    "DJI_0033.JPG",
    "DJI_0034.JPG",
    "DJI_0035.JPG",
]


@pytest.fixture(scope="module")
def raw(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The subset's images and their matched, unverified database (COLMAP's SIFT)."""
    root = tmp_path_factory.mktemp("colmap")
    images = root / "images"
    images.mkdir()
    for name in SUBSET:
        shutil.copy(BRIGHTON / "images" / name, images / name)
    db = root / "raw.db"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = 2000
    extraction.num_threads = 2
    pycolmap.extract_features(
        db,
        images,
        camera_mode=pycolmap.CameraMode.SINGLE,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    matching = pycolmap.FeatureMatchingOptions()
    matching.skip_geometric_verification = True
    matching.num_threads = 2
    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    return db, images


def _registered(db: Path, images: Path, out: Path) -> list[int]:
    """Registered images of each model incremental mapping makes."""
    out.mkdir()
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = 2
    models = pycolmap.incremental_mapping(db, images, out, options)
    return sorted((m.num_reg_images() for m in models.values()), reverse=True)


def test_here_and_through_the_service_then_every_image_registers(
    raw: tuple[Path, Path], tmp_path: Path
) -> None:
    source, images = raw
    here, served = tmp_path / "here.db", tmp_path / "served.db"
    shutil.copy(source, here)
    shutil.copy(source, served)
    report_path = tmp_path / "report.json"
    argv = ["colmap", str(here), "--images", str(images), "--report", str(report_path)]
    assert main([*argv, "--processes", "2"]) == 0
    api, url = start_api(service_env())
    with running(api):
        assert main(["colmap", str(served), "--images", str(images), "--url", url]) == 0

    # the same geometries whichever way the pairs went
    written = rows(here)
    assert written == rows(served) and len(written) == len(SUBSET) * (len(SUBSET) - 1) // 2
    for a, b in written:
        np.testing.assert_array_equal(
            geometry(here, a, b).inlier_matches, geometry(served, a, b).inlier_matches
        )

    report = json.loads(report_path.read_text())
    totals = report["totals"]
    assert totals["verified"] >= 2 * len(SUBSET) and totals["images_without_pose"] == 0
    for name, image in report["images"].items():
        assert image["pose_source"] == "image metadata (EXIF GPS, XMP: dji)"
        # strip 1's tags are 180 deg off its pixels: said; the others' fit
        assert image["pos_fits"] is (name not in STRIP1), (name, image)
    assert totals["images_pos_not_fitting"] == len(STRIP1)

    assert _registered(here, images, tmp_path / "sparse") == [len(SUBSET)]


def test_a_rerun_skips_what_is_verified(raw: tuple[Path, Path], tmp_path: Path) -> None:
    source, images = raw
    db = tmp_path / "db.db"
    shutil.copy(source, db)
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("DJI_0024.JPG DJI_0025.JPG\nDJI_0035.JPG DJI_0024.JPG\n")
    argv = ["colmap", str(db), "--images", str(images), "--processes", "0"]
    assert main([*argv, "--pairs", str(pairs)]) == 0
    assert len(rows(db)) == 2
    report = tmp_path / "again.json"
    assert main([*argv, "--report", str(report)]) == 0
    totals = json.loads(report.read_text())["totals"]
    assert totals["skipped_already_verified"] == 2
    assert len(rows(db)) == len(SUBSET) * (len(SUBSET) - 1) // 2


def test_match_and_verify_in_one_command_then_every_image_registers(
    raw: tuple[Path, Path], tmp_path: Path
) -> None:
    source, images = raw
    features = tmp_path / "features.db"  # COLMAP's SIFT, not matched
    shutil.copy(source, features)
    db = pycolmap.Database.open(str(features))
    db.clear_matches()
    db.clear_two_view_geometries()
    db.close()
    one, two = tmp_path / "one.db", tmp_path / "two.db"
    shutil.copy(features, one)
    shutil.copy(features, two)
    report_path = tmp_path / "report.json"
    argv = ["--images", str(images), "--processes", "2"]
    assert main(["match", str(one), *argv, "--verify", "--report", str(report_path)]) == 0
    assert main(["match", str(two), *argv]) == 0
    assert main(["colmap", str(two), "--images", str(images), "--processes", "0"]) == 0

    written = rows(one)
    assert written == rows(two)
    for a, b in written:
        np.testing.assert_array_equal(
            geometry(one, a, b).inlier_matches, geometry(two, a, b).inlier_matches
        )
    report = json.loads(report_path.read_text())
    assert report["totals"]["verified"] >= 2 * len(SUBSET)
    assert report["verification"]["totals"]["images_without_pose"] == 0
    for row in report["pairs"]:
        if row["matches"] >= 15:  # verified where it was matched: its inliers and time
            assert row["verify_ms"] > 0 and 0 <= row["inliers"] <= row["matches"], row
    assert _registered(one, images, tmp_path / "sparse") == [len(SUBSET)]


def test_the_rough_poses_predict_the_reconstructions_tracks(
    raw: tuple[Path, Path], tmp_path: Path
) -> None:
    """The prediction of :mod:`hmcc.guided` against a reconstruction no hmcc estimator made
    (COLMAP's own verification and mapping of the subset): for each pair of registered
    images outside strip 1 (whose tags are 180 deg off its pixels), each 3-D point seen in
    both: its observation in image 1, predicted in image 2 with the rough POS of the images'
    tags, lands within the pair's wide radius (the worst case of the POS errors), and the
    predictions of a pair are off alike (here by 15 to 280 px, but within a tenth of the wide
    radius of their median offset, where the first pass allows a quarter)."""
    from hmcc.guided import GuidedOptions, predict_in_image2, wide_radius_px
    from hmcc_colmap.capture import exif_focal_cameras
    from hmcc_colmap.database import PIXEL_OFFSET, read_snapshot
    from hmcc_colmap.guided_match import _cameras, _rough_poses, _task
    from hmcc_colmap.poses import takeoff_ground
    from hmcc_colmap.track import rough_sources

    source, images = raw
    db = tmp_path / "reference.db"
    shutil.copy(source, db)
    pycolmap.geometric_verification(db)
    (tmp_path / "sparse").mkdir()
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = 2
    models = pycolmap.incremental_mapping(db, images, tmp_path / "sparse", options)
    model = max(models.values(), key=lambda m: m.num_reg_images())

    snapshot = read_snapshot(db)
    ids = {info.name: info.image_id for info in snapshot.images}
    sources, _ = rough_sources(list(ids), None, images, track=True)
    rough, _ = _rough_poses(snapshot.images, sources)
    cameras, _ = exif_focal_cameras(snapshot.images, _cameras(snapshot.images), images)
    names = {image_id: name for name, image_id in ids.items()}
    ground = takeoff_ground({names[i]: float(r.position[2]) for i, r in rough.items()}, sources)
    assert ground is not None
    seen: dict[tuple[int, int], list[tuple[np.ndarray, np.ndarray]]] = {}
    for point in model.points3D.values():
        views = {}
        for element in point.track.elements:
            image = model.images[element.image_id]
            if image.name not in STRIP1:
                views[ids[image.name]] = np.asarray(image.points2D[element.point2D_idx].xy)
        for a in views:
            for b in views:
                if a < b:
                    seen.setdefault((a, b), []).append((views[a], views[b]))
    pairs = 0
    for (a, b), observed in seen.items():
        if len(observed) < 30:
            continue
        task = _task(a, b, cameras, rough, ground[0])
        assert task.pose1 is not None and task.pose2 is not None
        px1, px2 = (np.array([o[k] for o in observed]) - PIXEL_OFFSET for k in (0, 1))
        pred, valid = predict_in_image2(
            task.camera1, task.pose1, px1, task.camera2, task.pose2, task.z0
        )
        offsets = (px2 - pred)[valid]
        wide, _ = wide_radius_px(task.camera2, task.pose1, task.pose2, task.z0, GuidedOptions())
        assert valid.mean() > 0.99, (names[a], names[b])
        within = np.mean(np.hypot(*offsets.T) <= wide)
        # the POS errors move the predictions alike: about the median offset (the first
        # pass's shift), within a quarter of the wide radius (the first pass's cap)
        spread = np.hypot(*(offsets - np.median(offsets, axis=0)).T)
        assert within >= 0.99, (names[a], names[b], within)
        assert np.percentile(spread, 99) <= 0.25 * wide, (names[a], names[b], spread, wide)
        pairs += 1
    assert pairs >= 10
