"""``hmcc colmap`` with estimated poses: images with a GPS position only get a nadir attitude
headed along the flight track (as ``hmcc pairs`` gives them), and ``--detect-mounting`` finds
the camera's turn about its optical axis that the poses miss."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
import pytest

from hmcc.simulate_flight import FlightOptions, simulate_flight
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


def test_a_database_focal_far_from_the_exif_one_is_replaced_and_said(
    caliterra: tuple[Path, Path], tmp_path: Path
) -> None:
    # Caliterra's images are downscaled to 1600 px with the original's EXIF: COLMAP's prior
    # focal length (from the focal-plane resolution) is about 2.5x the EXIF one (1162 px)
    db, images = caliterra
    exif = _run(db, images, tmp_path)
    kept = _run(db, images, tmp_path, exif_focal=False)
    names = sorted(p.name for p in images.iterdir())
    assert exif["totals"]["images_focal_from_exif"] == len(names)
    assert kept["totals"]["images_focal_from_exif"] == 0
    for name in names:
        assert exif["images"][name]["focal_source"] == "exif"
        assert exif["images"][name]["focal_px"] == pytest.approx(1162, rel=0.02)
        assert kept["images"][name]["focal_source"] == "database"
        assert kept["images"][name]["focal_px"] > 2 * exif["images"][name]["focal_px"]


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


def _gps_only_flight(root: Path, turn: int, seed: int = 3) -> tuple[Path, Path]:
    """A simulated nadir flight (two strips flown north then south, :mod:`hmcc.simulate_flight`)
    as a COLMAP database and an ODM geo.txt of positions only (metres, no attitude), the images
    named in capture order. ``turn`` (0, 90 or 180 deg): every image turned so about the
    optical axis, as a camera mounted with the image top toward a wing (90) or the tail (180)
    gives them, where the track says the nose."""
    o = FlightOptions(
        strips=2,
        stations_per_strip=6,
        views=("V",),
        width_px=1200,
        height_px=800,
        focal_px=900.0,
        keypoints_per_image=600,
        pairs=40,
        outlier_ratio=0.3,
    )
    body = simulate_flight(o, seed).body
    db_path, geo = root / f"flight{turn}.db", root / f"geo{turn}.txt"
    width, height = (o.height_px, o.width_px) if turn == 90 else (o.width_px, o.height_px)
    db = pycolmap.Database.open(str(db_path))
    ids = {}
    try:
        camera = pycolmap.Camera(
            model="PINHOLE",
            width=width,
            height=height,
            params=[o.focal_px, o.focal_px, width / 2, height / 2],  # COLMAP's pixels
        )
        camera_id = db.write_camera(camera)
        for name, image in body["images"].items():
            u, v = np.asarray(image["keypoints"], dtype=np.float64).T
            if turn == 90:
                u, v = o.height_px - 1 - v, u
            elif turn == 180:
                u, v = o.width_px - 1 - u, o.height_px - 1 - v
            ids[name] = db.write_image(pycolmap.Image(name=name, camera_id=camera_id))
            db.write_keypoints(ids[name], (np.column_stack((u, v)) + 0.5).astype(np.float32))
        for pair in body["pairs"]:
            matches = np.asarray(pair["matches"], dtype=np.uint32)
            db.write_matches(ids[pair["image1"]], ids[pair["image2"]], matches)
    finally:
        db.close()
    lines = ["EPSG:32614"]  # a projected frame: metres east, north, up
    for name in sorted(body["images"]):
        p = body["images"][name]["pose"]["position"]
        lines.append(f"{name} {p['x']:.3f} {p['y']:.3f} {p['z']:.3f}")
    geo.write_text("\n".join(lines) + "\n")
    return db_path, geo


@pytest.mark.parametrize("turn", [0, 90, 180])
def test_the_turn_of_a_gps_only_flights_camera_is_found_from_the_motions(
    tmp_path: Path, turn: int
) -> None:
    """Positions only: the track gives every attitude (image top toward the direction of
    travel), and the run searches the camera's turn about its optical axis on its own, on
    those images, by the pairs whose rough motion (relative rotation and baseline direction)
    agrees with the verified one: a nadir camera's turn leaves the relative rotations as they
    were (so the method keeps the pairs under any turn) but not the baselines' directions in
    the cameras. The turn found undoes the camera's; the others fit no pair's motion."""
    db, geo = _gps_only_flight(tmp_path, turn)
    report = ColmapRun(db, poses=geo, options=RunOptions(processes=0)).run()
    totals = report["totals"]
    assert totals["images_attitude_estimated"] == 12
    mounting = report["mounting"]
    assert mounting is not None and mounting["images"] == "attitude estimated from the track"
    tried = {t["yaw_deg"]: t for t in mounting["tried"]}
    assert sorted(tried) == [0, 90, 180, 270] and mounting["sample_pairs"] >= 10
    found = mounting["yaw_deg"]
    assert found == (360 - turn) % 360 if turn != 90 else found in (90, 270)
    assert tried[found]["consistent"] >= mounting["sample_pairs"] / 2
    for yaw, t in tried.items():
        assert yaw == found or t["consistent"] < mounting["sample_pairs"] / 4
    assert totals["fallback_pairs"] <= 0.2 * totals["pairs"]
