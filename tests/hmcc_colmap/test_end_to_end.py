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
