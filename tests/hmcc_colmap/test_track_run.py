"""``hmcc colmap`` with estimated poses: images with a GPS position only get a nadir attitude
headed along the flight track (as ``hmcc pairs`` gives them), and ``--detect-mounting`` finds
the camera's turn about its optical axis that the poses miss."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pycolmap
import pytest

from hmcc_cli import main
from hmcc_colmap import ColmapRun, RunOptions
from tests.hmcc_colmap.dbs import db_from_pairs, pose_file, sim_pair
from tests.support.shared_data import SHARED

CALITERRA = SHARED / "fixtures" / "caliterra" / "images"


@pytest.fixture(scope="module")
def caliterra(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Six consecutive Caliterra images (EXIF GPS, no attitude), COLMAP's SIFT at 800 px,
    matched exhaustively, not verified."""
    root = tmp_path_factory.mktemp("caliterra")
    images = root / "images"
    images.mkdir()
    for path in sorted(CALITERRA.glob("*.jpg"))[:6]:
        shutil.copy(path, images / path.name)
    db = root / "raw.db"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = 800
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


def _run(db: Path, images: Path, tmp_path: Path, **options: Any) -> dict[str, Any]:
    copy = tmp_path / f"db{len(list(tmp_path.glob('db*')))}.db"
    shutil.copy(db, copy)
    return ColmapRun(copy, images=images, options=RunOptions(processes=0, **options)).run()


def test_gps_only_images_get_the_tracks_attitude_and_fewer_pairs_fall_back(
    caliterra: tuple[Path, Path], tmp_path: Path
) -> None:
    db, images = caliterra
    tracked = _run(db, images, tmp_path)
    plain = _run(db, images, tmp_path, track_attitude=False)
    names = sorted(p.name for p in images.iterdir())
    assert tracked["totals"]["images_attitude_estimated"] == len(names)
    assert plain["totals"]["images_attitude_estimated"] == 0
    for name in names:
        assert tracked["images"][name]["attitude"] == "estimated from the track"
        assert tracked["images"][name]["pose_issue"] is None
        assert plain["images"][name]["attitude"] is None
        assert plain["images"][name]["pose_issue"] is not None

    def fell_back(report: dict[str, Any]) -> int:
        return int(report["totals"]["fallback_pairs"] + report["totals"]["no_pose_pairs"])

    assert plain["totals"]["no_pose_pairs"] == plain["totals"]["pairs"] > 0
    assert fell_back(tracked) < fell_back(plain)


def _turned_pose_file(path: Path, pairs: list[dict[str, Any]], yaw: float) -> Path:
    """:func:`pose_file` with each pair's second camera's mounting yaw off by ``yaw`` deg."""
    pose_file(path, pairs)
    doc = json.loads(path.read_text())
    for name, pose in doc.items():
        assert "yaw" in pose["attitude"]
        if name.endswith("b.jpg"):
            mounting = pose.setdefault("mounting", {})
            mounting["yaw"] = mounting.get("yaw", 0.0) + yaw
    path.write_text(json.dumps(doc))
    return path


def test_most_pairs_falling_back_suggest_the_mounting_search_which_keeps_its_best_turn(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each pair's second camera turned by 180 deg about its optical axis: most pairs fall
    back and the run says so in one hint line; with --detect-mounting every turn is tried on
    the sample and the one kept is one under which most pairs verify without the fallback
    (one turn for the flight: it cannot undo a turn of half the images)."""
    pairs = [sim_pair(seed) for seed in range(1, 5)]
    db = tmp_path / "db.db"
    db_from_pairs(db, pairs)
    poses = _turned_pose_file(tmp_path / "p.json", pairs, 180.0)
    base = ["colmap", str(db), "--poses", str(poses), "--processes", "0", "--overwrite"]
    assert main([*base, "--report", str(tmp_path / "plain.json")]) == 0
    hints = [x for x in capsys.readouterr().err.splitlines() if "--detect-mounting" in x]
    assert len(hints) == 1
    plain = json.loads((tmp_path / "plain.json").read_text())
    assert plain["mounting"] is None and plain["mounting_hint"] == hints[0]
    assert plain["totals"]["fallback_pairs"] > len(pairs) / 2

    argv = [*base, "--detect-mounting", "--report", str(tmp_path / "found.json")]
    assert main(argv) == 0
    out, err = capsys.readouterr()
    found = json.loads((tmp_path / "found.json").read_text())
    mounting = found["mounting"]
    assert mounting["sample_pairs"] == len(pairs)
    tried = {t["yaw_deg"]: t["kept"] for t in mounting["tried"]}
    assert sorted(tried) == [0, 90, 180, 270]
    assert tried[mounting["yaw_deg"]] == max(tried.values())
    assert found["mounting_hint"] is None and "--detect-mounting" not in err
    assert f"mounting: {mounting['yaw_deg']} deg" in out


def test_a_mounting_as_given_is_kept_when_nothing_fits_better(tmp_path: Path) -> None:
    pairs = [sim_pair(seed) for seed in range(1, 3)]
    db = tmp_path / "db.db"
    db_from_pairs(db, pairs)
    report = ColmapRun(
        db,
        poses=pose_file(tmp_path / "p.json", pairs),
        options=RunOptions(processes=0, detect_mounting=True),
    ).run()
    assert report["mounting"]["yaw_deg"] == 0
    assert report["totals"]["fallback_pairs"] == 0
